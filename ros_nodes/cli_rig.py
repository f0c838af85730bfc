"""`metarig rig` (run an experiment on the simulated rig) and `metarig recover FILE`."""

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("metarig.rig")


def _parser() -> argparse.ArgumentParser:
    from ros_nodes.logic.sequence import ExperimentPlan

    d = ExperimentPlan()
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
    p.add_argument("--scene", default=d.scene, help="sample scene (design_engine preset)")
    p.add_argument("--nx", type=int, default=d.nx, help="units along x")
    p.add_argument("--ny", type=int, default=d.ny, help="units along y")
    p.add_argument("--strain", type=float, default=d.strain, help="pre-compression strain")
    p.add_argument("--settle-s", type=float, default=d.settle_s, help="settle time, s")
    p.add_argument("--pre-trigger-s", type=float, default=d.pre_trigger_s,
                   help="recording before the pulse, s")
    p.add_argument("--record-s", type=float, default=d.record_s, help="capture length, s")
    p.add_argument("--waveform", choices=("pulse", "burst"), default=d.waveform)
    p.add_argument("--amplitude", type=float, default=d.amplitude_m, help="amplitude, m")
    p.add_argument("--frequency", type=float, default=d.frequency_hz, help="frequency, Hz")
    p.add_argument("--cycles", type=float, default=d.cycles, help="burst periods")
    p.add_argument("--fps", type=float, default=d.fps, help="camera frame rate, Hz")
    p.add_argument("--width", type=int, default=d.width, help="frame width, px")
    p.add_argument("--height", type=int, default=d.height, help="frame height, px")
    p.add_argument("--m-per-px", type=float, default=d.m_per_px, help="image scale, m/px")
    p.add_argument("--perturb", type=float, default=d.perturb,
                   help="relative spread of the specimen's true stiffness/damping")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of all simulated noise")
    p.add_argument("--rtf", type=float, default=d.real_time_factor,
                   help="simulated seconds per wall second while devices run (0: max speed)")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="none",
                   help="MCAP chunk compression")
    p.add_argument("--timeout-s", type=float, default=d.timeout_s,
                   help="wall-time limit of any single wait, s")
    return p


def _plan(args):
    from ros_nodes.logic.sequence import ExperimentPlan

    return ExperimentPlan(
        scene=args.scene, nx=args.nx, ny=args.ny, strain=args.strain, settle_s=args.settle_s,
        pre_trigger_s=args.pre_trigger_s, record_s=args.record_s, waveform=args.waveform,
        amplitude_m=args.amplitude, frequency_hz=args.frequency, cycles=args.cycles, fps=args.fps,
        width=args.width, height=args.height, m_per_px=args.m_per_px, perturb=args.perturb,
        seed=args.seed, real_time_factor=args.rtf, timeout_s=args.timeout_s)


def _node_params(plan, out: Path, params_file: Path | None,
                 compression: str = "none") -> dict[str, dict]:
    from ros_nodes import params as P
    from ros_nodes.logic.sequence import node_parameters

    node_params = node_parameters(plan, out)
    node_params["recorder"]["compression"] = compression
    classes = {"shaker": P.ShakerNodeConfig, "stage": P.StageNodeConfig,
               "camera": P.CameraNodeConfig, "recorder": P.RecorderNodeConfig}
    for name, cls in classes.items():
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
