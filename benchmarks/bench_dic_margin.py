"""How far from its outline a unit's subset should stay: the slivers' rotation against the margin.

A slender unit's rotation is measured by the few pixel rows along its length, so every pixel
that the outline margin (`DICConfig.margin_px`; `tracking.dic_config.SMALL_UNIT_MARGIN_PX` for
designs with small units) leaves out costs precision; the pixels near the outline, though, mix
in the outline's own step edge, which moves the pose. Two parts, on the footage that
`bench_dic_design.py` filmed (one folder per render, `--footage DIR ...`):

- **tracked**: the footage tracked at each margin of `--margins` as `metarig track` does (one
  process, the neighbours' check), scored as `bench_dic_design.py` scores it (its `score`); the
  slender units are those of the default settings, the same units at every margin;
- **noise-free**: frames `--bias-frames` of the same motion rendered without noise at each
  `--bias-supersample` (sub-pixel samples per pixel side), every unit registered from its true
  pose against a noise-free reference: what is left is the bias of the outline's edge (and of
  the interpolation), p99 and largest rotation error per margin.

Writes `benchmarks/results/bench_dic_margin.json` (`--results`) and a chart beside it
(`bench_dic_margin.png`), and prints a table.
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import cv2
import numpy as np

from bench_dic_design import FPS, MPP, camera_config, load_footage, score, slender_units
from machine import describe

ROOT = Path(__file__).resolve().parents[1]


def tracked(folder: Path, margins: list[float]) -> list[dict]:
    """The footage of `folder` tracked at each margin; one row each."""
    from tracking.batch import track_source
    from tracking.dic import settings_for_units
    from tracking.frame_sources import open_source
    from tracking.units import bonds_from_outlines

    truth, _, polygons, calib, ss = load_footage(folder)
    ref_path = folder / "reference-8.png"
    # the slender units of the default settings: the same units at every margin
    slender = slender_units(polygons, calib, settings_for_units(polygons, MPP),
                            cv2.imread(str(ref_path), cv2.IMREAD_UNCHANGED))
    bonds = bonds_from_outlines(polygons)
    rows = []
    for m in margins:
        cfg = dataclasses.replace(settings_for_units(polygons, MPP), margin_px=m)
        traj, _ = track_source(open_source(folder / "frames"), polygons, calib, cfg,
                               workers=1, bonds=bonds, reference=str(ref_path))
        s = score(traj.q, traj.sigma, traj.lost, truth, slender, MPP)
        rows.append({"footage": str(folder), "supersample": ss, "margin_px": m,
                     "slender_units": int(slender.sum()),
                     **{k: s[k] for k in ("wrong_without_flag", "p99_position_px",
                                          "p99_rotation_mrad", "p99_rotation_mrad_slender",
                                          "p99_rotation_mrad_other", "lost_share",
                                          "uncertain_share", "within_2_sigma")}})
        print(f"tracked   ss {ss}  margin {m:4.2f} px: p99 rotation {s['p99_rotation_mrad']:.2f}"
              f" mrad (slender {s['p99_rotation_mrad_slender']:.2f}, others "
              f"{s['p99_rotation_mrad_other']:.2f}), wrong without a flag "
              f"{s['wrong_without_flag']}, lost {100 * s['lost_share']:.2f} %", flush=True)
    return rows


def noise_free(folder: Path, margins: list[float], supersamples: list[int],
               frames: list[int]) -> list[dict]:
    """Rotation bias of noise-free renders of `folder`'s motion, per render and margin."""
    from hardware_sim.camera import make_speckle_textures, render_frame
    from tracking.dic import DICTracker, prepare_frame, settings_for_units
    from tracking.icgn import icgn
    from tracking.reference import build_refs

    truth, _, polygons, calib, _ = load_footage(folder)
    h, w = cv2.imread(str(folder / "frames" / "00000.png"), cv2.IMREAD_UNCHANGED).shape
    rows = []
    for ss in supersamples:
        ccfg = dataclasses.replace(camera_config(w, h, calib.origin_px, FPS, MPP, 0, ss),
                                   noise_std=0.0)
        tex = make_speckle_textures(polygons, ccfg, np.random.default_rng(0))
        rng = np.random.default_rng(1)  # unused without noise
        ref = render_frame(ccfg, polygons, np.zeros((len(polygons), 3)), tex, rng)
        base = settings_for_units(polygons, MPP)
        tr = DICTracker(polygons, calib, base)  # the margin does not enter the prepared frames
        pr = prepare_frame(tr, ref)
        shots = {k: prepare_frame(tr, render_frame(ccfg, polygons, truth[k], tex, rng)).coef
                 for k in frames}
        for m in margins:
            refs = build_refs(pr.img, pr.coef, tr.polys_px, tr.centroid_px, m, base.min_points)
            idx = np.flatnonzero(refs.count > 0)
            err = []
            for k in frames:
                q = truth[k][idx]
                a0 = q[:, 2] * calib.image_rotation_sign
                t0 = np.stack([q[:, 0], -q[:, 1]], axis=1) / MPP
                r = icgn(shots[k], refs, idx, a0, t0, 50, 1e-4, 8.0)
                err.append(np.abs(r.alpha - a0))
            e = np.concatenate(err) * 1e3
            rows.append({"supersample": ss, "margin_px": m, "frames": frames,
                         "p99_rotation_mrad": float(np.percentile(e, 99)),
                         "max_rotation_mrad": float(e.max())})
            print(f"noise-free ss {ss}  margin {m:4.2f} px: rotation bias p99 "
                  f"{rows[-1]['p99_rotation_mrad']:.2f}, largest {e.max():.2f} mrad", flush=True)
    return rows


def chart(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for folder in dict.fromkeys(r["footage"] for r in res["tracked"]):
        rows = [r for r in res["tracked"] if r["footage"] == folder]
        ax.plot([r["margin_px"] for r in rows], [r["p99_rotation_mrad"] for r in rows], "o-",
                label=f"tracked, noisy footage rendered at {rows[0]['supersample']}x"
                      f"{rows[0]['supersample']} ({Path(folder).name})")
    for ss in dict.fromkeys(r["supersample"] for r in res["noise_free"]):
        rows = [r for r in res["noise_free"] if r["supersample"] == ss]
        ax.plot([r["margin_px"] for r in rows], [r["p99_rotation_mrad"] for r in rows], "s--",
                label=f"noise-free bias, rendered at {ss}x{ss}")
    ax.axhline(3.0, color="grey", lw=0.8, ls=":", label="target (p99 3 mrad)")
    ax.set_xlabel("outline margin of the subsets, px")
    ax.set_ylabel("p99 rotation error, mrad")
    ax.set_title("Optimised 24x16 focusing design, 0.4 mm/px, 1000 fps")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--footage", type=Path, nargs="+",
                   default=[Path("runs/bench_dic_design"), Path("runs/bench_dic_design_ss2")],
                   help="folders filmed by bench_dic_design.py (--out), any supersample")
    p.add_argument("--margins", type=float, nargs="+", default=[0.5, 0.75, 1.0, 1.25, 1.5, 2.0])
    p.add_argument("--bias-supersample", type=int, nargs="+", default=[2, 4, 8])
    p.add_argument("--bias-frames", type=int, nargs="+", default=[30, 50, 70, 90])
    p.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results")
    args = p.parse_args(argv)
    for f in args.footage:
        if not (f / "truth.npz").is_file() or not (f / "reference-8.png").is_file():
            p.error(f"{f}: no footage of bench_dic_design.py there (run it with --out {f}, "
                    f"and --supersample 2 for the 2 x 2 footage of the default second folder)")
    if min(args.margins) < 0:
        p.error("--margins must be >= 0")
    n_t = np.load(args.footage[0] / "truth.npz")["q"].shape[0]
    if not all(0 <= k < n_t for k in args.bias_frames):
        p.error(f"--bias-frames must lie in 0..{n_t - 1}")
    t0 = time.perf_counter()
    res = {"machine": describe(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "tracked": [row for f in args.footage for row in tracked(f, args.margins)],
           "noise_free": noise_free(args.footage[0], args.margins, args.bias_supersample,
                                    args.bias_frames)}
    res["wall_s"] = time.perf_counter() - t0
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "bench_dic_margin.json").write_text(json.dumps(res, indent=2))
    chart(res, args.results / "bench_dic_margin.png")
    print(f"wrote {args.results / 'bench_dic_margin.json'} and .png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
