"""Rerun comparison recording: size and write time for a 24 x 16 lattice, and a web-viewer check.

Scene: a 24 x 16 lattice of square units (12 mm on a 15 mm pitch, 384 units), a pulse
travelling along x, 100 samples at 1 kHz after the onset; the "experiment" is the simulation
scaled by 1.15 with one unit lost in one frame. Camera frames are 1076 x 724 uint8 speckle
images (fresh noise per frame, so they compress as real ones would not compress better).

1. Writes `comparison.rrd` with `comparison.rerun_log.write_rrd` three ways: no frames, raw
   (lossless) frames, JPEG-90 frames; reports the file size and the write time of each.
2. Unless `--no-view`: serves the web viewer with `rerun --web-viewer` and the JPEG one over
   plain HTTP, opens it in headless Chromium (selenium + chromedriver, SwiftShader WebGL),
   screenshots it until every view of the blueprint has drawn (or a time-out) and saves the
   last screenshot (`<out>/rerun_comparison.png`). The checks are made on the pixels: the page
   is not blank, and which view areas hold drawn content (the viewer is an egui canvas, so view
   titles are not in the DOM). The viewer and the browser are stopped afterwards.

Writes `<out>/bench_rerun_view.json`. Needs selenium (`pip install -e ".[dev]"`) and, for 2,
Chromium and its driver (Debian/Ubuntu: `apt-get install chromium chromium-driver`).
"""

import argparse
import functools
import http.server
import io
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path

import numpy as np

from comparison.metrics import compare
from comparison.plots import window_samples
from comparison.rerun_log import EXP_RGBA, SIM_RGBA, TARGET_RGBA, write_rrd
from metarig.polygon import points_inside
from metarig.trajectory import Trajectory

log = logging.getLogger("bench_rerun_view")

PITCH_M, SIDE_M = 0.015, 0.012
M_PER_PX, ORIGIN_PX = 3.5e-4, (57.0, 667.0)  # the lattice fills the frame
FRAME_HW = (724, 1076)
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    # WebGL on the CPU (SwiftShader through ANGLE): the same pixels with or without a GPU
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-gpu-sandbox",
    "--disable-dev-shm-usage",
    "--force-device-scale-factor=1",
    # nothing beside the page: no updates, sync, extensions, first-run or browser checks
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-default-apps",
    "--no-first-run",
    "--no-default-browser-check",
    "--mute-audio",
)
WINDOW = (1600, 1000)
# the curve colours of `comparison.rerun_log`: target energy experiment (red), simulation
# (blue); the largest displacement error (orange)
CURVE_RGB = {
    "target_ke": {"red_blue": (EXP_RGBA[:3], SIM_RGBA[:3])},
    "displacement_error": {"orange": ((255, 127, 14),)},
}
INSTALL_BROWSER = "apt-get install chromium chromium-driver"
INSTALL_SELENIUM = 'pip install -c constraints.txt -e ".[dev]"'


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


def find_browser() -> tuple[str | None, str | None, str]:
    """(chromium, chromedriver, why not): the paths on PATH or in /usr/bin, and when one of
    them (or selenium) is missing, what to install; `why not` is "" when all are there."""
    found = {}
    for name in ("chromium", "chromedriver"):
        found[name] = shutil.which(name) or shutil.which(name, path="/usr/bin")
    missing = [name for name, path in found.items() if path is None]
    reasons = []
    if missing:
        reasons.append(
            f"{' and '.join(missing)} not found on PATH or in /usr/bin "
            f"(Debian/Ubuntu: {INSTALL_BROWSER})"
        )
    try:
        import selenium  # noqa: F401
    except ImportError:
        reasons.append(f"selenium not installed ({INSTALL_SELENIUM}, or make install)")
    return found["chromium"], found["chromedriver"], "; ".join(reasons)


class _FileHandler(http.server.SimpleHTTPRequestHandler):
    """Serves one folder to the viewer page, which comes from another port (so CORS)."""

    def end_headers(self):
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, *args):
        pass


VIEWS = (
    "experiment",
    "simulation",
    "camera",
    "target_ke",
    "velocity_error",
    "displacement_error",
    "summary",
)


def view_regions(h: int, w: int) -> dict:
    """{view: (row0, row1, col0, col1)}: where each view of the blueprint draws in a screenshot
    of h x w pixels (lattice views and camera side by side over the curves and the summary)."""
    top, bottom = (int(0.08 * h), int(0.58 * h)), (int(0.66 * h), int(0.92 * h))
    regions = {}
    for i, name in enumerate(VIEWS[:3]):
        regions[name] = (*top, int(i * w / 3) + 8, int((i + 1) * w / 3) - 8)
    for i, name in enumerate(VIEWS[3:]):
        regions[name] = (*bottom, int(i * w / 4) + 8, int((i + 1) * w / 4) - 8)
    return regions


def view_content(img: np.ndarray) -> dict:
    """Which view areas of the blueprint hold drawn content, from a screenshot [H, W, 3] uint8.

    The areas are the blueprint's layout (lattice views side by side over the curves and the
    summary) in the viewer's window. A lattice view counts when >= 0.5 % of its area has the
    colours of the speed map (within 25 levels of a viridis sample, and saturated) and it shows
    magenta target outlines (>= 10 pixels); the camera view when its grey levels vary
    (std > 20); a curve or text view when >= 0.3 % of its pixels stand out from its background
    by 40 levels and, for the target-energy view, red and blue curves (the displacement-error
    view: an orange curve) that each span >= 25 % of the view's width (>= 20 pixels each; a
    legend's colour dot alone spans a few %).
    """
    from matplotlib import colormaps

    from comparison.plots import SPEED_CMAP

    h, w = img.shape[:2]
    f = img.astype(np.float64)
    palette = colormaps[SPEED_CMAP](np.linspace(0, 1, 64))[:, :3] * 255

    def near(region, rgb, tol):  # within `tol` (Euclidean, RGB levels) of any of the colours
        rgb = np.asarray(rgb, float)
        d2 = (region * region).sum(-1)[..., None] - 2 * region @ rgb.T + (rgb * rgb).sum(-1)
        return d2.min(-1) < tol * tol

    regions = view_regions(h, w)
    fractions, drawn = {}, {}
    for name in VIEWS[:3]:
        r0, r1, c0, c1 = regions[name]
        region = f[r0:r1, c0:c1]
        if name == "camera":
            fractions[name] = float(region.mean(axis=-1).std())
            drawn[name] = fractions[name] > 20
            continue
        sub = region[::2, ::2]  # every other pixel: enough for a fraction, 4x cheaper
        colour = near(sub, palette, 25) & (sub.max(axis=-1) - sub.min(axis=-1) > 40)
        magenta = int(near(region, [TARGET_RGBA[:3]], 60).sum())
        fractions[name] = float(colour.mean())
        fractions[f"{name}_magenta_px"] = magenta
        drawn[name] = fractions[name] > 0.005 and magenta >= 10
    for name in VIEWS[3:]:
        r0, r1, c0, c1 = regions[name]
        region = f[r0:r1, c0:c1]
        grey = region.mean(axis=-1)
        fractions[name] = float((np.abs(grey - np.median(grey)) > 40).mean())
        drawn[name] = fractions[name] > 0.003
        for key, rgbs in CURVE_RGB.get(name, {}).items():
            lines = [near(region, [rgb], 70) for rgb in rgbs]
            fractions[f"{name}_{key}_px"] = [int(m.sum()) for m in lines]
            fractions[f"{name}_{key}_width"] = [round(float(m.any(0).mean()), 3) for m in lines]
            drawn[name] = drawn[name] and all(
                m.sum() >= 20 and m.any(0).mean() >= 0.25 for m in lines
            )
    return {"fractions": fractions, "drawn": drawn}


def screenshot_rrd(
    rrd: str | Path,
    png: str | Path,
    web_port: int = 9190,
    timeout_s: float = 120.0,
    window: tuple[int, int] = WINDOW,
) -> dict:
    """Open `rrd` in the Rerun web viewer in headless Chromium and screenshot it until every
    view of its blueprint has drawn (`view_content`) or `timeout_s` has passed.

    `rerun --web-viewer` serves the viewer; the .rrd goes to it over plain HTTP from a server
    in this process (a file given to `rerun` itself is polled for growth, which keeps a core
    busy). Chromium starts with a fresh profile that is removed afterwards.

    Args:
        png: where the last full-size screenshot goes.

    Returns:
        {"title" (of the page), "nonblank", "views_with_content" (of 7), "drawn" (per view),
        "fractions" (the measures behind it, see `view_content`), "started" (the viewer app
        ran), "start_s" (when, from the viewer's launch), "shots" (taken), "panic" (the
        viewer's panic message, or ""), "seconds" (in all), "png"}.
    """
    from PIL import Image
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    chromium, chromedriver, missing = find_browser()
    if missing:
        raise RuntimeError(missing)
    rrd, png = Path(rrd).resolve(), Path(png)
    rerun = Path(sys.executable).with_name("rerun")
    files = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(_FileHandler, directory=str(rrd.parent))
    )
    threading.Thread(target=files.serve_forever, daemon=True).start()
    rrd_url = f"http://127.0.0.1:{files.server_address[1]}/{urllib.parse.quote(rrd.name)}"
    # given a URL the web viewer can read itself, rerun serves the viewer only (no gRPC server)
    cmd = [str(rerun), "--web-viewer", "--bind", "127.0.0.1", "--web-viewer-port", str(web_port)]
    cmd.append(rrd_url)
    # BROWSER=true: rerun would open the page in the desktop's browser too
    env = {**os.environ, "RERUN_ANALYTICS": "0", "BROWSER": "true"}
    viewer_log = tempfile.TemporaryFile()  # noqa: SIM115 (closed in the finally below)
    viewer = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=viewer_log, start_new_session=True, env=env
    )
    profile = tempfile.TemporaryDirectory(prefix="metarig-chromium-")
    driver = None
    t0 = time.perf_counter()
    img, checks, shots, started, start_s, panic = None, None, 0, False, None, ""
    try:
        try:
            _wait_http(f"http://127.0.0.1:{web_port}/", 30.0)
        except OSError as e:
            viewer_log.seek(0)
            tail = viewer_log.read().decode(errors="replace")[-2000:]
            raise RuntimeError(f"rerun --web-viewer did not serve: {e}\n{tail}") from None
        opts = webdriver.ChromeOptions()
        opts.binary_location = chromium
        for flag in CHROMIUM_FLAGS:
            opts.add_argument(flag)
        opts.add_argument(f"--user-data-dir={profile.name}")
        opts.add_argument(f"--window-size={window[0]},{window[1]}")
        driver = webdriver.Chrome(options=opts, service=Service(chromedriver))
        # the viewer logs its shader compiler at debug level (~17k messages), each one sent on
        # to chromedriver: dropping them saves most of the browser's and the driver's CPU time
        driver.execute_cdp_cmd(
            "Page.addScriptToEvaluateOnNewDocument", {"source": "console.debug = () => {};"}
        )
        query = urllib.parse.urlencode({"url": rrd_url, "renderer": "webgl"})
        driver.get(f"http://127.0.0.1:{web_port}/?{query}")
        deadline = time.monotonic() + timeout_s
        # the page sets window._handle once the wasm app runs: no screenshot before (a
        # screenshot waits for a frame, which costs the browser while it compiles)
        while time.monotonic() < deadline:
            state = driver.execute_script(
                "const h = window._handle;"
                "return h ? (h.has_panicked() ? 'panic: ' + h.panic_message() : 'ok') : '';"
            )
            if state:
                started, panic = True, state.removeprefix("panic: ") if state != "ok" else ""
                start_s = time.perf_counter() - t0
                break
            time.sleep(0.5)
        while not panic:
            img = np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))
            shots += 1
            checks = view_content(img)
            if all(checks["drawn"].values()) or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        title = driver.title
        if img is None:
            img = np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))
            checks = view_content(img)
    finally:
        if driver is not None:
            driver.quit()
        files.shutdown()
        files.server_close()
        profile.cleanup()
        viewer_log.close()
        if viewer.poll() is None:
            os.killpg(viewer.pid, signal.SIGTERM)  # the group this function started
            try:
                viewer.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(viewer.pid, signal.SIGKILL)
                viewer.wait(10)
    png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(png)
    return {
        "title": title,
        "nonblank": bool(img.std() > 10),
        "views_with_content": int(sum(checks["drawn"].values())),
        **checks,
        "started": started,
        "start_s": None if start_s is None else round(start_s, 1),
        "shots": shots,
        "panic": panic,
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
    parser.add_argument(
        "--timeout-s", type=float, default=120.0, help="longest wait for every view to draw"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        results = measure_writes(Path(tmp), args.nx, args.ny, args.num_frames)
        if not args.no_view:
            missing = find_browser()[2]
            if missing:
                log.warning("no viewer check: %s", missing)
            else:
                shot = Path(tmp) / "screenshot.png"
                view = screenshot_rrd(
                    results["jpeg90_frames"]["path"], shot, timeout_s=args.timeout_s
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
