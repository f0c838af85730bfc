"""`metarig rig` (run an experiment on the simulated rig) and `metarig recover FILE`."""

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("metarig.rig")


# plan field -> flag, where the flag is not the field name with dashes (kept for compatibility)
FLAG_NAMES = {"amplitude_m": "amplitude", "frequency_hz": "frequency", "real_time_factor": "rtf"}
# plan fields set by the experiment, not from the command line
NO_FLAG = ("clock_step_s",)


def plan_flags(p: argparse.ArgumentParser, plan_cls) -> None:
    """One flag per plan field, from its metadata (default, description, choices)."""
    for f in dataclasses.fields(plan_cls):
        if f.name in NO_FLAG:
            continue
        default = getattr(plan_cls(), f.name)
        flag = "--" + FLAG_NAMES.get(f.name, f.name).replace("_", "-")
        p.add_argument(flag, dest=f.name, type=type(default), default=default,
                       choices=f.metadata.get("choices"), help=f.metadata.get("description"))


def _parser() -> argparse.ArgumentParser:
    from ros_nodes.logic.sequence import ExperimentPlan

    p = argparse.ArgumentParser(
        prog="metarig rig", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Run one experiment on the simulated rig: pre-compress, settle, record, fire "
                    "the pulse, record, stop; writes a run folder with one MCAP recording.")
    p.add_argument("--out", type=Path, default=Path("runs/rig"), help="run folder")
    p.add_argument("--processes", action="store_true",
                   help="one process per node (default: all nodes in this process)")
    p.add_argument("--hardware", choices=("sim", "real"), default="sim",
                   help="simulated rig, or real devices (no driver exists in this project)")
    p.add_argument("--params", type=Path, default=None,
                   help="ROS 2 YAML parameter file applied to the nodes (node_name: "
                        "ros__parameters: ...)")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="none",
                   help="MCAP chunk compression")
    plan_flags(p, ExperimentPlan)
    return p


def _plan(args):
    from ros_nodes.logic.sequence import ExperimentPlan

    return ExperimentPlan(**{f.name: getattr(args, f.name)
                             for f in dataclasses.fields(ExperimentPlan) if f.name not in NO_FLAG})


def _node_params(plan, out: Path, params_file: Path | None,
                 compression: str = "none") -> dict[str, dict]:
    from ros_nodes import params as P
    from ros_nodes.logic.sequence import node_parameters
    from ros_nodes.registry import NODES

    node_params = node_parameters(plan, out)
    node_params["recorder"]["compression"] = compression
    for name in node_params:
        cls = NODES[name].config()
        if params_file is not None:
            node_params[name].update(P.load_yaml(params_file, name))
        values = {k: v for k, v in node_params[name].items() if k != "use_sim_time"}
        node_params[name].update(P.to_flat(P.from_flat(cls, values)))  # validated + resolved
    return node_params


def rig_main(argv: list[str] | None = None) -> int:
    """Run an experiment on the simulated rig and write a run folder (see --help)."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")
    if args.hardware == "real":
        print("metarig rig: no driver for real shaker/stage/camera hardware exists in this "
              "project; use the simulated rig (--hardware sim)", file=sys.stderr)
        return 2
    from ros_nodes.params import ConfigError

    try:
        plan = _plan(args)
        node_params = _node_params(plan, args.out.resolve(), args.params, args.compression)
    except (ValueError, ConfigError) as e:
        print(f"metarig rig: {e}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    stale = args.out / "recording.mcap"
    if stale.exists():
        stale.unlink()
    from ros_nodes.nodes._rig import run_rig

    return run_rig(plan, node_params, args.out.resolve(), processes=args.processes)


def sequencer_main(argv: list[str] | None = None) -> int:
    """`metarig-sequencer`: the sequencer with every node in its own process
    (= `metarig rig --processes`)."""
    return rig_main(["--processes", *(sys.argv[1:] if argv is None else argv)])


def recover_main(argv: list[str] | None = None) -> int:
    """Salvage an MCAP recording whose writer was killed into a new, valid file."""
    p = argparse.ArgumentParser(prog="metarig recover", description=recover_main.__doc__,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("file", type=Path, help="the damaged .mcap file")
    p.add_argument("-o", "--out", type=Path, default=None,
                   help="output file (default: FILE with .recovered.mcap)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from ros_nodes.logic.recorder import recover

    if not args.file.is_file():
        print(f"metarig recover: no such file: {args.file}", file=sys.stderr)
        return 2
    out = args.out or args.file.with_suffix(".recovered.mcap")
    if out.resolve() == args.file.resolve():
        print("metarig recover: the output must differ from the input", file=sys.stderr)
        return 2
    try:
        rep = recover(args.file, out)
    except ValueError as e:
        print(f"metarig recover: {e}", file=sys.stderr)
        return 2
    state = "file was complete" if rep.complete else f"stopped at damage ({rep.error})"
    log.info("recovered %d messages on %d channels into %s; %s", rep.messages, rep.channels,
             out, state)
    print(json.dumps(rep.as_dict()))
    return 0
