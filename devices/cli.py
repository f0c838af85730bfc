"""`metarig devices`: what lab devices this machine can see, and whether a lab file fits them.

Without `--lab`: lists pylon cameras, GenTL producers and their cameras, VISA instruments and
serial ports, each probe failing softly (one line saying why). With `--lab FILE`: checks the
file against the devices without moving anything (`devices.labcheck`), one line per check, and
exits 1 if any failed (2 if the file itself is wrong).
"""

import argparse
import dataclasses
import json
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="metarig devices", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="List the lab devices this machine can see (pylon and GenTL cameras, VISA "
                    "instruments, serial ports), or check a lab file against them without "
                    "moving anything.")
    p.add_argument("--lab", type=Path, default=None,
                   help="lab file (TOML) to check: each device opens, is the one named, its "
                        "limits fit, a test frame, a dry-run waveform (not played)")
    p.add_argument("--visa-sim", action="store_true",
                   help="also list the emulated function generator (pyvisa-sim, @sim)")
    p.add_argument("--visa-library", action="append", default=[], metavar="LIB",
                   help="also list the instruments of this VISA library (repeatable)")
    p.add_argument("--json", action="store_true", help="a machine-readable report on stdout")
    return p


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def _list(args) -> int:
    from devices.lab import SHAKER_EMULATOR_YAML
    from devices.probe import probe_all

    libraries = ("", *args.visa_library) + ((f"{SHAKER_EMULATOR_YAML}@sim",)
                                            if args.visa_sim else ())
    probes = probe_all(libraries)
    if args.json:
        print(json.dumps({"probes": [dataclasses.asdict(p) for p in probes]}, indent=2))
        return 0
    nouns = {"pylon": "camera", "gentl": "camera", "visa": "instrument", "serial": "port"}
    for p in probes:
        noun = nouns[p.kind.split()[0]]
        where = f" ({p.source})" if p.kind.startswith("gentl") else ""
        if p.error:
            print(f"{p.kind}: cannot look: {p.error}{where}")
            continue
        print(f"{p.kind}: {_plural(len(p.found), noun)}{where}")
        for f in p.found:
            print(f"  {f.name:<24} {f.detail}".rstrip())
    return 0


def _check(args) -> int:
    from devices.lab import LabFileError, read_lab
    from devices.labcheck import check_lab

    try:
        lab = read_lab(args.lab)
    except LabFileError as e:
        print(f"metarig devices: {e}", file=sys.stderr)
        return 2
    checks = check_lab(lab)
    failed = [c for c in checks if not c.ok]
    if args.json:
        print(json.dumps({"lab": str(args.lab), "ok": not failed,
                          "checks": [dataclasses.asdict(c) for c in checks]}, indent=2))
    else:
        for c in checks:
            print(f"{'ok' if c.ok else 'FAILED':<7} {c.device:<7} {c.what}: {c.detail}")
        print(f"{args.lab}: " + (f"{len(failed)} of {_plural(len(checks), 'check')} FAILED"
                                 if failed else f"all {_plural(len(checks), 'check')} passed"))
    return 1 if failed else 0


def devices_main(argv: list[str] | None = None) -> int:
    """List the devices this machine sees, or check a lab file against them (see --help)."""
    args = _parser().parse_args(argv)
    return _check(args) if args.lab is not None else _list(args)
