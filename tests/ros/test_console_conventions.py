"""Console scripts behave alike: ``--help`` exits 0, prints the description once and each
option's default; ``--quiet`` has one meaning; progress bars do not flood a log file."""

from __future__ import annotations

import argparse
import io
import sys

import pytest
from medc_training.console import QUIET_HELP, HelpFormatter, progress_bar


def _mains():
    from medc_bringup import demo, launcher, recorder
    from medc_lab.cli import reproduce
    from medc_training.cli import bench, clone, inspect, train

    return {"medc-train": train.main, "medc-clone": clone.main, "medc-reproduce": reproduce.main,
            "medc-inspect": inspect.main, "medc-launch": launcher.main, "medc-demo": demo.main,
            "medc-record": recorder.main, "medc-bench": bench.main}


@pytest.mark.parametrize("script", sorted(_mains()))
def test_help_exits_0_and_prints_the_description_once(script, capsys):
    main = _mains()[script]
    try:
        rc = main(["--help"])
    except SystemExit as exc:
        rc = exc.code
    assert rc in (0, None)
    text = capsys.readouterr().out
    assert text.startswith("usage: " + script)
    first = next(line for line in text.splitlines()[1:] if line.strip() and not line.startswith(" "))
    assert text.count(first) == 1, f"{script} --help prints {first!r} more than once"


def test_bench_help_names_each_benchmark_with_what_it_measures(capsys):
    from medc_training.cli import bench

    assert bench.main(["--help"]) == 0
    text = capsys.readouterr().out
    for name in ("env", "ros", "train"):
        line = next(line for line in text.splitlines() if line.startswith(f"  {name} "))
        assert len(line.split(None, 1)[1]) > 20, line  # a real summary, not an empty slot
    assert bench.main(["nonsense"]) == 2


def _option(parser: argparse.ArgumentParser, flag: str) -> argparse.Action:
    return next(a for a in parser._actions if flag in a.option_strings)


def test_quiet_means_the_same_everywhere():
    from medc_bringup import launcher, recorder
    from medc_training.cli import clone, train

    parsers = {"medc-train": train.build_parser(), "medc-clone": clone.build_parser(),
               "medc-record": recorder.build_parser(), "medc-launch": launcher.build_parser()}
    for name, parser in parsers.items():
        assert _option(parser, "--quiet").help == QUIET_HELP, name
    # Their --help shows the same text (medc-demo builds its parser in main()).
    import contextlib

    for main in (launcher.main, __import__("medc_bringup.demo", fromlist=["main"]).main):
        out = io.StringIO()
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
            main(["--help"])
        assert " ".join(QUIET_HELP.split()) in " ".join(out.getvalue().split())


def test_defaults_are_shown_unless_they_say_nothing():
    p = argparse.ArgumentParser(prog="x", formatter_class=HelpFormatter)
    p.add_argument("--steps", type=int, default=100, help="training steps")
    p.add_argument("--grid", type=int, help="grid side")
    p.add_argument("--quiet", action="store_true", help="quiet")
    p.add_argument("--out", default="demo-out", help="folder (default demo-out)")
    text = " ".join(p.format_help().split())
    assert "training steps (default: 100)" in text
    assert "grid side (default" not in text and "quiet (default" not in text
    assert text.count("default demo-out") == 1 and "(default: demo-out)" not in text


def test_a_progress_bar_into_a_file_does_not_redraw_every_update(monkeypatch):
    from tqdm import tqdm

    monkeypatch.delenv("MEDC_PROGRESS_INTERVAL", raising=False)
    log = io.StringIO()  # not a terminal
    with progress_bar(2000, file=log, unit="step") as bar:
        for _ in range(2000):
            bar.update(1)
    assert log.getvalue().count("\r") <= 3, log.getvalue()[:500]
    # What a plain bar does to the same file (the flood this avoids).
    flood = io.StringIO()
    with tqdm(total=2000, file=flood, mininterval=0, miniters=1) as bar:
        for _ in range(2000):
            bar.update(1)
    assert flood.getvalue().count("\r") > 100


def test_a_training_run_logged_to_a_file_redraws_its_bar_at_the_logs_pace(monkeypatch, tmp_path):
    """medc-train's and the demo's bar (runner.run_training) into a log file: 20 evaluations in a
    few seconds give the first and the final line, not a line per evaluation."""
    from medc_training.config import TrainConfig
    from medc_training.ppo import Trainer
    from medc_training.runner import run_training

    monkeypatch.delenv("MEDC_PROGRESS_INTERVAL", raising=False)
    log = io.StringIO()  # not a terminal
    monkeypatch.setattr(sys, "stderr", log)
    cfg = TrainConfig(agents=1, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32, epochs=1,
                      minibatches=2, eval_every=32, eval_episodes=4, eval_envs=4, total_steps=640, arch="mlp",
                      seed=3).validate()
    run_training(Trainer(cfg, []), cfg, tmp_path / "run", progress=True, tensorboard=False)
    assert (tmp_path / "run" / "metrics.csv").read_text().count("\n") == 22  # header + 21 evaluations
    assert log.getvalue().count("%|") <= 3, log.getvalue()[:1000]
    assert "640/640" in log.getvalue() and "ep_len=" in log.getvalue()  # the final line says it all


def test_demo_quiet_drops_the_step_lines(capsys):
    from medc_bringup.demo import Narrator

    Narrator(quiet=True).step("1. users register")
    Narrator(quiet=True).say("done")
    assert capsys.readouterr().out == ""
    loud = Narrator()
    loud.step("1. users register")
    loud.say("done")
    assert "users register" in capsys.readouterr().out
