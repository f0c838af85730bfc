"""`metarig rig` (run an experiment on the simulated rig) and `metarig recover FILE`."""

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("metarig.rig")


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
