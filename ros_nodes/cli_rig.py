"""`metarig rig` (run an experiment on the simulated rig, or on the devices of a lab file) and
`metarig recover FILE`."""

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

from metarig.argtypes import positive

log = logging.getLogger("metarig.rig")


# plan field -> flag, where the flag is not the field name with dashes (kept for compatibility)
FLAG_NAMES = {"amplitude_m": "amplitude", "frequency_hz": "frequency", "real_time_factor": "rtf"}
# plan fields set by the experiment, not from the command line
NO_FLAG = ("clock_step_s", "material_si")


class _Given(argparse.Action):
    """Store the value and note that the flag was given (`namespace.given`)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.given = getattr(namespace, "given", set()) | {self.dest}


class _GivenSwitch(_Given):
    """A boolean plan field as a switch: the flag alone sets it."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        super().__call__(parser, namespace, True, option_string)


def plan_flags(p: argparse.ArgumentParser, plan_cls) -> None:
    """One flag per plan field, from its metadata (default, description, choices); a nested
    config (the specimen's imperfections) gives one flag per field of it, named
    `--<field>-<its field>` (`--specimen-friction-hz`); a boolean field is a switch."""
    for name, f, default in _plan_fields(plan_cls):
        if isinstance(default, bool):
            p.add_argument(plan_flag(name), dest=name, default=default, action=_GivenSwitch,
                           help=f.metadata.get("description"))
            continue
        p.add_argument(plan_flag(name), dest=name, type=type(default), default=default,
                       action=_Given, choices=f.metadata.get("choices"),
                       help=f.metadata.get("description"))


def _plan_fields(cls, prefix: str = ""):
    """(dotted name, field, default) of every flag-bearing field of a plan class."""
    defaults = cls()
    for f in dataclasses.fields(cls):
        if f.name in NO_FLAG:
            continue
        default = getattr(defaults, f.name)
        if dataclasses.is_dataclass(default):
            yield from _plan_fields(type(default), f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, f, default


def plan_flag(name: str) -> str:
    """The command-line flag of plan field `name` (dotted for a nested config's field)."""
    return "--" + FLAG_NAMES.get(name, name).replace("_", "-").replace(".", "-")


def _parser() -> argparse.ArgumentParser:
    from ros_nodes.logic.sequence import ExperimentPlan

    p = argparse.ArgumentParser(
        prog="metarig rig", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Run one experiment on the simulated rig (or on the devices of a lab file: "
                    "--hardware lab --lab FILE): pre-compress, settle, record, fire the pulse, "
                    "record, stop; writes a run folder with one MCAP recording.")
    p.add_argument("--out", type=Path, default=Path("runs/rig"), help="run folder")
    p.add_argument("--processes", action="store_true",
                   help="one process per node (default: all nodes in this process)")
    p.add_argument("--hardware", choices=("sim", "lab"), default="sim",
                   help="the simulated rig, or the devices of the lab file --lab on the system "
                        "clock (checked first as `metarig devices --lab` does; records only)")
    p.add_argument("--lab", type=Path, default=None, metavar="LAB.toml",
                   help="lab file (TOML) naming the devices, with --hardware lab")
    p.add_argument("--params", type=Path, default=None,
                   help="ROS 2 YAML parameter file applied to the nodes (node_name: "
                        "ros__parameters: ...)")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="none",
                   help="MCAP chunk compression")
    p.add_argument("--no-compare", action="store_true",
                   help="only record: skip tracking the frames and the comparison")
    p.add_argument("--live-dic", action="store_true",
                   help="also run the live DIC node (decimated preview on /dic/poses); the "
                   "run's MCAP gets the full-rate offline tracking in its place")
    p.add_argument("--workers", type=positive(int), default=None,
                   help="tracker processes after the capture (default: all cores)")
    plan_flags(p, ExperimentPlan)
    return p


def _plan(args):
    """The plan of the flags; a `--design` file sets nx, ny from its lattice. A text flag given
    empty is refused (empty is the plan's "not given", e.g. no design file)."""
    from ros_nodes.logic.sequence import ExperimentPlan

    values = {name: getattr(args, name) for name, _, _ in _plan_fields(ExperimentPlan)}
    given = getattr(args, "given", set())
    for name in sorted(given):
        if isinstance(values[name], str) and not values[name].strip():
            raise ValueError(f"{plan_flag(name)} is empty; leave the flag out for the default")
    if values["design"]:
        path = Path(values["design"])
        try:
            shape = json.loads(path.read_text())["lattice"]["shape"]
            nx, ny = (int(v) for v in shape)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(f"--design {path}: not a readable design file ({e})") from None
        if ("nx" in given and values["nx"] != nx) or ("ny" in given and values["ny"] != ny):
            raise ValueError(f"--nx/--ny disagree with the design file's lattice {nx}x{ny}")
        values["nx"], values["ny"] = nx, ny
        values["design"] = str(path.resolve())
    if values["material"]:
        from design_engine.physics.material_file import read_material_file

        # read and checked here, once: MaterialFileError (a ValueError) names the key
        values["material_si"] = json.dumps(dict(read_material_file(values["material"])[0]))
        values["material"] = str(Path(values["material"]).resolve())
    nested = {}
    for name in [n for n in values if "." in n]:
        outer, inner = name.split(".", 1)
        nested.setdefault(outer, {})[inner] = values.pop(name)
    defaults = ExperimentPlan()
    for outer, kw in nested.items():
        values[outer] = type(getattr(defaults, outer))(**kw)
    return ExperimentPlan(**values)


def _node_params(plan, out: Path, params_file: Path | None, compression: str = "none",
                 lab_file: Path | None = None, frame_rate_hz: float = 0.0) -> dict[str, dict]:
    from ros_nodes import params as P
    from ros_nodes.logic.sequence import lab_node_parameters, node_parameters
    from ros_nodes.registry import NODES

    node_params = node_parameters(plan, out) if lab_file is None else \
        lab_node_parameters(plan, out, lab_file, frame_rate_hz)
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
    if args.hardware == "lab" or args.lab is not None:
        return lab_main(args)
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
    calibration = write_calibration(plan, args.out)
    if args.live_dic:
        node_params["dic_tracker"] = {"use_sim_time": True, "calibration_path": str(calibration)}
    from ros_nodes.nodes._rig import run_rig

    code = run_rig(plan, node_params, args.out.resolve(), processes=args.processes)
    if code != 0 or args.no_compare:
        return code
    return compare_run(args.out, args.workers)


def lab_main(args) -> int:
    """`metarig rig --hardware lab --lab FILE`: the lab file and the plan checked, the file's
    [ros] applied, every device checked (nothing moves), then the experiment on the devices on
    the system clock (`ros_nodes.lab_run`). Records only: a lab recording is compared with
    `metarig compare DIR --calibration FILE` (the lab camera's calibration)."""
    from devices.lab import LabFileError
    from ros_nodes.lab_run import LabRunError, apply_ros, check_plan, lab_for_rig, \
        nominal_design_json, preflight, refuse_sim_flags
    from ros_nodes.params import ConfigError

    given = getattr(args, "given", set())
    try:
        if args.hardware != "lab":
            raise LabRunError("--lab is for --hardware lab")
        if args.lab is None:
            raise LabRunError("--hardware lab needs --lab LAB.toml (the lab file; `metarig "
                              "devices --lab FILE` checks one)")
        if args.live_dic:
            raise LabRunError("--live-dic: only for the simulated rig (its camera's "
                              "calibration is known); track a lab recording with `metarig "
                              "compare DIR --calibration FILE`")
        refuse_sim_flags(given, plan_flag)
        lab = lab_for_rig(args.lab)
        plan = _plan(args)
        rate = plan.fps if "fps" in given else 0.0
        plan = dataclasses.replace(plan, fps=rate or lab.camera.settings.frame_rate_hz)
        check_plan(plan, lab, rate)
        lab_file = args.lab.resolve()
        node_params = _node_params(plan, args.out.resolve(), args.params, args.compression,
                                   lab_file, rate)
    except (ValueError, ConfigError, LabFileError) as e:  # LabRunError is a ValueError
        print(f"metarig rig: {e}", file=sys.stderr)
        return 2
    env = apply_ros(lab.ros)
    log.info("ROS: %s", ", ".join(f"{k}={v}" for k, v in env.items()))
    log.info("checking the devices of %s (nothing moves)", args.lab)
    failed = preflight(lab, lambda line: log.info("%s", line))
    if failed:
        more = f" (and {len(failed) - 1} more above)" if len(failed) > 1 else ""
        print(f"metarig rig: {args.lab}: {failed[0]}{more}; nothing was started",
              file=sys.stderr)
        return 1
    log.info("building the sample's nominal design (%s %dx%d%s)", plan.scene, plan.nx, plan.ny,
             f", {plan.design}" if plan.design else "")
    design = nominal_design_json(plan)
    args.out.mkdir(parents=True, exist_ok=True)
    stale = args.out / "recording.mcap"
    if stale.exists():
        stale.unlink()
    from ros_nodes.nodes._rig import run_rig

    code = run_rig(plan, node_params, args.out.resolve(), processes=args.processes,
                   lab={"lab_file": lab_file, "design_json": design, "ros": env})
    if code == 0:
        log.info("recorded on the lab devices (no comparison: compare with `metarig compare "
                 "%s --calibration FILE`, the camera's calibration)", args.out)
    return code


CALIBRATION_NAME = "calibration.json"


def write_calibration(plan, out: Path) -> Path:
    """The simulated camera's calibration (`tracking.calibration` format) for the run's sample:
    its pixel scale, frame rate and the origin that centres the sample in the frame."""
    from hardware_sim.rig import centred_origin
    from hardware_sim.specimen import SpecimenConfig, build

    polygons = build(SpecimenConfig(scene=plan.scene, nx=plan.nx, ny=plan.ny,
                                    design_path=plan.design)).nominal_polygons_m
    origin = centred_origin(polygons, plan.width, plan.height, plan.m_per_px)
    path = out / CALIBRATION_NAME
    path.write_text(json.dumps({"fps": plan.fps, "m_per_px": plan.m_per_px,
                                "origin_px": [float(origin[0]), float(origin[1])],
                                "y_up": True}))
    return path


def compare_run(out: Path, workers: int | None) -> int:
    """Track the recorded frames (all cores), compare with the simulation, report; the run
    folder gains the comparison files and `run.json` its summary and timings."""
    import time

    from ros_nodes.logic.comparison_run import CompareError, velocity_text
    from ros_nodes.recorded_compare import compare_recording
    from ros_nodes.logic.sequence import SUMMARY_NAME

    t0 = time.perf_counter()
    try:
        s = compare_recording(out, out, poses="track", workers=workers,
                              progress=sys.stderr.isatty())
    except CompareError as e:
        print(f"metarig rig: the recording is kept, but the comparison failed: {e}",
              file=sys.stderr)
        return 1
    run = json.loads((out / SUMMARY_NAME).read_text())
    run["comparison"] = {k: s[k] for k in ("velocity_nrmse", "velocity_noise_nrmse",
                                           "velocity_nrmse_beyond_noise",
                                           "energy_map_correlation", "target_peak_ke_rel_err",
                                           "max_displacement_error_m", "lost_units", "onset_s",
                                           "mcap", "rrd") if k in s}
    run.setdefault("timings_s", {})["track_and_compare"] = time.perf_counter() - t0
    run["timings_s"]["total_with_comparison"] = (run["timings_s"].get("total_wall", 0.0)
                                                 + run["timings_s"]["track_and_compare"])
    (out / SUMMARY_NAME).write_text(json.dumps(run, indent=2, default=str))
    log.info("compared in %.1f s: %s, target peak KE %+.1f %%, %d lost units; open with: "
             "rerun %s", run["timings_s"]["track_and_compare"], velocity_text(s),
             100 * s["target_peak_ke_rel_err"], s["lost_units"], s["rrd"])
    return 0


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
    out = args.file.with_suffix(".recovered.mcap") if args.out is None else args.out
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
