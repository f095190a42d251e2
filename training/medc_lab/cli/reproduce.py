"""`medc-reproduce`: the paper's experiments (Figs. 6-11) at a named scale, several seeds.

    medc-reproduce --scale cpu --seeds 4 --other-seeds 2 --out docs/reproduction
    medc-reproduce --scale cpu --only experts          # (re)train models/experts and models/team

Phases (``--only`` picks some; default all):

- ``experts``: trains the expert bundles the experiments use (models/experts/*.safetensors)
  and the shipped team (models/team/A3W2.safetensors) by DAgger cloning of the scripted
  oracle (medc_training.dagger, as ``medc-clone``). Existing DAgger bundles for the same grid
  and step limit are reused unless ``--retrain``.
- ``fig6``: MEDC with the free (A1W0), complex (A1W3) and combined experts vs MDRL-sparse on
  A3W2 and A3W3.
- ``fig7``: A3W2 with 5 proper / random / biased / malicious experts vs sparse.
- ``fig8``: MEDC (6 experts) vs FRL (8 users) vs RS vs IL on A3W2 and A3W3, with wall time.
- ``fig9``: 8 users of which 3 are faulty: MEDC vs FRL vs IL on A3W2.
- ``fig10``: fleet coordination and maze cleaning, MEDC vs FRL vs IL, truthful (Fig. 10) and
  with 3 faulty experts/users (Fig. 11).
- ``long``, ``long-other``: the supplementary longer runs (``--long-steps``).
- ``sweep``: the claims scale only (docs/reproduction/claims/SWEEP.md): MEDC with the six users'
  experts over area x R_E and over Q against MDRL-sparse, 3 seeds; any other scale plans nothing.
  ``--scale claims --seeds 3 --only sweep``.

Every run writes OUT/runs/<run>/seed<k>/ (metrics.csv, summary.json), which appears only
when the run has finished (it trains in a hidden .seed<k>.partial/ beside it); a finished run is
not run again and an unfinished one resumes from its checkpoint, so a killed reproduction picks
up where it stopped. "Finished" means finished with the same configuration: a run folder holding
another (say a different step count) is refused, naming the fields, unless ``--overwrite``.
The figures and OUT/report.md are written at the end from whatever runs exist. The runs go to a
local process pool (``--jobs``) or, with ``--ray``, to Ray: a local cluster, or with
``--ray HEAD:6379`` an existing one (docs/training.md). The experiments themselves are declared in
medc_lab.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from medc_training.engines import INTERRUPTED, add_engine_arguments, engine_from_args
from medc_training.runs import RunMismatch

from ..catalogue import BUDGETS, OTHER_APPS, PHASES
from ..plan import Plan
from ..report import build_report
from ..reproduction import record_command, reproduce


def main(argv: list[str] | None = None) -> int:
    from medc_training.console import HelpFormatter, epilog

    p = argparse.ArgumentParser(prog="medc-reproduce", description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter, epilog=epilog(__doc__))
    p.add_argument("--scale", choices=sorted(BUDGETS), default="cpu")
    p.add_argument("--seeds", type=int, default=4, help="seeds per target-localization run (default 4)")
    p.add_argument("--out", default="docs/reproduction")
    p.add_argument("--only", action="append", choices=(*PHASES, "report"),
                   help="phase(s) to run (repeatable; default all). 'report' only rebuilds report.md")
    p.add_argument("--models", default="models", help="where expert/team bundles live (default models/)")
    p.add_argument("--steps", type=int, help="override the training steps of each experiment run")
    p.add_argument("--expert-steps", type=int, help="override the training steps of each expert")
    p.add_argument("--team-steps", type=int, help="override the training steps of the shipped team")
    p.add_argument("--other-steps", type=int, help="override the training steps of fleet/maze runs")
    p.add_argument("--long-steps", type=int, help="training steps of the supplementary long runs")
    p.add_argument("--other-seeds", type=int, default=2, help="seeds for Figs. 10-11 (default 2)")
    p.add_argument("--retrain", action="store_true", help="retrain experts even if bundles exist")
    p.add_argument("--overwrite", action="store_true",
                   help="rerun and replace finished runs of another configuration (refused without it)")
    p.add_argument("--no-other-apps", action="store_true", help="skip fleet/maze experts and Figs. 10-11")
    p.add_argument("--app", action="append", choices=tuple(OTHER_APPS), default=None,
                   help="repeatable: plan the experts and runs of only this fleet/maze application "
                        "(default both); target localization is not affected")
    p.add_argument("--device", default="cpu",
                   help="torch device of every run: cpu or cuda (with cuda, --jobs 1, or --ray)")
    add_engine_arguments(p)
    args = p.parse_args(argv)
    if args.seeds < 1:
        p.error("--seeds must be >= 1")
    out, models = Path(args.out), Path(args.models)
    out.mkdir(parents=True, exist_ok=True)
    phases = args.only or list(PHASES)
    budget = {"steps": args.steps, "expert_steps": args.expert_steps, "team_steps": args.team_steps,
              "fleet_maze_steps": args.other_steps, "long_steps": args.long_steps}
    try:
        plan = Plan(args.scale, args.seeds, out, models, budget, args.other_seeds, device=args.device,
                    apps=args.app)
    except ValueError as exc:
        p.error(str(exc))
    try:
        engine = engine_from_args(args)
    except ValueError as exc:
        p.error(str(exc))
    command = "medc-reproduce " + " ".join(argv if argv is not None else sys.argv[1:])
    command = record_command(out, command, report_only=phases == ["report"])
    try:
        elapsed = reproduce(plan, phases, engine, retrain=args.retrain, other_apps=not args.no_other_apps,
                            overwrite=args.overwrite)
    except KeyboardInterrupt:
        print(f"medc-reproduce: interrupted; {INTERRUPTED}", file=sys.stderr)
        return 130
    except RunMismatch as exc:
        print(f"medc-reproduce: error: {exc}", file=sys.stderr)
        return 2
    path = build_report(out, args.scale, args.seeds, command, plan, elapsed)
    print(f"report: {path}")
    print(json.dumps({"report": str(path), "elapsed_s": elapsed}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
