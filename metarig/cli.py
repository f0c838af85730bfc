"""`metarig` command: dispatches subcommands to the package that owns them.

Subcommand modules are imported lazily, so `metarig simulate` never imports ROS and a
missing optional piece only affects its own subcommand.
"""

import importlib
import sys

from metarig.signals import stop_on_signals

# subcommand -> (module, function, one-line help). Each function is `main(argv) -> int`.
SUBCOMMANDS: dict[str, tuple[str, str, str]] = {
    "simulate": ("design_engine.commands.simulate", "simulate_main", "simulate a scene and write its outputs"),
    "modes": ("design_engine.commands.simulate", "modes_main", "linear modal analysis of a scene"),
    "design": ("design_engine.commands.design", "design_main", "optimise a design for a task (MMA)"),
    "pareto": ("design_engine.commands.pareto", "pareto_main", "Pareto sweep of a two-objective task on Dask"),
    "robustness": ("design_engine.commands.robustness", "robustness_main",
                   "target-to-rest ratio over input frequency x amplitude (Fig. 2C) on Dask"),
    "export": ("design_engine.commands.export", "export_main", "export a design's outlines for fabrication (SVG, DXF)"),
    "bench": ("design_engine.commands.bench", "bench_main", "speed-accuracy studies (work-precision, speedup)"),
    "rig": ("ros_nodes.cli_rig", "rig_main", "run an experiment on the simulated (or real) rig"),
    "devices": ("devices.cli", "devices_main",
                "list the lab devices this machine sees, or check a lab file against them"),
    "recover": ("ros_nodes.cli_rig", "recover_main", "salvage an MCAP recording whose writer was killed"),
    "track": ("tracking.cli", "track_main", "track unit poses in frames by DIC"),
    "camera-calibrate": ("tracking.camera_calibrate_cli", "camera_calibrate_main",
                         "camera and sample plane from photographs of a calibration target"),
    "demo": ("ros_nodes.cli_demo", "demo_main",
             "the main job: design a small lattice, test it on the simulated rig, compare"),
    "import": ("ros_nodes.cli_import", "import_main",
               "a lab's own camera files (MRAW, CINE, TIFF, video, images) + drive signal -> a "
               "run folder"),
    "compare": ("ros_nodes.cli_compare", "compare_main",
                "compare a recorded experiment with the simulation of its measured input"),
    "calibrate": ("ros_nodes.cli_calibrate", "calibrate_main", "fit material constants to a recorded test"),
    "loop": ("ros_nodes.cli_loop", "loop_main",
             "design, test on the rig, calibrate, redesign from what was measured (rounds)"),
}


def _usage() -> str:
    lines = ["usage: metarig <command> [options]", "", "commands:"]
    for name, (_, _, text) in SUBCOMMANDS.items():
        lines.append(f"  {name:<16}{text}")
    lines.append("")
    lines.append("Run `metarig <command> --help` for the options of one command.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `metarig` console script."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"metarig: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, func_name, _ = SUBCOMMANDS[name]
    func = getattr(importlib.import_module(module_name), func_name)
    stop_on_signals()  # SIGTERM, and SIGINT in a background job, stop a command like Ctrl-C
    try:
        return int(func(rest) or 0)
    except KeyboardInterrupt:
        print("metarig: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
