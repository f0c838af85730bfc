"""The simulated rig under load: the same seed must give the same experiment.

Runs one `metarig rig` command several times, each pass with a number of busy-loop processes
beside it, and compares what each recorded, topic by topic (SHA-256 of the message payloads,
`check_identical.topic_fingerprints`): the simulated rig's truth and footage
(/camera/ground_truth, /camera/image_raw) and the device records must be identical whatever the
load; topics stamped or filled from the wall clock may differ (they are listed). Also kept per
pass: the camera's line on the device records it solved the specimen under (their SHA-256, the
samples used and those left out), the load before and after, and, where the command compares,
its summary.

    .venv/bin/python benchmarks/bench_rig_determinism.py --busy 0,3 \\
        --results benchmarks/results -- --nx 6 --ny 4 --no-compare --record-s 0.02

Writes `<out>/bench_rig_determinism.json` (and a copy in `--results`); exits 1 when the truth or
the footage differs between passes.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from check_identical import topic_fingerprints
from machine import describe

BIN = Path(sys.prefix) / "bin"
# what must not depend on the load
MUST_MATCH = (
    "/camera/ground_truth",
    "/camera/image_raw",
    "/camera/reference_image",
    "/shaker/joint_states",
    "/stage/joint_states",
)


def one_pass(run: Path, busy: int, rig_args: list[str], env: dict) -> dict:
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
    load0, t0 = os.getloadavg(), time.monotonic()
    try:
        r = subprocess.run(
            [str(BIN / "metarig"), "rig", "--out", str(run), *rig_args],
            env=env,
            capture_output=True,
            text=True,
            timeout=3600,
        )
    finally:
        for b in burners:
            b.kill()
            b.wait()
    log = r.stdout + r.stderr
    (run / "bench.log").write_text(log)
    if r.returncode != 0:
        raise RuntimeError(f"metarig rig failed (exit {r.returncode}):\n{log[-3000:]}")
    records = re.findall(r"device records up to .*", log)
    out = {
        "busy_processes": busy,
        "load_before": load0,
        "load_after": os.getloadavg(),
        "wall_s": time.monotonic() - t0,
        "device_records": records[-1] if records else "",
        "topics": topic_fingerprints(run),
    }
    if (run / "summary.json").exists():
        out["summary"] = json.loads((run / "summary.json").read_text())
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--out", type=Path, default=Path("runs/bench_rig_determinism"))
    p.add_argument("--busy", default="0,3", help="busy-loop processes beside each pass")
    p.add_argument("--results", type=Path, default=None, help="also copy the JSON here")
    p.add_argument("rig_args", nargs="*", help="arguments of `metarig rig` (after --)")
    args = p.parse_args(argv)
    try:
        passes = [int(s) for s in args.busy.split(",")]
    except ValueError:
        p.error("--busy takes comma-separated counts")
    env = dict(
        os.environ,
        ROS_DOMAIN_ID=str(110 + os.getpid() % 40),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
    )
    res = {
        "machine": describe(),
        "command": "metarig rig " + " ".join(args.rig_args),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "passes": [],
    }
    for k, busy in enumerate(passes):
        print(f"pass {k}: {busy} busy processes ...", flush=True)
        res["passes"].append(one_pass(args.out / f"pass{k}-busy{busy}", busy, args.rig_args, env))
        print(f"  {res['passes'][-1]['device_records']}", flush=True)
    first = res["passes"][0]["topics"]
    res["identical"] = sorted(
        t for t in first if all(q["topics"].get(t) == first[t] for q in res["passes"])
    )
    res["differ"] = sorted(
        set().union(*(q["topics"] for q in res["passes"])) - set(res["identical"])
    )
    bad = [t for t in MUST_MATCH if t in res["differ"]]
    res["deterministic"] = not bad
    for d in filter(None, (args.out, args.results)):
        d.mkdir(parents=True, exist_ok=True)
        (d / "bench_rig_determinism.json").write_text(json.dumps(res, indent=2) + "\n")
    print(f"identical in every pass: {', '.join(res['identical'])}")
    print(f"differ: {', '.join(res['differ']) or 'none'}")
    for q in res["passes"]:
        s = q.get("summary", {})
        print(
            f"busy {q['busy_processes']}: load {q['load_before'][0]:.1f}->"
            f"{q['load_after'][0]:.1f}, {q['wall_s']:.0f} s"
            + (f", velocity NRMSE {100 * s['velocity_nrmse']:.2f} %" if s else "")
        )
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
