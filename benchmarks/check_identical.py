"""Bit-identical outputs across a change: fingerprints of what the engine and the rig compute.

A fingerprint is the SHA-256 of the exact bytes of:
- every preset scene kind at a small size: the simulated trajectory (`simulate_scene`) and the
  objective with its gradient (`make_objective`), float64;
- a short design run (`metarig design focusing-demo --max-evals 3`): the history of objective
  values, constraint values and design vectors (wall times left out);
- a simulated rig run (`metarig rig --nx 6 --ny 4 --no-compare`): the payloads of every MCAP
  topic (log times left out), topic by topic.

It runs the sources of `--src` (default: this checkout) in subprocesses, through the public
interfaces only (`design_engine`'s re-exports and the `metarig` commands), so one script
fingerprints the code before and after a reorganisation. Compare two fingerprints with
`--compare`: it prints what differs and exits 1 if anything that is deterministic does. Rig
topics that differ between two runs of the same sources (wall-clock payloads) are named in
`--same-code` runs and ignored.

    git worktree add --detach /tmp/before <ref>
    .venv/bin/python benchmarks/check_identical.py --src /tmp/before --out /tmp/before.json
    .venv/bin/python benchmarks/check_identical.py --out /tmp/after.json
    .venv/bin/python benchmarks/check_identical.py --compare /tmp/before.json /tmp/after.json
"""

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
# (preset, nx, ny): one of each scene kind, small enough for seconds each
SCENES = (("focusing-24x16", 8, 6), ("precompression-24x18", 8, 6), ("protection-24x18", 8, 6),
          ("spin-24x16", 8, 6), ("kagome-20x12", 6, 4))

_ENGINE = r"""
import hashlib, json, sys
import numpy as np
import design_engine as de

out = {}
for name, nx, ny in json.loads(sys.argv[1]):
    if name not in de.PRESETS:
        continue
    scene = de.build_scene(name, nx=nx, ny=ny)
    run = de.simulate_scene(scene)
    traj = run.trajectory
    h = hashlib.sha256()
    for field in (traj.t, traj.q, traj.qdot):
        h.update(np.ascontiguousarray(np.asarray(field, np.float64)).tobytes())
    out[f"simulate/{name}"] = h.hexdigest()
    value_and_grad, _ = de.make_objective(scene)
    (value, _aux), grad = value_and_grad(np.asarray(scene.design, np.float64))
    h = hashlib.sha256(np.float64(np.asarray(value)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(grad, np.float64)).tobytes())
    out[f"objective/{name}"] = h.hexdigest()
print(json.dumps(out))
"""


def _python(src: Path, code: str, *args: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(src))
    res = subprocess.run([sys.executable, "-c", code, *args], env=env, cwd=src,
                         capture_output=True, text=True)
    if res.returncode:
        raise SystemExit(f"check_identical: failed in {src}:\n{res.stderr[-3000:]}")
    return res.stdout


def _metarig(src: Path, *args: str) -> None:
    _python(src, "import sys; from metarig.cli import main; sys.exit(main())", *args)


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


def _strip_times(obj):
    """History records without their wall-clock fields (every `*_s` timing, dates, host)."""
    if isinstance(obj, dict):
        return {k: _strip_times(v) for k, v in obj.items()
                if not (k.endswith("_s") or any(w in k for w in (
                    "wall", "elapsed", "seconds", "started", "finished", "date", "host", "load",
                    "commit")))}
    if isinstance(obj, list):
        return [_strip_times(v) for v in obj]
    return obj


def design_fingerprint(src: Path, tmp: Path) -> dict:
    folder = tmp / "design"
    _metarig(src, "design", "focusing-demo", "--max-evals", "3", "--out", str(folder),
             "--no-plots")
    history = json.loads((folder / "history.json").read_text())
    design = json.loads((folder / "design.json").read_text())
    return {"design/history": _digest(_strip_times(history)),
            "design/design.json": _digest(_strip_times(design))}


def rig_fingerprint(src: Path, tmp: Path) -> dict:
    folder = tmp / "rig"
    _metarig(src, "rig", "--nx", "6", "--ny", "4", "--no-compare", "--record-s", "0.02",
             "--out", str(folder))
    return {f"rig{topic}": h for topic, h in topic_fingerprints(folder).items()}


def topic_fingerprints(folder: Path) -> dict[str, str]:
    """{topic: SHA-256 of the payloads of its messages} over the MCAP files under `folder` (log
    times left out)."""
    from mcap.reader import make_reader

    hashes: dict[str, hashlib._Hash] = {}
    for mcap in sorted(folder.rglob("*.mcap")):
        with open(mcap, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages():
                hashes.setdefault(channel.topic, hashlib.sha256()).update(message.data)
    return {topic: h.hexdigest() for topic, h in sorted(hashes.items())}


def fingerprint(src: Path, parts: list[str], work: Path | None = None) -> dict:
    out = {"src": str(src)}
    with tempfile.TemporaryDirectory(prefix="check-identical-") as tmp:
        tmp = work or tmp
        if "engine" in parts:
            print("fingerprint: engine scenes", flush=True)
            out.update(json.loads(_python(src, _ENGINE, json.dumps(SCENES)).splitlines()[-1]))
        if "design" in parts:
            print("fingerprint: design run", flush=True)
            out.update(design_fingerprint(src, Path(tmp)))
        if "rig" in parts:
            print("fingerprint: rig run", flush=True)
            out.update(rig_fingerprint(src, Path(tmp)))
    return out


def compare(a: dict, b: dict, noisy: set[str], report: Path | None = None) -> int:
    keys = sorted((set(a) | set(b)) - {"src"})
    differ = [k for k in keys if a.get(k) != b.get(k) and k not in noisy]
    missing = [k for k in keys if k not in a or k not in b]
    differ = [k for k in differ if k not in missing]
    for k in keys:
        mark = ("noisy" if k in noisy else "missing" if k in missing
                else "same" if a.get(k) == b.get(k) else "DIFFERS")
        print(f"{mark:8} {k}")
    if report is not None:
        report.write_text(json.dumps({
            "before": a.get("src"), "after": b.get("src"),
            "verdict": {k: ("noisy" if k in noisy else "missing" if k in missing
                            else "same" if a.get(k) == b.get(k) else "differs") for k in keys},
            "identical": len(keys) - len(differ) - len(missing), "compared": len(keys) - len(missing),
            "noisy": sorted(noisy & set(keys))}, indent=1) + "\n")
    print(f"{len(keys) - len(differ) - len(missing)} of {len(keys) - len(missing)} fingerprints "
          "identical"
          + (f" ({len(noisy & set(keys))} wall-clock topics ignored)" if noisy else ""))
    return 1 if differ else 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--src", type=Path, default=REPO, help="sources to fingerprint")
    p.add_argument("--out", type=Path, help="fingerprint JSON to write")
    p.add_argument("--parts", default="engine,design,rig", help="engine,design,rig")
    p.add_argument("--work", type=Path, help="keep the runs' folders here (default: a "
                   "temporary folder, removed)")
    p.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    p.add_argument("--report", type=Path, help="with --compare: write the verdicts as JSON")
    p.add_argument("--same-code", nargs="*", type=Path, default=[],
                   help="fingerprints of repeated runs of one source: keys that differ among "
                        "them are wall-clock noise, ignored by --compare")
    args = p.parse_args(argv)
    if args.compare:
        runs = [json.loads(f.read_text()) for f in args.same_code]
        noisy = {k for r in runs[1:] for k in r if k != "src" and r.get(k) != runs[0].get(k)}
        return compare(*(json.loads(f.read_text()) for f in args.compare), noisy, args.report)
    if not args.out:
        p.error("--out is required unless --compare is given")
    result = fingerprint(args.src.resolve(), args.parts.split(","), args.work)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out} ({len(result) - 1} fingerprints)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
