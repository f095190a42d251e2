"""The defaults the docs state are the code's: docs/ros-reference.md's node parameters (read from
the nodes' declarations, as their ``--help`` is: medc_common.cli_help), docs/ros-guide.md's launch
config table (the shipped launch.yaml and medc_bringup.launcher), the defaults both ROS pages state
in their prose, and docs/training.md's medc-controllers scenario (its argument parser). A doc that
restates a default the code does not have fails here."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
ROS_GUIDE_MD = ROOT / "docs" / "ros-guide.md"
ROS_REFERENCE_MD = ROOT / "docs" / "ros-reference.md"
TRAINING_MD = ROOT / "docs" / "training.md"

#: `name` (VALUE ...) or `name` (default **VALUE ...): VALUE a number, true/false, "empty" or `text`.
STATED = re.compile(r"`(?P<name>[a-z_]+)` \((?:default )?(?:\*\*)?"
                    r"(?P<value>`[^`]*`|-?\d+(?:\.\d+)?(?![\w.])|true\b|false\b|empty\b)")


def _value(text: str) -> object:
    if text.startswith("`"):
        return text.strip("`")
    if text in ("true", "false"):
        return text == "true"
    if text == "empty":
        return ""
    return float(text)


def _same(doc: object, code: object) -> bool:
    if isinstance(code, bool) or isinstance(doc, bool):
        return doc is code
    if isinstance(code, (int, float)):
        return isinstance(doc, float) and doc == float(code)
    return doc == code


def stated_defaults(text: str) -> dict[str, list[object]]:
    """Every default ``text`` states, per parameter name (a name may be stated more than once)."""
    out: dict[str, list[object]] = {}
    for m in STATED.finditer(text.replace("\n", " ")):
        out.setdefault(m["name"], []).append(_value(m["value"]))
    return out


def ros_docs_text() -> str:
    """The two ROS pages, the guide then the reference: where the docs state the graph's defaults."""
    return ROS_GUIDE_MD.read_text() + "\n\n" + ROS_REFERENCE_MD.read_text()


def paragraph(text: str, head: str) -> str:
    """The paragraph of ``text`` that starts with ``head``."""
    start = text.index(head)
    end = text.find("\n\n", start)
    return text[start:end if end >= 0 else len(text)]


def node_defaults(*modules: str) -> dict[str, object]:
    """The defaults the node modules declare (what ``medc-sim --help`` / ``medc-agent --help`` print)."""
    import ast

    from medc_common.cli_help import declared_parameters

    out = {}
    for name, default, _ in declared_parameters(*modules):
        try:
            out[name] = ast.literal_eval(default)
        except ValueError:
            out[name] = default  # an expression (e.g. wait_for_subscribers = agents): not a literal
    return out


NODES = {
    "**`medc-sim`**": ("medc_sim.simulator",),
    "**`medc-agent`**": ("medc_agents.node", "medc_agents.estimate"),
}


@pytest.mark.parametrize("head", list(NODES))
def test_the_node_paragraphs_name_every_parameter_with_the_declared_defaults(head):
    text = paragraph(ROS_REFERENCE_MD.read_text(), head)
    code = node_defaults(*NODES[head])
    named = set(re.findall(r"`([a-z_]+)`", text))
    assert set(code) <= named, f"{head} does not name {sorted(set(code) - named)}"
    stated = stated_defaults(text)
    checked = {name: values for name, values in stated.items() if name in code}
    assert len(checked) >= 12, checked  # the parser reads the paragraph
    wrong = {name: (values, code[name]) for name, values in checked.items()
             if not all(_same(v, code[name]) for v in values)}
    assert not wrong, f"{head}: doc default vs code: {wrong}"


def test_defaults_stated_in_the_prose_of_the_ros_docs_are_the_nodes():
    """`lost_timeout_s` (default **1.5 s**) in "A lost UAV" and the like: a parameter whose default
    is the same on every node that declares it is checked wherever docs/ros-guide.md or
    docs/ros-reference.md states it so."""
    declared: dict[str, list[object]] = {}
    for modules in NODES.values():
        for name, value in node_defaults(*modules).items():
            declared.setdefault(name, []).append(value)
    unique = {name: values[0] for name, values in declared.items() if all(v == values[0] for v in values)}
    bold = re.compile(r"`(?P<name>[a-z_]+)` \(default \*\*(?P<value>-?\d+(?:\.\d+)?)")
    stated = [(m["name"], float(m["value"])) for m in bold.finditer(ros_docs_text().replace("\n", " "))]
    assert {"move_timeout_s", "lost_timeout_s", "stall_timeout_s"} <= {name for name, _ in stated}
    wrong = [(name, value, unique[name]) for name, value in stated if not _same(value, unique[name])]
    assert not wrong, f"docs/ros-guide.md or docs/ros-reference.md default vs code: {wrong}"


def _table(text: str, heading: str) -> dict[str, str]:
    """Key -> default column of the markdown table under ``heading``."""
    section = text[text.index(heading):]
    rows = {}
    for line in section.splitlines()[1:]:
        if line.startswith("#"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not cells[0].startswith("`"):
            continue
        keys = re.findall(r"`([a-z_]+)`", cells[0])
        values = [cells[1]] * len(keys)
        if len(keys) > 1 and cells[1].count(", ") == len(keys) - 1:
            values = cells[1].split(", ")
        for key, value in zip(keys, values, strict=True):
            rows[key] = value.strip("`")
    return rows


def test_the_launch_config_table_is_the_shipped_launch_yaml():
    from medc_bringup.launcher import DEFAULT_CONFIG

    shipped = yaml.safe_load(Path(DEFAULT_CONFIG).read_text())
    rows = _table(ROS_GUIDE_MD.read_text(), "### Launch config")
    assert set(rows) == set(shipped), set(rows) ^ set(shipped)
    wrong = {key: (rows[key], shipped[key]) for key in rows if yaml.safe_load(rows[key]) != shipped[key]}
    assert not wrong, f"docs/ros-guide.md launch config table vs launch.yaml: {wrong}"


def test_the_scenario_defaults_the_docs_state_are_the_launchers():
    from medc_bringup import launcher

    text = ros_docs_text()
    row = next(line for line in text.splitlines() if line.startswith("| `agents`, `walls`, `grid`"))
    keys = ("agents", "walls", "grid", "max_steps")
    found = re.search(r"else (\d+), (\d+), (\d+), (\d+)", row)
    scenario = lambda m: dict(zip(keys, map(int, m.groups()), strict=True))  # noqa: E731
    assert found and scenario(found) == launcher.SCENARIO_DEFAULTS, row
    found = re.search(r"classical controller[^:]*: (\d+), (\d+), (\d+), (\d+)", row)
    assert found and scenario(found) == launcher.CONTROLLER_DEFAULTS, row
    # "the controller scenario (3 agents, 2 walls, 20×20, 100 steps, `realistic`...)"
    stated = re.findall(r"controller scenario \((\d+) agents, (\d+) walls, (\d+)×\d+, (\d+) steps,"
                        r"\s+`([a-z-]+)`", text)
    assert stated
    for *numbers, sensing in stated:
        assert dict(zip(keys, map(int, numbers), strict=True)) == launcher.CONTROLLER_DEFAULTS
        assert sensing == launcher.CONTROLLER_SENSING
    # "20×20 realistic", wherever the docs name the controller scenario in short.
    grid = launcher.CONTROLLER_DEFAULTS["grid"]
    for short in re.findall(r"controller scenario, (\d+)×(\d+) ([a-z-]+)", text):
        assert short == (str(grid), str(grid), launcher.CONTROLLER_SENSING), short
    # A config file that leaves `policy` out: the dataclass's default, which the table names.
    policy_row = next(line for line in text.splitlines() if line.startswith("| `policy` |"))
    assert f"leaves the key out runs `{launcher.LaunchConfig.policy}`" in policy_row


def _parser_of(main, monkeypatch) -> argparse.ArgumentParser:
    """The ArgumentParser ``main`` builds, caught at its parse_args (nothing runs)."""
    caught = {}

    class Caught(Exception):
        pass

    def catch(self, *args, **kwargs):
        caught["parser"] = self
        raise Caught

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", catch)
    with pytest.raises(Caught):
        main([])
    return caught["parser"]


def test_training_md_states_medc_controllers_defaults(monkeypatch):
    from medc_training.cli import play_controllers

    defaults = {a.dest: a.default for a in _parser_of(play_controllers.main, monkeypatch)._actions}
    text = TRAINING_MD.read_text()
    example = re.search(r"medc-controllers +# every controller on ([a-z-]+) (\d+)x(\d+), walls (\d+)", text)
    assert example, "the medc-controllers example line"
    assert (example[1], int(example[2]), int(example[4])) == (defaults["sensing"], defaults["grid"],
                                                              defaults["walls"])
    table = re.search(r"(\w+) sensing, (\d+)x\d+, walls (\d+), (\d+) agents, (\d+) steps, "
                      r"(\d+) environments, seed (\d+)", text.replace("\n", " "))
    assert table, "the medc-controllers table's scenario"
    assert (table[1].lower(), *map(int, table.groups()[1:])) == (
        defaults["sensing"], defaults["grid"], defaults["walls"], defaults["agents"], defaults["max_steps"],
        defaults["num_envs"], defaults["seed"])


def _slug(heading: str) -> str:
    """GitHub's anchor for a markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


@pytest.mark.parametrize("page", ["README.md", "CONTRIBUTING.md", "CHANGELOG.md", "docs/ros.md",
                                  "docs/ros-guide.md", "docs/ros-reference.md", "docs/training.md",
                                  "docs/bundles.md", "docs/environments.md", "docs/radbench.md"])
def test_links_between_the_pages_land_on_a_file_and_heading(page):
    """docs/ros.md maps the sections that links name to the guide and the reference: every link of
    these pages to a markdown page names a file that exists and, with an anchor, one of its headings."""
    source = ROOT / page
    text = re.sub(r"```.*?```", "", source.read_text(), flags=re.S)
    broken = []
    for target, anchor in re.findall(r"\]\(([^)\s#]*\.md|)(?:#([^)\s]+))?\)", text):
        path = (source.parent / target).resolve() if target else source
        if not path.is_file():
            broken.append(f"{target}: no such file")
            continue
        if anchor:
            headings = re.findall(r"^#+ (.+)$", re.sub(r"```.*?```", "", path.read_text(), flags=re.S),
                                  flags=re.M)
            if anchor not in {_slug(h) for h in headings}:
                broken.append(f"{target}#{anchor}: no such heading")
    assert not broken, f"{page}: {broken}"
