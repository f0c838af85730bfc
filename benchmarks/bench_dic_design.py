"""DIC on an optimised design, against exact truth: the scene where the tracker struggles.

The sample is the focusing design of `design_engine/studies/fixtures/focusing-contact-24x16.json`
(evaluation 60 of a focusing run: 384 units, many of them slender slivers), driven by the paper's
pulse (A = 7.5 mm, f = 30 Hz, from 5 ms) and solved by the simulated rig's physics; the camera
films it at 1000 fps and 0.4 mm/px with the rig camera's defaults (1 % read noise, 15 % lighting
gradient, blur over half a frame, frames stamped at the middle of their exposure), after a
reference image of the sample at rest. `metarig track`'s engine tracks the frames (2 worker
processes); the poses are compared with the truth at the stamps.

Reported (the targets of the tracking issue in brackets): unit-frames wrong by more than 0.5 px
or 10 mrad without a flag [0], where a pose is flagged when it is lost or when its own stated
standard error says it may be that far off (3 sigma beyond the bound: `UNCERTAIN_SIGMAS`), and
also counted without the second kind of flag (`wrong_not_lost`); 99th-percentile position and
rotation error over the unflagged unit-frames and over all tracked ones [<= 0.1 px, <= 3 mrad];
lost unit-frames and uncertain ones, slender units (no search template fits inside them) counted
separately [<= 2 %]; the share of true errors within 2 stated standard errors [about 95 %];
tracking speed [>= 20 frames/s on 2 cores]; with the machine and its load, and the CPU time the
tracking took (all its processes, start-up and PNG decoding included), which a busy machine
changes far less. `metarig track`'s default split: 1 process whose numba threads share the
cores (`--workers`, `--threads`). Every pose is also checked against its bonded neighbours
(the ligaments found in the outlines, `bonds` in the results; `--no-neighbours`: without). Also the share of
each component's error variance that is white from frame to frame (the rest is each unit's
constant, mostly the reference image's noise), against `comparison.metrics.FRAME_NOISE_SHARE`,
and what the comparison states from it: the share of the true velocity errors (the
comparison's rates of the tracked poses against those of the truth, over units never lost)
within 2 of the standard errors that `FRAME_NOISE_SHARE` of the poses' stated variance gives
them (`comparison.metrics.rate_noise_var`) [about 95 %], and the share that would make the
stated rate noise right on average (`velocity_error_share`). The tracked poses are kept in
`<out>/tracks.npz` (or `tracks_refN.npz`).

The reference image averages `--reference-frames` frames at rest (default: the rig's,
`hardware_sim.camera.REFERENCE_FRAMES`); it is rendered for each count once, beside the
footage (`reference-N.png`), so counts compare on the same frames; another count than the
rig's writes `..._refN.json`, and another `--seed` than 0 (footage and specimen noise)
`..._seedN.json`. The frames are rendered at `--supersample` (default `SUPERSAMPLE`, the camera
model's own) sub-pixel samples per pixel side; footage keeps the count it was rendered at.

Writes `<out>/bench_dic_design.json` and, with `--results DIR`, a copy there. Prints a table.
`--design periodic` films the scene's periodic focusing design instead (squares, no slivers):
`bench_dic_periodic.json`.
"""

import argparse
import json
import os
import resource
import time
from pathlib import Path

import cv2
import numpy as np

from machine import describe

ROOT = Path(__file__).resolve().parents[1]
DESIGN = ROOT / "design_engine" / "studies" / "fixtures" / "focusing-contact-24x16.json"
# the render's sub-pixel samples per pixel side: the camera model's default. A real pixel
# integrates its light exactly; 2 x 2 samples alias each outline's step edge into a few grey
# steps that follow the edge's sub-pixel position, which moved the poses of noise-free renders by
# up to 2.4 mrad (p99 1.2) on this design, against 2.2 (0.93) at 4 and 1.9 (0.90) at 8
SUPERSAMPLE = 4
FPS, MPP = 1000.0, 4e-4  # the footage: frame rate, 1/s, and image scale, m/px
WRONG_PX, WRONG_RAD = 0.5, 0.01  # a pose further off than this is wrong
UNCERTAIN_SIGMAS = 3.0  # a pose whose stated error reaches a bound in this many sigma says so



def _shown(design: str) -> str:
    """The design as the results file names it: `periodic`, or its path from the repository."""
    p = Path(design).resolve()
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else design


def film_design(folder: Path, fps: float, m_per_px: float, duration_s: float, seed: int,
                design: str, supersample: int):
    """Render the frames (PNG) and the reference image; returns (truth q [n_t, n, 3] at the
    stamps, stamps s, polygons m, calibration)."""
    from hardware_sim.rig import MotionRecord, capture_times, centred_origin, exposure_motion, film
    from hardware_sim.specimen import SpecimenConfig, build
    from tracking.calibration import Calibration

    specimen = build(SpecimenConfig(scene="focusing-24x16",
                                    design_path="" if design == "periodic" else design))
    t_in = np.arange(0.0, duration_s + 0.02, 1e-4)
    u_in = 0.5 * 7.5e-3 * (1 - np.cos(2 * np.pi * 30 * np.clip(t_in - 0.005, 0, 1 / 30)))
    times = capture_times(1.0 / fps, duration_s, fps)
    print(f"solving the specimen for {times.size} frames ...", flush=True)
    traj = exposure_motion(specimen, times, MotionRecord(t_in, u_in), None, fps)
    lo = specimen.polygons_m.reshape(-1, 2).min(axis=0)
    hi = specimen.polygons_m.reshape(-1, 2).max(axis=0)
    w = int(np.ceil((hi[0] - lo[0]) / m_per_px)) + 80  # room for the driven edge's 7.5 mm
    h = int(np.ceil((hi[1] - lo[1]) / m_per_px)) + 40
    origin = centred_origin(specimen.polygons_m, w, h, m_per_px)
    ccfg = camera_config(w, h, origin, fps, m_per_px, seed, supersample)
    folder.mkdir(parents=True, exist_ok=True)
    stamps, truth = [], []
    for k, (t, frame, q) in enumerate(film(specimen, ccfg, traj, np.random.default_rng(seed))):
        cv2.imwrite(str(folder / f"{k:05d}.png"), frame)
        stamps.append(t)
        truth.append(q)
    calib = Calibration(fps=fps, m_per_px=m_per_px, origin_px=origin, y_up=True)
    return np.array(truth), np.array(stamps), specimen.polygons_m, calib


def load_footage(folder: Path):
    """(truth q [n_t, n, 3], stamps s, polygons m, calibration, supersample) of footage this
    benchmark filmed into `folder` (its `truth.npz`; footage of before `--supersample`: 2)."""
    from tracking.calibration import Calibration

    d = np.load(folder / "truth.npz")
    calib = Calibration(fps=FPS, m_per_px=MPP, origin_px=tuple(d["origin_px"]), y_up=True)
    filmed = int(d["supersample"]) if "supersample" in d else 2
    return d["q"], d["t"], d["polygons_m"], calib, filmed


def slender_units(polygons: np.ndarray, calib, cfg, reference: np.ndarray) -> np.ndarray:
    """[n] units no search template fits in under tracker settings `cfg`."""
    from tracking.dic import DICTracker, init_state
    from tracking.search import MIN_TEMPLATE_HALF

    return init_state(DICTracker(polygons, calib, cfg), reference).refs.tpl_half < MIN_TEMPLATE_HALF


def camera_config(width_px: int, height_px: int, origin_px, fps: float, m_per_px: float,
                  seed: int, supersample: int):
    """The rig camera's defaults at this scale (1 % read noise, 15 % lighting gradient)."""
    from hardware_sim import camera as cam

    return cam.CameraConfig(width_px=width_px, height_px=height_px, fps=fps, m_per_px=m_per_px,
                            origin_px=tuple(origin_px), supersample=supersample, exposure_samples=3,
                            noise_std=0.01, lighting_gradient=0.15, seed=seed)


def reference(out: Path, frames: int, polygons: np.ndarray, origin_px, fps: float,
              m_per_px: float, seed: int, supersample: int) -> Path:
    """The footage's reference image averaged over `frames` frames at rest (rendered once)."""
    from hardware_sim.camera import reference_image

    path = out / f"reference-{frames}.png"
    if not path.exists():
        h, w = cv2.imread(str(next((out / "frames").glob("*.png"))), cv2.IMREAD_UNCHANGED).shape
        ccfg = camera_config(w, h, origin_px, fps, m_per_px, seed, supersample)
        cv2.imwrite(str(path), reference_image(ccfg, polygons, seed, frames))
    return path


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and its finished worker processes."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def score(q: np.ndarray, sigma: np.ndarray, lost: np.ndarray, truth: np.ndarray,
          slender: np.ndarray, m_per_px: float) -> dict:
    """The tracking targets' figures of poses q [n_t, n, 3] with stated errors sigma [n_t, n, 3]
    and lost flags [n_t, n] against the truth [n_t, n, 3]; `slender` [n] marks the units no
    search template fits in (the results file's keys from `flag` to `within_2_sigma`)."""
    mpp = m_per_px
    e = q - truth
    pos_px = np.hypot(e[..., 0], e[..., 1]) / mpp
    rot = np.abs(e[..., 2])
    ok = ~lost
    wrong = ok & ((pos_px > WRONG_PX) | (rot > WRONG_RAD))
    sig_px = np.hypot(sigma[..., 0], sigma[..., 1]) / mpp
    uncertain = ok & ((UNCERTAIN_SIGMAS * sig_px > WRONG_PX)
                      | (UNCERTAIN_SIGMAS * sigma[..., 2] > WRONG_RAD))
    trusted = ok & ~uncertain
    z = np.abs(e) / sigma
    return {
        "flag": {"wrong_px": WRONG_PX, "wrong_rad": WRONG_RAD,
                 "uncertain_sigmas": UNCERTAIN_SIGMAS},
        "wrong_without_flag": int((wrong & ~uncertain).sum()),
        "wrong_without_flag_where": [[int(k), int(u)]
                                     for k, u in np.argwhere(wrong & ~uncertain)[:20]],
        "wrong_not_lost": int(wrong.sum()),
        "wrong_not_lost_where": [[int(k), int(u)] for k, u in np.argwhere(wrong)[:20]],
        "wrong_not_lost_sigmas": [float(v) for v in np.sort(np.maximum(
            pos_px / np.maximum(sig_px, 1e-12), rot / sigma[..., 2])[wrong])[:20]],
        "p99_position_px": float(np.percentile(pos_px[trusted], 99)),
        "p99_rotation_mrad": float(np.percentile(rot[trusted], 99) * 1e3),
        "p99_rotation_mrad_slender": float(np.percentile(rot[:, slender][trusted[:, slender]],
                                                         99) * 1e3) if slender.any() else None,
        "p99_rotation_mrad_other": float(np.percentile(rot[:, ~slender][trusted[:, ~slender]],
                                                       99) * 1e3),
        "p99_position_px_all_tracked": float(np.percentile(pos_px[ok], 99)),
        "p99_rotation_mrad_all_tracked": float(np.percentile(rot[ok], 99) * 1e3),
        "lost_share": float(lost.mean()),
        "lost_share_slender": float(lost[:, slender].mean()) if slender.any() else 0.0,
        "lost_share_other": float(lost[:, ~slender].mean()),
        "uncertain_share": float(uncertain.mean()),
        "uncertain_share_slender": float(uncertain[:, slender].mean()) if slender.any()
        else 0.0,
        "uncertain_share_other": float(uncertain[:, ~slender].mean()),
        "within_2_sigma": [float(np.mean(z[..., i][ok] < 2.0)) for i in range(3)],
    }


def white_share(e: np.ndarray) -> list[float]:
    """Share of the error variance (e [n_t, n, 3], NaN where lost) left once each unit's mean
    error is taken away, per component: the part white from frame to frame."""
    dev = e - np.nanmean(e, axis=0, keepdims=True)
    return [float(np.nanmean(dev[..., i] ** 2) / np.nanmean(e[..., i] ** 2)) for i in range(3)]


def rate_errors(t: np.ndarray, q: np.ndarray, sigma: np.ndarray, truth: np.ndarray):
    """(error, variance): the comparison's rates of tracked poses q [n_t, n, 3] minus those of
    the truth, and their variance were all of each pose's stated variance (sigma [n_t, n, 3])
    white from frame to frame; units lost in any frame left out."""
    from comparison.metrics import frame_rates, rate_noise_var

    keep = np.all(np.isfinite(q) & np.isfinite(sigma), axis=(0, 2))
    err = frame_rates(t, q[:, keep]) - frame_rates(t, truth[:, keep])
    return err, rate_noise_var(t, sigma[:, keep] ** 2)


def velocity_within_2_sigma(t: np.ndarray, q: np.ndarray, sigma: np.ndarray,
                            truth: np.ndarray, share: float) -> list[float]:
    """Share of the rate errors (`rate_errors`) within 2 standard errors, per component, with
    `share` of each pose's stated variance white from frame to frame."""
    err, var = rate_errors(t, q, sigma, truth)
    return [float(np.mean(np.abs(err[..., i]) < 2.0 * np.sqrt(share * var[..., i])))
            for i in range(3)]


def velocity_error_share(t: np.ndarray, q: np.ndarray, sigma: np.ndarray,
                         truth: np.ndarray) -> list[float]:
    """The share that would make the stated rate noise right on average, per component: the
    mean square of the rate errors (`rate_errors`) over their mean variance at a share of 1."""
    err, var = rate_errors(t, q, sigma, truth)
    return [float(np.mean(err[..., i] ** 2) / np.mean(var[..., i])) for i in range(3)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("runs/bench_dic_design"))
    p.add_argument("--results", type=Path, default=None, help="also copy the JSON here")
    p.add_argument("--duration-s", type=float, default=0.1)
    p.add_argument("--workers", type=int, default=1,
                   help="tracker processes (`metarig track --workers`); each decodes and "
                        "prepares every frame itself, so on 2 cores 1 process with 2 numba "
                        "threads is the cheaper split")
    p.add_argument("--threads", type=int, default=0,
                   help="numba threads per process (0: the cores shared out between them)")
    p.add_argument("--no-neighbours", dest="neighbours", action="store_false",
                   help="track without the check of every pose against its bonded neighbours")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--supersample", type=int, default=SUPERSAMPLE,
                   help="sub-pixel samples per pixel side of the render (pixel integration)")
    p.add_argument("--reference-frames", type=int, default=None,
                   help="frames at rest the reference image averages (default: the rig's)")
    p.add_argument("--design", default=str(DESIGN),
                   help="design file of the sample, or `periodic` for the scene's periodic design "
                        "(the results file is then bench_dic_periodic.json)")
    args = p.parse_args(argv)
    if args.design != "periodic" and not Path(args.design).is_file():
        p.error(f"{args.design}: no such design file")
    from hardware_sim.camera import REFERENCE_FRAMES
    from comparison.metrics import FRAME_NOISE_SHARE

    n_ref = REFERENCE_FRAMES if args.reference_frames is None else args.reference_frames
    if n_ref < 1:
        p.error("--reference-frames must be >= 1")
    from tracking.batch import track_source
    from tracking.dic import settings_for_units
    from tracking.frame_sources import open_source
    from tracking.units import bonds_from_outlines

    fps, mpp = FPS, MPP
    frames = args.out / "frames"
    truth_file = args.out / "truth.npz"
    if truth_file.exists():  # resume: the footage is already there
        truth, stamps, polygons, calib, filmed = load_footage(args.out)
        if filmed != args.supersample:
            p.error(f"{args.out} holds footage rendered at --supersample {filmed}; "
                    f"pass that or another --out")
    else:
        truth, stamps, polygons, calib = film_design(frames, fps, mpp, args.duration_s,
                                                     args.seed, args.design, args.supersample)
        np.savez(truth_file, q=truth, t=stamps, polygons_m=polygons,
                 origin_px=np.asarray(calib.origin_px), supersample=args.supersample)
    cfg = settings_for_units(polygons, mpp)
    ref_path = reference(args.out, n_ref, polygons, calib.origin_px, fps, mpp, args.seed,
                         args.supersample)
    ref = cv2.imread(str(ref_path), cv2.IMREAD_UNCHANGED)
    slender = slender_units(polygons, calib, cfg, ref)
    # the lattice's ligaments, for the check of every pose against its neighbours
    bonds = bonds_from_outlines(polygons) if args.neighbours else None
    load0 = os.getloadavg()
    cpu0 = _cpu_s()
    t0 = time.perf_counter()
    traj, _ = track_source(open_source(frames), polygons, calib, cfg, workers=args.workers,
                           threads=args.threads, bonds=bonds,
                           reference=str(ref_path))
    wall = time.perf_counter() - t0
    cpu = _cpu_s() - cpu0
    e = traj.q - truth
    res = {
        "machine": describe(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "design": _shown(args.design), "frames": int(traj.n_t),
        "units": int(traj.n_units), "slender_units": int(slender.sum()),
        "reference_frames": n_ref, "supersample": args.supersample,
        "bonds": 0 if bonds is None else int(bonds.shape[0]),
        "settings": {"margin_px": cfg.margin_px, "min_points": cfg.min_points,
                     "prefilter_sigma_px": cfg.prefilter_sigma_px,
                     "sigma_floor_px": cfg.sigma_floor_px,
                     "sigma_blur_share": cfg.sigma_blur_share,
                     "neighbour_px": cfg.neighbour_px,
                     "neighbour_static_px": cfg.neighbour_static_px},
        **score(traj.q, traj.sigma, traj.lost, truth, slender, mpp),
        "white_share": white_share(e), "frame_noise_share": FRAME_NOISE_SHARE,
        "velocity_within_2_sigma": velocity_within_2_sigma(traj.t, traj.q, traj.sigma, truth,
                                                           FRAME_NOISE_SHARE),
        "velocity_error_share": velocity_error_share(traj.t, traj.q, traj.sigma, truth),
        "frames_per_s": float(traj.n_t / wall), "workers": args.workers,
        "threads_per_worker": args.threads or max(1, (os.cpu_count() or 1) // args.workers),
        "cpu_ms_per_frame": 1e3 * cpu / traj.n_t,
        "load_average_1min": {"before": load0[0], "after": os.getloadavg()[0]},
    }
    suffix = ("" if n_ref == REFERENCE_FRAMES else f"_ref{n_ref}") \
        + (f"_seed{args.seed}" if args.seed else "")
    np.savez(args.out / f"tracks{suffix}.npz", t=traj.t, q=traj.q, sigma=traj.sigma)
    for d in filter(None, (args.out, args.results)):
        d.mkdir(parents=True, exist_ok=True)
        name = "bench_dic_periodic" if args.design == "periodic" else "bench_dic_design"
        (d / f"{name}{suffix}.json").write_text(json.dumps(res, indent=2))
    rows = [("unit-frames wrong without a flag (target 0)", res["wrong_without_flag"]),
            ("  wrong and not lost (sigma not counted)", res["wrong_not_lost"]),
            ("p99 position error, px (<= 0.1)", f"{res['p99_position_px']:.3f}"),
            ("p99 rotation error, mrad (<= 3)", f"{res['p99_rotation_mrad']:.2f}"),
            ("  rotation, slender / other units, mrad",
             " / ".join("-" if v is None else f"{v:.2f}" for v in
                        (res["p99_rotation_mrad_slender"], res["p99_rotation_mrad_other"]))),
            ("  all tracked: px / mrad", f"{res['p99_position_px_all_tracked']:.3f} / "
                                        f"{res['p99_rotation_mrad_all_tracked']:.2f}"),
            ("lost unit-frames (<= 2 %)", f"{100 * res['lost_share']:.2f} %"),
            (f"  of the {res['slender_units']} slender units", f"{100 * res['lost_share_slender']:.2f} %"),
            ("  of the others", f"{100 * res['lost_share_other']:.2f} %"),
            ("uncertain unit-frames (slender / others)",
             f"{100 * res['uncertain_share_slender']:.2f} / "
             f"{100 * res['uncertain_share_other']:.2f} %"),
            ("within 2 sigma x / y / theta (~95 %)",
             " / ".join(f"{100 * v:.1f}" for v in res["within_2_sigma"])),
            (f"white share x / y / theta ({FRAME_NOISE_SHARE:.2f})",
             " / ".join(f"{v:.2f}" for v in res["white_share"])),
            ("velocity within 2 sigma x / y / theta (~95 %)",
             " / ".join(f"{100 * v:.1f}" for v in res["velocity_within_2_sigma"])),
            ("tracking speed, frames/s (>= 20)", f"{res['frames_per_s']:.1f}"),
            ("  CPU per frame, all processes, ms", f"{res['cpu_ms_per_frame']:.0f}")]
    for name, v in rows:
        print(f"{name:<46}{v!s:>16}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
