"""`metarig loop TASK --out DIR`: design, test on the rig, calibrate, redesign; round by round.

Round k (`DIR/round-k/`): the design (round 1: optimised for TASK, or `--design FILE`; later
rounds: optimised from the round before's design with the material calibrated in that round),
its experiment on the simulated rig (`metarig rig`, with the discrepant specimen; rig flags
after `--`, the same in every round), the task's objective measured from the tracked poses and
predicted by the round's model, an identification experiment on the same specimen, and the
material calibrated from it (`metarig calibrate`). Finished steps are
kept: a second invocation resumes. Writes `DIR/loop.json` (per round: design, model and
calibrated material with their stated errors, predicted and measured objective) and
`DIR/loop.rrd` (the rounds side by side in Rerun). See `ros_nodes.logic.closed_loop`.
"""

import argparse
import logging
import sys
from pathlib import Path

from metarig.argtypes import grid_size, non_negative, positive, text


def build_parser() -> argparse.ArgumentParser:
    from ros_nodes.logic.closed_loop import IDENTIFY_CHOICES

    p = argparse.ArgumentParser(
        prog="metarig loop", description=loop_main.__doc__,
        epilog="Flags after `--` go to `metarig rig` in every round, e.g. `-- --perturb 0.2 "
               "--seed 576 --specimen-thickness-error -0.05` (see `metarig rig --help`).")
    p.add_argument("task", help="task preset name or task file (.toml), as `metarig design`")
    p.add_argument("--out", type=Path, required=True, help="the loop's folder (resumed if it "
                   "holds finished steps)")
    p.add_argument("--rounds", type=positive(int), default=2, help="design-test-calibrate "
                   "rounds (default 2)")
    p.add_argument("--design", type=Path, default=None, help="round 1 tests this design file "
                   "(metarig-design/1) instead of optimising one")
    p.add_argument("--material", type=Path, default=None, help="nominal material file of round "
                   "1's model (default: the default material); the rig's sample keeps its own")
    p.add_argument("--size", type=grid_size, default=None, help="lattice size NXxNY (default "
                   "the task's)")
    p.add_argument("--max-evals", type=positive(int), default=None, help="design budget of "
                   "each round, evaluations (default the task's)")
    p.add_argument("--fit", type=text("--fit"), default=None, help="parameters the calibration "
                   "fits (as `metarig calibrate --fit`; default its own)")
    p.add_argument("--workers", type=positive(int), default=None, help="tracker processes "
                   "(default: all cores)")
    p.add_argument("--identify", choices=IDENTIFY_CHOICES, default=IDENTIFY_CHOICES[0], help="what the "
                   "calibration fits: an identification experiment on the same specimen (a 1 mm "
                   "pulse at 100 Hz, 150 ms capture; default) or the task's own experiment")
    p.add_argument("--no-warm-start", dest="warm_start", action="store_false", help="every "
                   "round designs from round 1's start (default: round k from round k-1's "
                   "design)")
    p.add_argument("--design-seed", type=non_negative(int), default=None, help="round 1 "
                   "designs from the task's periodic design plus the random perturbation drawn "
                   "with this seed (`metarig design --seed`; default: the task's initial design)")
    return p


def loop_main(argv: list[str] | None = None) -> int:
    """Close the loop: design, test on the rig, calibrate, redesign with what was measured."""
    argv = sys.argv[1:] if argv is None else list(argv)
    rig_args: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, rig_args = argv[:cut], argv[cut + 1:]
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger("metarig.loop").setLevel(logging.INFO)
    from ros_nodes.logic.closed_loop import LoopError, LoopPlan, run_loop

    plan = LoopPlan(task=args.task, out=args.out, rounds=args.rounds, design=args.design,
                    material=args.material, size=args.size, max_evals=args.max_evals,
                    rig_args=tuple(rig_args), fit=args.fit, workers=args.workers,
                    identify=args.identify, warm_start=args.warm_start,
                    design_seed=args.design_seed)
    try:
        doc = run_loop(plan)
    except LoopError as exc:
        print(f"metarig loop: error: {exc}", file=sys.stderr)
        return 2
    print(f"\nmetarig loop: {doc['task']} on {doc['lattice'][0]}x{doc['lattice'][1]} units -> "
          f"{doc['out']}")
    print(f"{'round':>5}  {'design J':>11}  {'predicted J':>11}  {'measured J':>11}  "
          "measured/predicted")
    for r in doc["rounds"]:
        d = r["design_objective_J"]
        print(f"{r['round']:>5}  {d if d is not None else float('nan'):>11.4g}  "
              f"{r['predicted_objective_J']:>11.4g}  {r['measured_objective_J']:>11.4g}  "
              f"{r['measured_over_predicted']:.3f}")
    print(f"wrote {args.out}/loop.json; open the rounds side by side with: rerun "
          f"{args.out}/loop.rrd")
    return 0


if __name__ == "__main__":
    raise SystemExit(loop_main())
