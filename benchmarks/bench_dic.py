"""DIC tracker benchmark: accuracy on exact synthetic speckle, and throughput for 384 units.

Scene: a 24 x 16 lattice of square units, 37 px wide on a 44 px pitch (1076 x 724 frames),
each with its own speckle (Gaussian blobs of 1 px radius), rendered by `hardware_sim.camera`
with pixel integration, so the poses it was given are exact. The units move in a smooth wave
(centroid +-1.5 px / +-1 px, rotation +-0.05 rad around a reference-frame offset, i.e. up to
0.1 rad from the reference) so neighbours never overlap.

1. Accuracy, per condition (clean; 2 % Gaussian noise + 0.7 px Gaussian blur): RMS position
   error (px) and RMS rotation error (mrad) over all units and frames after the reference,
   and the count of lost unit-frames (none are occluded, so any is a failure).
2. Throughput: frames/s of `metarig track`'s engine on the noisy sequence stored as PNG files
   (decode + tracking), in a fresh process pinned to 1 or 2 CPUs: 1 core; 2 cores as numba
   threads in one process; 2 cores as two worker processes. Also the CPU time per frame
   (independent of how busy the shared machine is) and how many of the 2 cores a spinning
   process actually got while timing. For scale, plain per-unit OpenCV ECC
   (`findTransformECC`, Euclidean, 1 core) on the same subsets.

Writes `<out>/bench_dic.json` and `--results` (default `benchmarks/results/bench_dic.json`, the
file the README quotes) and prints a table. `--no-throughput` measures the accuracy only. The
machine has 2 cores shared with other work, so rates vary with load.
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from hardware_sim.camera import (
    CameraConfig,
    make_speckle_textures,
    render_frame,
    square_lattice_polygons,
)
from metarig.polygon import area_centroids
from tracking.batch import run_tracking
from tracking.calibration import Calibration
from tracking.dic import DICConfig, DICTracker, init_state, track_frame
from tracking.frame_sources import open_source

PITCH_PX, SIDE_PX, NX, NY = 44, 37, 24, 16
MPP = 0.015 / PITCH_PX  # 15 mm pitch


def make_scene(noise: float, blur: float):
    w, h = NX * PITCH_PX + 20, NY * PITCH_PX + 20
    cfg = CameraConfig(width_px=w, height_px=h, m_per_px=MPP, origin_px=(10.0, h - 10.0),
                       speckle_sigma_m=1.0 * MPP, speckle_fill=0.7, unit_level=20.0,
                       speckle_level=230.0, supersample=3, noise_std=noise,
                       blur_sigma_px=blur)
    half = PITCH_PX * MPP / 2
    polys = square_lattice_polygons(NX, NY, PITCH_PX * MPP, SIDE_PX * MPP, (half, half))
    return cfg, polys


def wave(polys: np.ndarray, k: int) -> np.ndarray:
    """[n, 3] true poses at frame k (m, m, rad); zero at k = 0."""
    c = area_centroids(polys) / (PITCH_PX * MPP)
    ph = 2 * np.pi * (c[:, 0] / 8 + c[:, 1] / 11)
    om = 2 * np.pi * k / 30

    def s(a):
        return np.sin(om + ph + a) - np.sin(ph + a)

    return np.stack([1.5 * MPP * s(0.0), 1.0 * MPP * s(1.0), 0.05 * s(2.0)], axis=1)


def render(cfg, polys, n_t: int, seed: int):
    rng = np.random.default_rng(seed)
    tex = make_speckle_textures(polys, cfg, rng)
    truth = np.array([wave(polys, k) for k in range(n_t)])
    t0 = time.perf_counter()
    frames = [render_frame(cfg, polys, truth[k], tex, rng) for k in range(n_t)]
    return frames, truth, (time.perf_counter() - t0) / n_t


def accuracy(frames, truth, calib, polys) -> dict:
    import numba

    numba.set_num_threads(1)
    tr = DICTracker(polys, calib, DICConfig())
    st = init_state(tr, frames[0])
    q, lost = [], []
    t0 = time.perf_counter()
    for f in frames:
        st, fp = track_frame(tr, st, f)
        q.append(fp.q)
        lost.append(fp.lost)
    dt = time.perf_counter() - t0
    e = (np.array(q) - truth)[1:]
    return {
        "pos_rms_px": float(np.sqrt(np.nanmean((e[..., :2] ** 2).sum(-1))) / MPP),
        "rot_rms_mrad": float(np.sqrt(np.nanmean(e[..., 2] ** 2)) * 1e3),
        "pos_max_px": float(np.nanmax(np.hypot(e[..., 0], e[..., 1])) / MPP),
        "lost_unit_frames": int(np.array(lost).sum()),
        "frames": len(frames),
        "in_memory_fps_1core": len(frames) / dt,
    }


def ecc_baseline(frames, calib, polys, n_frames: int = 3) -> float:
    """Frames/s of plain per-unit cv2.findTransformECC (Euclidean) on the same subsets."""
    tr = DICTracker(polys, calib, DICConfig())
    st = init_state(tr, frames[0])
    refs = st.refs
    ref = frames[0].astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    t0 = time.perf_counter()
    for f in frames[1 : 1 + n_frames]:
        img = f.astype(np.float32)
        for b in range(refs.n):
            cx, cy = np.rint(refs.centre_px[b]).astype(int)
            r = int(refs.rmax[b] / np.sqrt(2))  # the square inside the subset
            tpl = ref[cy - r : cy + r + 1, cx - r : cx + r + 1]
            pad = 8
            win = img[cy - r - pad : cy + r + pad + 1, cx - r - pad : cx + r + pad + 1]
            warp = np.array([[1, 0, pad], [0, 1, pad]], np.float32)
            try:
                cv2.findTransformECC(tpl, win, warp, cv2.MOTION_EUCLIDEAN, crit, None, 5)
            except cv2.error:
                pass
    return n_frames / (time.perf_counter() - t0)


def write_pngs(frames, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        p = folder / f"f{i:05d}.png"
        if not p.exists():
            cv2.imwrite(str(p), f)
    return folder


def _throughput_child(folder: str, workers: int, threads: int) -> dict:
    """Run inside a CPU-pinned child: time `metarig track`'s engine on the PNG folder."""
    import resource

    cfg, polys = make_scene(0.02, 0.7)
    calib = Calibration(fps=cfg.fps, m_per_px=MPP, origin_px=cfg.origin_px, y_up=True)
    spec = open_source(folder)
    run_tracking(spec, polys, calib, DICConfig(), workers=1, threads=threads, max_frames=2)
    t0, c0 = time.perf_counter(), time.process_time()
    res = run_tracking(spec, polys, calib, DICConfig(), workers=workers, threads=threads)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0 + resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime
    assert res.complete
    n = res.q.shape[0]
    return {"fps": n / wall, "cpu_ms_per_frame": 1e3 * cpu / n, "frames": n}


def throughput(folder: Path, cores: int, workers: int, threads: int) -> dict:
    """frames/s of the tracker pinned to `cores` CPUs (fresh process, so pinning holds)."""
    cpus = sorted(os.sched_getaffinity(0))[:cores]
    cmd = [sys.executable, __file__, "--child", str(folder), str(workers), str(threads)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True,
                         preexec_fn=lambda: os.sched_setaffinity(0, cpus))
    r = json.loads(out.stdout.strip().splitlines()[-1])
    r.update(cores=cores, workers=workers, threads=threads)
    return r


def cores_available(cores: int = 2) -> float:
    """How many cores this process really gets now (pure-Python spin in `cores` processes)."""
    code = ("import time\nt=time.perf_counter()\nc=time.process_time()\n"
            "x=sum(range(30_000_000))\nprint((time.process_time()-c)/(time.perf_counter()-t))")
    cmd = [sys.executable, "-c", code]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True) for _ in range(cores)]
    return float(sum(float(p.communicate()[0]) for p in procs))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        print(json.dumps(_throughput_child(argv[1], int(argv[2]), int(argv[3]))))
        return 0
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", default="runs/bench_dic", help="output folder")
    p.add_argument("--frames", type=int, default=30, help="frames per accuracy condition")
    p.add_argument("--timing-frames", type=int, default=60, help="frames for throughput")
    p.add_argument("--no-ecc", action="store_true", help="skip the ECC baseline")
    p.add_argument("--no-throughput", action="store_true",
                   help="accuracy only (no PNG decoding, pinned processes or ECC)")
    p.add_argument("--results", type=Path,
                   default=Path(__file__).resolve().parent / "results" / "bench_dic.json",
                   help="copy of the JSON kept with the repository")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result: dict = {"scene": {"units": NX * NY, "unit_px": SIDE_PX, "pitch_px": PITCH_PX,
                              "frame": [NX * PITCH_PX + 20, NY * PITCH_PX + 20],
                              "speckle_sigma_px": 1.0}, "cpu_count": os.cpu_count()}
    conditions = {"clean": (0.0, 0.0), "noise2%+blur0.7px": (0.02, 0.7)}
    noisy = None
    for name, (noise, blur) in conditions.items():
        cfg, polys = make_scene(noise, blur)
        calib = Calibration(fps=cfg.fps, m_per_px=MPP, origin_px=cfg.origin_px, y_up=True)
        n_t = (max(args.frames, args.timing_frames) if noise and not args.no_throughput
               else args.frames)
        frames, truth, render_s = render(cfg, polys, n_t, seed=1)
        acc = accuracy(frames[: args.frames], truth[: args.frames], calib, polys)
        acc["render_s_per_frame"] = render_s
        result[name] = acc
        print(f"{name}: {acc}", file=sys.stderr)
        if noise:
            noisy = (frames, calib, polys)
    rates = {}
    if not args.no_throughput:
        frames, calib, polys = noisy
        folder = write_pngs(frames, out / "frames_noisy")
        result["cores_available_during_timing"] = cores_available()
        for cores, workers, threads in ((1, 1, 1), (2, 1, 2), (2, 2, 1)):
            r = throughput(folder, cores, workers, threads)
            rates[f"{cores}_core_{workers}proc_{threads}thr"] = r
            print(f"throughput {r}", file=sys.stderr)
        if not args.no_ecc:
            rates["ecc_per_unit_1_core"] = {"fps": ecc_baseline(frames, calib, polys)}
        result["throughput_fps"] = rates
    result["load_average_end"] = os.getloadavg()
    (out / "bench_dic.json").write_text(json.dumps(result, indent=2))
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(result, indent=2) + "\n")

    print("\naccuracy (384 units, 37 px, frames after the reference)")
    print(f"{'condition':<20}{'pos RMS px':>12}{'rot RMS mrad':>14}{'lost':>6}{'max px':>9}")
    for name in conditions:
        a = result[name]
        print(f"{name:<20}{a['pos_rms_px']:>12.4f}{a['rot_rms_mrad']:>14.3f}"
              f"{a['lost_unit_frames']:>6d}{a['pos_max_px']:>9.4f}")
    if rates:
        print("\nthroughput (384 units, noisy frames, PNG decode included; cores = CPUs pinned)")
        print(f"{'setting':<26}{'frames/s':>10}{'CPU ms/frame':>14}")
        for k, v in rates.items():
            print(f"{k:<26}{v['fps']:>10.1f}{v.get('cpu_ms_per_frame', float('nan')):>14.1f}")
        print(f"{'in-memory tracker, 1 thr':<26}"
              f"{result['noise2%+blur0.7px']['in_memory_fps_1core']:>10.1f}")
        print(f"cores really available while timing (of 2): "
              f"{result['cores_available_during_timing']:.2f}")
    print(f"\nwritten {out / 'bench_dic.json'} and {args.results}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
