"""Rerun comparison recording: size and write time for a 24 x 16 lattice, and a web-viewer check.

Scene: a 24 x 16 lattice of square units (12 mm on a 15 mm pitch, 384 units), a pulse
travelling along x, 100 samples at 1 kHz after the onset; the "experiment" is the simulation
scaled by 1.15 with one unit lost in one frame. Camera frames are 1076 x 724 uint8 speckle
images (fresh noise per frame, so they compress as real ones would not compress better).

1. Writes `comparison.rrd` with `comparison.rerun_log.write_rrd` three ways: no frames, raw
   (lossless) frames, JPEG-90 frames; reports the file size and the write time of each.
2. Unless `--no-view`: serves the JPEG one with `rerun --web-viewer`, opens it in headless
   Chromium (selenium + chromedriver, SwiftShader WebGL), waits for the blueprint's views to
   draw and saves a screenshot (`<out>/rerun_comparison.png`). It then checks from the pixels
   that the page is not blank and which view areas hold drawn content (the viewer is an egui
   canvas, so view titles are not in the DOM). The viewer is stopped afterwards.

Writes `<out>/bench_rerun_view.json`. Needs `chromium`, `chromedriver` and `selenium` for 2.
"""

import argparse
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from comparison.metrics import compare
from comparison.plots import window_samples
from comparison.rerun_log import write_rrd
from metarig.polygon import points_inside
from metarig.trajectory import Trajectory

log = logging.getLogger("bench_rerun_view")

PITCH_M, SIDE_M = 0.015, 0.012
M_PER_PX, ORIGIN_PX = 3.5e-4, (57.0, 667.0)  # the lattice fills the frame
FRAME_HW = (724, 1076)
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-gpu-sandbox",
    "--disable-dev-shm-usage",
)
WINDOW = (1600, 1000)


def lattice(nx: int, ny: int) -> np.ndarray:
    """[nx * ny, 4, 2] counter-clockwise squares, row-major with x fastest, m."""
    cx, cy = np.meshgrid(np.arange(nx) * PITCH_M, np.arange(ny) * PITCH_M)
    c = np.stack([cx.ravel(), cy.ravel()], axis=-1)
    h = SIDE_M / 2
    return c[:, None, :] + np.array([[-h, -h], [h, -h], [h, h], [-h, h]])


def synthetic_case(
    nx: int = 24, ny: int = 16, n_frames: int = 100, fps: float = 1000.0, onset_s: float = 0.005
):
    """A comparison of a travelling pulse with a 15 % louder copy of itself (one unit lost)."""
    polys = lattice(nx, ny)
    n = len(polys)
    n_before = round(onset_s * fps)
    t = np.arange(n_before + n_frames) / fps
    x = polys.mean(axis=1)[:, 0]

    def wave(scale):
        tau = np.clip(t[:, None] - onset_s - x[None, :] / 8.0, 0.0, None)
        s = np.sin(2 * np.pi * 25 * tau) * (tau > 0) * np.exp(-x / 0.4)[None, :]
        q = np.zeros((len(t), n, 3))
        q[..., 0], q[..., 2] = scale * 1.5e-3 * s, scale * 3e-2 * s
        return q

    lost = np.zeros((len(t), n), bool)
    lost[len(t) // 2, nx + 3] = True
    q_exp = wave(1.15)
    q_exp[lost] = np.nan
    exp = Trajectory.from_positions(t, q_exp, lost=lost)
    sim = Trajectory.from_positions(t, wave(1.0))
    target = np.array([n - nx // 2 - 1, n - nx // 2])
    c = compare(exp, sim, np.full(n, 2e-3), np.full(n, 5e-8), target, np.arange(nx), onset_s)
    return c, polys, window_samples(c, t, exp.q), window_samples(c, t, sim.q), target


def speckle_frames(polys: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """[n, H, W] uint8: speckled units at their reference place on a dark background, with
    fresh sensor noise in every frame (a backdrop, not a DIC-grade render)."""
    rng = np.random.default_rng(seed)
    h, w = FRAME_HW
    rows, cols = np.arange(h)[:, None], np.arange(w)[None, :]
    x, y = (cols - ORIGIN_PX[0]) * M_PER_PX, (ORIGIN_PX[1] - rows) * M_PER_PX
    inside = np.zeros((h, w), bool)
    for p in polys:
        inside |= points_inside(x, y, p)
    base = np.where(inside, 60 + 150 * (rng.random((h, w)) > 0.5), 25).astype(np.float64)
    noise = rng.normal(0.0, 6.0, size=(n, h, w))
    return np.clip(base[None] + noise, 0, 255).astype(np.uint8)


def measure_writes(out: Path, nx: int, ny: int, n_frames: int) -> dict:
    """Write the recording without frames, with raw frames and with JPEG frames; size, time."""
    c, polys, q_exp, q_sim, target = synthetic_case(nx, ny, n_frames)
    frames = speckle_frames(polys, len(c.t))
    cam = {"frames": frames, "m_per_px": M_PER_PX, "origin_px": ORIGIN_PX}
    variants = {"no_frames": {}, "raw_frames": cam, "jpeg90_frames": {**cam, "jpeg_quality": 90}}
    results = {"units": len(polys), "samples": len(c.t), "frame_hw": list(FRAME_HW)}
    for name, kw in variants.items():
        path = out / f"comparison_{name}.rrd"
        t0 = time.perf_counter()
        write_rrd(path, c, polys, q_exp, q_sim, target, recording_id=f"bench-{name}", **kw)
        results[name] = {
            "seconds": round(time.perf_counter() - t0, 3),
            "mbytes": round(path.stat().st_size / 1e6, 2),
            "path": str(path),
        }
        log.info("%-14s %6.2f MB  %5.2f s", name, results[name]["mbytes"], results[name]["seconds"])
    return results


def _wait_http(url: str, timeout_s: float) -> None:
    import urllib.request

    end = time.monotonic() + timeout_s
    while True:
        try:
            urllib.request.urlopen(url, timeout=2).close()
            return
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.3)


def view_content(img: np.ndarray) -> dict:
    """Which view areas of the blueprint hold drawn content, from a screenshot [H, W, 3] uint8.

    The areas are the blueprint's layout (lattice views side by side over the curves and the
    summary) in the viewer's window. A lattice view counts when >= 0.5 % of its area has the
    colours of the speed map (within 25 levels of a viridis sample, and saturated) and it shows
    magenta target outlines (>= 10 pixels); the camera view when its grey levels vary
    (std > 20); the target-energy view when it holds red and blue curve pixels; a curve or text
    view otherwise when >= 0.3 % of its pixels stand out from its background by 40 levels.
    """
    from matplotlib import colormaps

    from comparison.plots import SPEED_CMAP

    h, w = img.shape[:2]
    f = img.astype(np.float64)
    palette = colormaps[SPEED_CMAP](np.linspace(0, 1, 64))[:, :3] * 255

    def near(region, rgb, tol):
        return np.linalg.norm(region[..., None, :] - np.asarray(rgb, float), axis=-1).min(-1) < tol

    top, bottom = (int(0.08 * h), int(0.58 * h)), (int(0.66 * h), int(0.92 * h))
    fractions, drawn = {}, {}
    for i, name in enumerate(("experiment", "simulation", "camera")):
        region = f[top[0] : top[1], int(i * w / 3) + 8 : int((i + 1) * w / 3) - 8]
        if name == "camera":
            fractions[name] = float(region.mean(axis=-1).std())
            drawn[name] = fractions[name] > 20
            continue
        sub = region[::2, ::2]  # every other pixel: enough for a fraction, 4x cheaper
        colour = near(sub, palette, 25) & (sub.max(axis=-1) - sub.min(axis=-1) > 40)
        magenta = int(near(region, [(255, 0, 255)], 60).sum())
        fractions[name] = float(colour.mean())
        fractions[f"{name}_magenta_px"] = magenta
        drawn[name] = fractions[name] > 0.005 and magenta >= 10
    for i, name in enumerate(("target_ke", "velocity_error", "displacement_error", "summary")):
        region = f[bottom[0] : bottom[1], int(i * w / 4) + 8 : int((i + 1) * w / 4) - 8]
        grey = region.mean(axis=-1)
        fractions[name] = float((np.abs(grey - np.median(grey)) > 40).mean())
        drawn[name] = fractions[name] > 0.003
        if name == "target_ke":
            reds = int(near(region, [(214, 39, 40)], 70).sum())
            blues = int(near(region, [(31, 119, 180)], 70).sum())
            fractions["target_ke_red_blue_px"] = [reds, blues]
            drawn[name] = drawn[name] and reds >= 20 and blues >= 20
    return {"fractions": fractions, "drawn": drawn}


def screenshot_rrd(
    rrd: str | Path,
    png: str | Path,
    web_port: int = 9190,
    grpc_port: int = 9877,
    settle_s: float = 12.0,
) -> dict:
    """Serve `rrd` in the Rerun web viewer, screenshot it in headless Chromium, check it.

    Args:
        png: where the full-size screenshot goes.

    Returns:
        {"title" (of the page), "nonblank", "views_with_content" (of 7), "drawn" (per view),
        "fractions" (the measures behind it, see `view_content`), "seconds", "png"}.
    """
    from PIL import Image
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    rerun = Path(sys.executable).with_name("rerun")
    cmd = [
        str(rerun),
        "--web-viewer",
        "--bind",
        "127.0.0.1",
        "--web-viewer-port",
        str(web_port),
        "--port",
        str(grpc_port),
        "--renderer",
        "webgl",
        str(rrd),
    ]
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    viewer = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True, env=env
    )
    driver = None
    t0 = time.perf_counter()
    try:
        _wait_http(f"http://127.0.0.1:{web_port}/", 30.0)
        opts = webdriver.ChromeOptions()
        opts.binary_location = shutil.which("chromium") or "chromium"
        for flag in CHROMIUM_FLAGS:
            opts.add_argument(flag)
        opts.add_argument(f"--window-size={WINDOW[0]},{WINDOW[1]}")
        driver = webdriver.Chrome(
            options=opts, service=Service(shutil.which("chromedriver") or "chromedriver")
        )
        driver.get(
            f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy"
        )
        time.sleep(settle_s)  # wasm start, data load over gRPC, first frames of the views
        png = Path(png)
        png.parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(png))
        title = driver.title
    finally:
        if driver is not None:
            driver.quit()
        if viewer.poll() is None:
            os.killpg(viewer.pid, signal.SIGTERM)  # the group this function started
            try:
                viewer.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(viewer.pid, signal.SIGKILL)
                viewer.wait(10)
    img = np.asarray(Image.open(png).convert("RGB"))
    checks = view_content(img)
    return {
        "title": title,
        "nonblank": bool(img.std() > 10),
        "views_with_content": int(sum(checks["drawn"].values())),
        **checks,
        "seconds": round(time.perf_counter() - t0, 1),
        "png": str(png),
    }


def save_small(png: Path, dest: Path) -> None:
    """A 3/4-size, 128-colour copy of a screenshot (for the results folder)."""
    from PIL import Image

    img = Image.open(png).convert("RGB")
    img = img.resize((img.width * 3 // 4, img.height * 3 // 4))
    img.quantize(colors=128).save(dest, optimize=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--nx", type=int, default=24)
    parser.add_argument("--ny", type=int, default=16)
    parser.add_argument("--num-frames", type=int, default=100)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--no-view", action="store_true", help="skip the web-viewer check")
    parser.add_argument("--settle-s", type=float, default=12.0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        results = measure_writes(Path(tmp), args.nx, args.ny, args.num_frames)
        if not args.no_view:
            if not (shutil.which("chromium") and shutil.which("chromedriver")):
                log.warning("chromium / chromedriver not found: no viewer check")
            else:
                shot = Path(tmp) / "screenshot.png"
                view = screenshot_rrd(
                    results["jpeg90_frames"]["path"], shot, settle_s=args.settle_s
                )
                save_small(shot, args.out / "rerun_comparison.png")
                view["png"] = "rerun_comparison.png"
                results["viewer"] = view
                log.info(
                    "viewer: nonblank=%s, views drawn=%d/7 %s",
                    view["nonblank"],
                    view["views_with_content"],
                    view["drawn"],
                )
        for v in results.values():
            if isinstance(v, dict):
                v.pop("path", None)
    (args.out / "bench_rerun_view.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
