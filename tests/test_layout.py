"""The repository layout of design.md section 2: valid ament_python packages, one-way imports.

Packages (docs/ros-reference.md, "Packages"): ``medc_common`` (topic contract and ROS plumbing) is what the
node packages share; ``medc_sim``, ``medc_agents`` and ``medc_registry`` are leaves that never
import each other; ``medc_bringup`` (launcher, demo, benches, gas report) may import them all and
nothing imports it. Every package.xml declares exactly what its package imports, and no module of
the house takes part in an import cycle (function-local imports included). In training/, the
research harness ``medc_lab`` imports the product ``medc_training``, never the reverse.
"""

from __future__ import annotations

import ast
import re
import sys
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
ROS_SRC = REPO_ROOT / "ros_ws" / "src"
TRAINING = REPO_ROOT / "training"

AMENT_PYTHON = sorted(p.name for p in ROS_SRC.iterdir() if (p / "setup.py").is_file())
#: Node packages that must not need one another (a UAV runs an agent without the simulator).
LEAVES = ("medc_sim", "medc_agents", "medc_registry")
SHARED = "medc_common"
BRINGUP = "medc_bringup"
#: Packages of this repository that a package may import (medc_interfaces: the messages).
HOUSE = {*AMENT_PYTHON, "medc_interfaces", "medc_training", "medc_lab"}
#: The Python packages of training/ (its pyproject.toml ships both): the product and the harness.
PRODUCT, HARNESS = "medc_training", "medc_lab"
TRAINING_PACKAGES = (PRODUCT, HARNESS)

#: rosdep keys of the third-party Python modules the ROS packages import.
ROSDEP_KEYS = {
    "numpy": "python3-numpy",
    "torch": "python3-torch",
    "yaml": "python3-yaml",
    "matplotlib": "python3-matplotlib",
    "web3": "python3-web3",
    "eth_abi": "python3-eth-abi",
    "eth_account": "python3-eth-account",
    "eth_utils": "python3-eth-utils",
    "httpx": "python3-httpx",
    "requests": "python3-requests",
    "mcap": "python3-mcap-pip",
    "foxglove": "python3-foxglove-sdk-pip",
}


def test_the_expected_packages_exist() -> None:
    assert set(AMENT_PYTHON) == {SHARED, *LEAVES, BRINGUP}


@pytest.mark.parametrize("pkg", AMENT_PYTHON)
def test_ament_python_package_is_valid(pkg: str) -> None:
    root = ROS_SRC / pkg
    tree = ET.parse(root / "package.xml").getroot()
    assert tree.tag == "package" and tree.get("format") == "3"
    assert tree.findtext("name") == pkg
    assert tree.find("export/build_type").text == "ament_python"
    assert (root / "resource" / pkg).is_file(), "ament index marker missing"
    assert (root / "setup.py").is_file() and (root / pkg / "__init__.py").is_file()
    assert (root / "setup.cfg").read_text().count(f"$base/lib/{pkg}") == 2, "setup.cfg script dirs"


# ---------------------------------------------------------------- modules and their imports
def _house_modules() -> dict[str, tuple[Path, bool]]:
    """Every module of the house: dotted name -> (file, is a package __init__)."""
    roots = [(TRAINING, TRAINING / pkg) for pkg in TRAINING_PACKAGES]
    roots += [(ROS_SRC / p, ROS_SRC / p / p) for p in AMENT_PYTHON]
    modules: dict[str, tuple[Path, bool]] = {}
    for base, package in roots:
        for path in sorted(package.rglob("*.py")):
            parts = list(path.relative_to(base).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            modules[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return modules


MODULES = _house_modules()


def _imports(path: Path, is_package: bool, module: str) -> Iterator[tuple[str, int]]:
    """``(absolute module name, line)`` of every import in ``path``, at any depth (function-local
    imports included); relative imports resolved against ``module``; for ``from M import N`` the
    submodule ``M.N`` when it is one of the house, else ``M``."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = parts[: len(parts) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if name == "__future__":
                continue
            for alias in node.names:
                sub = f"{name}.{alias.name}"
                yield (sub if sub in MODULES else name), node.lineno


def _house_target(name: str) -> str | None:
    """The house module an import of ``name`` runs (its longest prefix that is one), if any."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def _top_level_imports(pkg: str) -> dict[str, str]:
    """Top-level names the modules of ROS package ``pkg`` and its launch files (``launch/*.py``,
    installed with it) import (stdlib and itself left out), each with one place that imports it."""
    found: dict[str, str] = {}
    sources = [(path, is_package, module) for module, (path, is_package) in MODULES.items()
               if module.split(".")[0] == pkg]
    launch_files = sorted((ROS_SRC / pkg).glob("launch/*.py"))
    sources += [(path, False, f"{pkg}.launch.{path.name}") for path in launch_files]
    for path, is_package, module in sources:
        for name, line in _imports(path, is_package, module):
            top = name.split(".")[0]
            if top != pkg and top not in sys.stdlib_module_names:
                found.setdefault(top, f"{path.relative_to(REPO_ROOT)}:{line}")
    return found


def _is_ros_package(name: str) -> bool:
    return (name in ("rclpy", "ament_index_python", "launch", "launch_ros")
            or name.endswith(("_msgs", "_interfaces")) or name.startswith("medc_"))


def _exec_depends(pkg: str) -> list[str]:
    tree = ET.parse(ROS_SRC / pkg / "package.xml").getroot()
    return [e.text.strip() for e in tree.findall("exec_depend")]


@pytest.mark.parametrize("pkg", AMENT_PYTHON)
def test_package_xml_declares_exactly_what_the_package_imports(pkg: str) -> None:
    imported = _top_level_imports(pkg)
    unknown = sorted(n for n in imported if not _is_ros_package(n) and n not in ROSDEP_KEYS)
    assert not unknown, (
        f"{pkg} imports {unknown} ({', '.join(imported[n] for n in unknown)}): add its rosdep key to "
        "ROSDEP_KEYS here and an <exec_depend> to the package.xml"
    )
    needed = {n if _is_ros_package(n) else ROSDEP_KEYS[n]: where for n, where in imported.items()}
    declared = _exec_depends(pkg)
    assert len(declared) == len(set(declared)), f"{pkg}/package.xml declares a dependency twice"
    missing = sorted(set(needed) - set(declared))
    assert not missing, f"{pkg}/package.xml lacks <exec_depend> for " + ", ".join(
        f"{d} (imported at {needed[d]})" for d in missing)
    unused = sorted(set(declared) - set(needed))
    assert not unused, f"{pkg}/package.xml declares {unused}, which no module of {pkg} imports"


def _package_graph() -> dict[str, set[str]]:
    """House package -> the house packages its modules import."""
    return {pkg: {n for n in _top_level_imports(pkg) if n in HOUSE} for pkg in AMENT_PYTHON}


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a path ``[a, b, ..., a]``, or None (iterative DFS, sorted order)."""
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done
    for start in sorted(graph):
        if start in state:
            continue
        path, stack = [start], [iter(sorted(graph[start]))]
        state[start] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph.get(nxt, ()))))
    return None


def test_cycle_finder_reports_the_path() -> None:
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"a"}}) == ["a", "a"]


def test_package_graph_points_one_way() -> None:
    graph = _package_graph()
    cycle = _find_cycle(graph)
    assert cycle is None, "package import cycle: " + " -> ".join(cycle)
    for leaf in LEAVES:
        others = graph[leaf] & {*LEAVES, BRINGUP}
        assert not others, f"{leaf} imports {sorted(others)}: share it through {SHARED} instead"
    assert graph[SHARED] <= {"medc_interfaces"}, f"{SHARED} must need no other MEDC package"
    importers = sorted(p for p in AMENT_PYTHON if p != BRINGUP and BRINGUP in graph[p])
    assert not importers, f"{importers} import {BRINGUP}; nothing at run time may need it"


def _module_graph() -> dict[str, set[str]]:
    """House module -> the house modules it imports (function-local imports included)."""
    graph: dict[str, set[str]] = {}
    for module, (path, is_package) in MODULES.items():
        targets = {_house_target(name) for name, _ in _imports(path, is_package, module)}
        graph[module] = {t for t in targets if t is not None and t != module}
    return graph


def test_no_module_takes_part_in_an_import_cycle() -> None:
    cycle = _find_cycle(_module_graph())
    assert cycle is None, "import cycle (function-local imports count): " + " -> ".join(cycle)


def test_the_gas_report_is_an_offline_tool() -> None:
    """medc-gas-report measures the contracts; no other module (the CLI included) imports it."""
    importers = sorted(m for m, targets in _module_graph().items() if "medc_bringup.gas" in targets)
    assert importers == [], f"{importers} import the gas report"


def test_training_never_imports_ros_web3_or_nodes() -> None:
    forbidden = {"rclpy", "web3", "medc_interfaces", *AMENT_PYTHON}
    for module, (path, is_package) in MODULES.items():
        if module.split(".")[0] not in TRAINING_PACKAGES:
            continue
        bad = {name.split(".")[0] for name, _ in _imports(path, is_package, module)} & forbidden
        assert not bad, f"{path.relative_to(REPO_ROOT)} imports {sorted(bad)}"


def _importers_of(package: str, among: str) -> list[tuple[str, int, str]]:
    """``(module, line, imported name)`` of every import of ``package`` by a module of ``among``
    (function-local and relative imports included)."""
    return [(module, line, name) for module, (path, is_package) in MODULES.items()
            if module.split(".")[0] == among
            for name, line in _imports(path, is_package, module) if name.split(".")[0] == package]


def test_the_product_never_imports_the_harness() -> None:
    """The research harness (experiments, report, studies) depends on the product, not the reverse:
    whatever medc-train, the bundles and the nodes need lives in medc_training."""
    assert _importers_of(PRODUCT, HARNESS), "no harness module imports the product: is medc_lab there?"
    for owner in (PRODUCT, *AMENT_PYTHON):
        found = [f"{MODULES[m][0].relative_to(REPO_ROOT)}:{line} imports {name}"
                 for m, line, name in _importers_of(HARNESS, owner)]
        assert found == [], f"{owner} imports the research harness:\n" + "\n".join(found)


def test_the_harness_check_finds_a_function_local_relative_import(tmp_path, monkeypatch) -> None:
    fake = tmp_path / "fake.py"
    fake.write_text("def f():\n    from medc_lab import plan\n")
    monkeypatch.setitem(MODULES, "medc_training.fake", (fake, False))
    assert _importers_of(HARNESS, PRODUCT) == [("medc_training.fake", 2, "medc_lab.plan")]


# ---------------------------------------------------------------- console scripts
def _entry_points() -> Iterator[tuple[str, str, str, str]]:
    """``(declared in, group, name, "module:function")`` of every entry point of the house."""
    for pkg in AMENT_PYTHON:
        setup = ROS_SRC / pkg / "setup.py"
        for node in ast.walk(ast.parse(setup.read_text())):
            if isinstance(node, ast.keyword) and node.arg == "entry_points":
                for group, specs in ast.literal_eval(node.value).items():
                    for spec in specs:
                        name, _, target = (s.strip() for s in spec.partition("="))
                        yield pkg, group, name, target
    project = tomllib.loads((TRAINING / "pyproject.toml").read_text())["project"]
    specs = [("console_scripts", name, target) for name, target in project["scripts"].items()]
    specs += [(group, name, target) for group, entries in project["entry-points"].items()
              for name, target in entries.items()]
    for group, name, target in specs:
        # training/pyproject.toml ships the product and the harness: each owns its own scripts.
        top = target.split(".")[0]
        yield (top if top in TRAINING_PACKAGES else PRODUCT), group, name, target


def test_every_entry_point_names_a_function_of_its_own_package() -> None:
    seen: dict[tuple[str, str], str] = {}
    for owner, group, name, target in _entry_points():
        assert (group, name) not in seen, f"{group} {name} declared by {seen[(group, name)]} and {owner}"
        seen[(group, name)] = owner
        module, _, function = target.partition(":")
        assert module.split(".")[0] == owner, f"{name} ({target}) is not in {owner}, which declares it"
        assert module in MODULES, f"{name}: no module {module}"
        tree = ast.parse(MODULES[module][0].read_text())
        defined = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
        assert function in defined, f"{name}: {module} defines no function {function}"
    scripts = {name for group, name in seen if group == "console_scripts"}
    assert {"medc-launch", "medc-demo", "medc-gas-report", "medc-sim", "medc-agent", "medc-bridge",
            "medc-registry"} <= scripts
    assert seen[("medc_bench", "ros")] == BRINGUP


# ---------------------------------------------------------------- module names
#: Files that every package may have; they never name a module of their own.
COMMON_FILES = {"__init__.py", "__main__.py", "setup.py", "conftest.py"}


def _shared_module_names(roots: tuple[Path, ...], base: Path = REPO_ROOT) -> dict[str, list[str]]:
    """File name -> its paths (relative to ``base``), for every module file name found more than
    once under ``roots`` (tests and build folders left out)."""
    paths: dict[str, list[str]] = {}
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            parts = path.relative_to(root).parts
            if path.name in COMMON_FILES or {"tests", "build"} & set(parts):
                continue
            paths.setdefault(path.name, []).append(str(path.relative_to(base)))
    return {name: found for name, found in paths.items() if len(found) > 1}


def test_the_name_check_finds_two_modules_of_one_name(tmp_path) -> None:
    for module in ("a/x/cli.py", "b/cli.py", "a/__init__.py", "b/__init__.py", "b/tests/x.py", "a/x.py"):
        (tmp_path / module).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / module).write_text("")
    assert _shared_module_names((tmp_path,), tmp_path) == {"cli.py": ["a/x/cli.py", "b/cli.py"]}


def test_every_module_has_a_name_of_its_own() -> None:
    """No two modules of training/ or ros_ws/src share a file name: a name says which module it is
    without its package (a traceback, a grep, an editor's tab)."""
    shared = _shared_module_names((TRAINING, ROS_SRC))
    assert shared == {}, "\n".join(f"{name}: {', '.join(found)}" for name, found in shared.items())


# ---------------------------------------------------------------- one definition of each name
#: Source trees whose modules the checks below read (tests may compare names freely).
SOURCE_ROOTS = (*(TRAINING / pkg for pkg in TRAINING_PACKAGES), ROS_SRC, REPO_ROOT / "scripts")
ENVS = TRAINING / "medc_training" / "envs"


def _source_files() -> Iterator[Path]:
    for root in SOURCE_ROOTS:
        yield from sorted(root.rglob("*.py"))


def _scoped_nodes(tree: ast.AST) -> Iterator[tuple[str, ast.AST]]:
    """Every node of ``tree`` with the qualified name of the function or class around it."""
    def walk(node: ast.AST, scope: str) -> Iterator[tuple[str, ast.AST]]:
        for child in ast.iter_child_nodes(node):
            inner = scope
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                inner = f"{scope}.{child.name}" if scope else child.name
            yield inner, child
            yield from walk(child, inner)
    yield from walk(tree, "")


def test_applications_are_known_only_to_the_environments() -> None:
    """Outside ``envs/`` no source file names an application in quotes or asks whether it has a
    source estimate by name (``core_has_estimate``, ``HAS_ESTIMATE``): code asks the application's
    descriptor (``medc_training.envs.application``) and names one through
    ``medc_training.envs.names``."""
    from medc_training.envs.names import ENV_NAMES

    quoted = re.compile("|".join(rf"[\"']{name}[\"']" for name in ENV_NAMES))
    found = []
    for path in _source_files():
        if ENVS in path.parents:
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if quoted.search(line) or "core_has_estimate" in line or "HAS_ESTIMATE" in line:
                found.append(f"{path.relative_to(REPO_ROOT)}:{number}: {line.strip()}")
    assert found == [], "ask the application's descriptor instead:\n" + "\n".join(found)


def _assignments(name: str) -> list[tuple[str, ast.AST]]:
    out = []
    for path in [*_source_files(), *sorted((REPO_ROOT / "tests").rglob("*.py"))]:
        for node in ast.walk(ast.parse(path.read_text())):
            targets = (node.targets if isinstance(node, ast.Assign)
                       else [node.target] if isinstance(node, ast.AnnAssign) else [])
            if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                out.append((path.relative_to(REPO_ROOT).as_posix(), node.value))
    return out


def test_one_bundle_size_limit() -> None:
    """The loader, the agents and the registry share one ceiling: a bundle the bridge fetches and
    caches is one every agent accepts."""
    defined = _assignments("MAX_BUNDLE_BYTES")
    assert [where for where, _ in defined] == ["training/medc_training/untrusted.py"], defined
    content = _assignments("MAX_CONTENT_BYTES")
    assert [(where, ast.unparse(value)) for where, value in content] == [
        ("ros_ws/src/medc_registry/medc_registry/cid.py", "MAX_BUNDLE_BYTES")
    ]


def test_one_printable_text_filter() -> None:
    """Text from strangers is made printable by ``medc_training.untrusted.printable`` alone."""
    filters = sorted(path.relative_to(REPO_ROOT).as_posix() for path in _source_files()
                     if '<= "~"' in path.read_text() or "<= '~'" in path.read_text())
    assert filters == ["training/medc_training/untrusted.py"]


def test_the_contracts_declare_each_shared_error_and_constant_once():
    """Errors and constants both contracts use are declared once (contracts/src/MedcShared.sol);
    a contract may re-export a constant (``ONE = Fixed.ONE``) but not give it a value of its own,
    and no error is declared twice under one name."""
    import re

    sources = {p.name: p.read_text() for p in sorted((REPO_ROOT / "contracts" / "src").glob("*.sol"))}
    errors = [name for text in sources.values() for name in re.findall(r"^\s*error\s+(\w+)\s*\(", text, re.M)]
    assert sorted(n for n in set(errors) if errors.count(n) > 1) == []
    assert {"UnregisteredUser", "ReviewOutOfRange"} <= set(errors)
    for name in ("ONE", "INITIAL_REPUTATION"):
        valued = [file for file, text in sources.items()
                  if re.search(rf"\bconstant\s+{name}\s*=\s*[0-9]", text)]
        assert valued == ["MedcShared.sol"], (name, valued)


#: The most lines a class or a function (its decorators, docstring and body) of the house may take.
MAX_CLASS_LINES, MAX_FUNCTION_LINES = 250, 80


def _oversized(tree: ast.AST) -> Iterator[tuple[str, str, int]]:
    """(kind, qualified name, lines) of every class over MAX_CLASS_LINES and function over
    MAX_FUNCTION_LINES in ``tree`` (nested ones included)."""
    for scope, node in _scoped_nodes(tree):
        if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            lines = node.end_lineno - first + 1
            limit = MAX_CLASS_LINES if isinstance(node, ast.ClassDef) else MAX_FUNCTION_LINES
            if lines > limit:
                yield type(node).__name__, scope, lines


def test_the_size_check_finds_a_long_function():
    lines = [f"x{i} = {i}" for i in range(MAX_FUNCTION_LINES)]
    method = "class A:\n    def f(self):\n" + "".join(f"        {line}\n" for line in lines)
    assert list(_oversized(ast.parse(method))) == [("FunctionDef", "A.f", MAX_FUNCTION_LINES + 1)]
    function = "def g():\n" + "".join(f"    {line}\n" for line in lines[1:])
    assert list(_oversized(ast.parse(function))) == []


def test_no_class_over_250_and_no_function_over_80_lines():
    """Modules split by job: every class of training/, ros_ws/src and scripts/ fits in
    MAX_CLASS_LINES lines and every function in MAX_FUNCTION_LINES."""
    found = [f"{path.relative_to(REPO_ROOT)}: {kind} {name} has {lines} lines"
             for path in _source_files() for kind, name, lines in _oversized(ast.parse(path.read_text()))]
    assert found == [], "\n".join(found)


def test_every_committed_bundle_of_the_run_records_is_listed_with_its_hash():
    """docs/reproduction/WEIGHTS.sha256 lists every bundle the run records commit, with its SHA-256,
    so a verdict's weights can be checked (``sha256sum -c`` there) and none changes unnoticed."""
    import hashlib
    import subprocess

    folder = REPO_ROOT / "docs" / "reproduction"
    tracked = subprocess.run(["git", "-C", str(folder), "ls-files", "-z", "--", "*.safetensors"],
                             capture_output=True, check=True).stdout.decode().split("\0")
    tracked = sorted(p for p in tracked if p)
    listed = {}
    for line in (folder / "WEIGHTS.sha256").read_text().splitlines():
        digest, name = line.split(maxsplit=1)
        listed[name] = digest
    assert sorted(listed) == tracked, "docs/reproduction/WEIGHTS.sha256: regenerate it (CONTRIBUTING.md)"
    for name, digest in listed.items():
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest, name
