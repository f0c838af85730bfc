"""`metarig track`: DIC-track every unit in a folder of images, a video or an MCAP recording.

Parallel over units on all cores: within a process the units of a frame are solved on numba
threads while a reader thread decodes and prepares the next frame; with `--workers N` the unit
ids are also split into N contiguous blocks, one per process, each reading the frames itself.
Every path runs the same tracker (`ros_nodes.logic.dic`) as the live node and units are
independent, so results do not depend on the split. Results stream back in blocks of frames;
Ctrl-C stops the workers and writes what every worker has finished.

Output (.npz, the trajectory layout of `metarig simulate`): `t` [n_t] s (k / fps); `q`
[n_t, n_units, 3] (u m, v m, theta rad) from the reference outline, NaN where lost; `qdot`
[n_t, n_units, 3] backward difference (q[k] - q[k-1]) * fps, NaN at k = 0 and next to lost
frames; `quality` [n_t, n_units] ZNCC; `lost` [n_t, n_units] bool; `complete` (False when
interrupted); `fps`.
"""

import argparse
import logging
import multiprocessing as mp
import os
import queue as queue_mod
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numba
import numpy as np

from ros_nodes.logic.calibration import Calibration, CalibrationError, load_calibration
from ros_nodes.logic.dic import (
    DICConfig,
    DICTracker,
    FrameError,
    PreparedFrame,
    all_lost,
    init_state,
    prepare_frame,
    track_frame,
)
from ros_nodes.logic.dic_units import UnitsError, load_unit_polygons
from ros_nodes.logic.frame_sources import (
    BadFrame,
    SourceError,
    SourceSpec,
    count_frames,
    iter_frames,
    open_source,
)

log = logging.getLogger("metarig.track")
_DEFAULTS = DICConfig()


@dataclass(frozen=True, slots=True)
class TrackJob:
    """One worker's share of the tracking.

    Attributes:
        spec: the frame source. polygons_m: [n, nv, 2] outlines of this worker's units (m).
        calib: calibration. cfg: tracker settings.
        reference: image file showing the reference configuration (None: the first frame).
        block: frames per result block. max_frames: stop after this many (0: all).
        threads: numba threads for this job's units (0: leave the process default).
    """

    spec: SourceSpec
    polygons_m: np.ndarray
    calib: Calibration
    cfg: DICConfig
    reference: str | None
    block: int
    max_frames: int
    threads: int = 0


@dataclass(frozen=True, slots=True)
class Block:
    """Results of consecutive frames k0 .. k0 + len - 1 for one worker's units.

    Attributes:
        k0: first frame index. q: [m, n, 3]. quality: [m, n]. lost: [m, n]. bad: [m] bool
        frame unusable (all units lost).
    """

    k0: int
    q: np.ndarray
    quality: np.ndarray
    lost: np.ndarray
    bad: np.ndarray


def _reference_image(job: TrackJob) -> np.ndarray:
    if job.reference is not None:
        img = cv2.imread(job.reference, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SourceError(f"{job.reference}: cannot read the reference image")
        return img
    for _, item in iter_frames(job.spec):
        if isinstance(item, BadFrame):
            raise SourceError(f"{job.spec.path}: the first frame (the reference) is unreadable: "
                              f"{item.reason}")
        return item
    raise SourceError(f"{job.spec.path}: holds no frames")


def _prepared_frames(
    tracker: DICTracker, spec: SourceSpec, max_frames: int
) -> Iterator[tuple[int, PreparedFrame | str]]:
    """Frames read and prepared (rectified, spline-filtered) by a background thread.

    Decoding and the B-spline prefilter release the GIL, so they overlap with tracking of the
    previous frame. Yields (k, prepared frame) or (k, reason the frame is unusable).
    """
    out: queue_mod.Queue = queue_mod.Queue(maxsize=2)
    halt = threading.Event()
    end = object()

    def produce():
        try:
            for k, item in iter_frames(spec):
                if halt.is_set() or (max_frames and k >= max_frames):
                    break
                if isinstance(item, BadFrame):
                    out.put((k, item.reason))
                    continue
                try:
                    out.put((k, prepare_frame(tracker, item)))
                except FrameError as exc:
                    out.put((k, str(exc)))
        except Exception as exc:  # noqa: BLE001 - handed to the consuming thread
            out.put((None, exc))
        finally:
            out.put(end)

    reader = threading.Thread(target=produce, name="frame-reader", daemon=True)
    reader.start()
    try:
        while (item := out.get()) is not end:
            k, x = item
            if k is None:
                raise x
            yield k, x
    finally:
        halt.set()
        while reader.is_alive():  # unblock a reader waiting on a full queue
            try:
                out.get_nowait()
            except queue_mod.Empty:
                reader.join(0.05)


def track_blocks(job: TrackJob, stop: Callable[[], bool] = lambda: False) -> Iterator[Block]:
    """Track the job's units through the source, yielding results every `job.block` frames."""
    if job.threads > 0:
        numba.set_num_threads(min(job.threads, numba.config.NUMBA_NUM_THREADS))
    tracker = DICTracker(job.polygons_m, job.calib, job.cfg)
    try:
        state = init_state(tracker, _reference_image(job))
    except FrameError as exc:
        raise SourceError(f"reference frame unusable: {exc}") from None
    buf: list[tuple] = []
    k0 = 0
    for k, item in _prepared_frames(tracker, job.spec, job.max_frames):
        if isinstance(item, str):
            state, poses = all_lost(state, item)
        else:
            state, poses = track_frame(tracker, state, item)
        if poses.error:
            log.warning("frame %d unusable, all units flagged lost: %s", k, poses.error)
        buf.append((poses.q, poses.quality, poses.lost, bool(poses.error)))
        if len(buf) >= job.block:
            yield _pack(k0, buf)
            k0 += len(buf)
            buf = []
            if stop():
                return
    if buf:
        yield _pack(k0, buf)


def _pack(k0: int, buf: list[tuple]) -> Block:
    q, qual, lost, bad = zip(*buf, strict=True)
    return Block(k0, np.array(q), np.array(qual), np.array(lost), np.array(bad))


def _worker(wid: int, job: TrackJob, out: "mp.Queue", stop: "mp.Event") -> None:
    """Process entry: stream blocks (or an error) to the parent; Ctrl-C is the parent's job."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        for blk in track_blocks(job, stop.is_set):
            out.put(("block", wid, blk))
        out.put(("done", wid, None))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which decides
        out.put(("error", wid, f"{type(exc).__name__}: {exc}"))


@dataclass(frozen=True, slots=True)
class TrackResult:
    """Assembled output. q: [n_t, n_units, 3]; quality, lost: [n_t, n_units]; bad: [n_t]."""

    q: np.ndarray
    quality: np.ndarray
    lost: np.ndarray
    bad: np.ndarray
    complete: bool


def _assemble(parts: list[list[Block]], splits: list[np.ndarray], n_units: int,
              complete: bool) -> TrackResult:
    """Join per-worker block lists into full arrays, keeping only frames every worker did."""
    n_t = min((sum(b.q.shape[0] for b in p) for p in parts), default=0)
    q = np.full((n_t, n_units, 3), np.nan)
    qual = np.full((n_t, n_units), np.nan)
    lost = np.ones((n_t, n_units), bool)
    bad = np.zeros(n_t, bool)
    for blocks, ids in zip(parts, splits, strict=True):
        for b in blocks:
            m = min(b.q.shape[0], n_t - b.k0)
            if m <= 0:
                continue
            sl = slice(b.k0, b.k0 + m)
            q[sl, ids], qual[sl, ids], lost[sl, ids] = b.q[:m], b.quality[:m], b.lost[:m]
            bad[sl] |= b.bad[:m]
    return TrackResult(q, qual, lost, bad, complete)


def run_tracking(
    spec: SourceSpec, polygons_m: np.ndarray, calib: Calibration, cfg: DICConfig,
    workers: int = 1, reference: str | None = None, block: int = 8, max_frames: int = 0,
    progress: bool = False, threads: int = 0,
) -> TrackResult:
    """Track all units, in this process (workers = 1) or split over worker processes.

    Within a process, units are solved on `threads` numba threads (0: all cores shared out
    between the workers) while a reader thread decodes and prepares the next frame.

    Ctrl-C (KeyboardInterrupt) returns what every worker finished, with complete = False.

    Raises:
        SourceError: the source or the reference frame cannot be read.
    """
    from tqdm import tqdm

    n = polygons_m.shape[0]
    workers = max(1, min(int(workers), n))
    splits = np.array_split(np.arange(n), workers)
    threads = threads or max(1, (os.cpu_count() or 1) // workers)
    jobs = [TrackJob(spec, polygons_m[ids], calib, cfg, reference, block, max_frames, threads)
            for ids in splits]
    total = count_frames(spec)
    if total is not None and max_frames:
        total = min(total, max_frames)
    bar = tqdm(total=total, unit="frame", disable=not progress, desc="track")
    parts: list[list[Block]] = [[] for _ in jobs]
    done_frames = 0

    def advance():
        nonlocal done_frames
        now = min(sum(b.q.shape[0] for b in p) for p in parts)
        bar.update(now - done_frames)
        done_frames = now

    complete = False
    try:
        if workers == 1:
            for blk in track_blocks(jobs[0]):
                parts[0].append(blk)
                advance()
            complete = True
        else:
            complete = _run_pool(jobs, parts, advance)
    except KeyboardInterrupt:
        log.warning("interrupted: keeping the %d frames every worker finished", done_frames)
    finally:
        bar.close()
    return _assemble(parts, splits, n, complete)


def _run_pool(jobs: list[TrackJob], parts: list[list[Block]], advance: Callable) -> bool:
    """Run jobs in worker processes; True when all finished. Raises on a worker error."""
    # spawn, not fork: a forked child of a process whose OpenMP (numba) threads are running
    # can deadlock in its first parallel region
    ctx = mp.get_context("spawn")
    out = ctx.Queue(maxsize=4 * len(jobs))
    stop = ctx.Event()
    procs = [ctx.Process(target=_worker, args=(i, j, out, stop), daemon=True)
             for i, j in enumerate(jobs)]
    for p in procs:
        p.start()
    running = set(range(len(jobs)))
    error = None
    try:
        while running:
            try:
                kind, wid, payload = out.get(timeout=1.0)
            except queue_mod.Empty:
                dead = [i for i in running if not procs[i].is_alive()]
                if dead and out.empty():
                    raise SourceError(f"worker {dead[0]} died (exit code "
                                      f"{procs[dead[0]].exitcode})") from None
                continue
            if kind == "block":
                parts[wid].append(payload)
                advance()
            elif kind == "done":
                running.discard(wid)
            else:
                error = payload
                break
    except KeyboardInterrupt:
        stop.set()
        _drain(out, parts, procs)
        raise
    finally:
        stop.set()
        for p in procs:
            p.join(timeout=5.0)
            if p.is_alive():
                p.terminate()
    if error is not None:
        raise SourceError(f"tracking failed in a worker: {error}")
    return True


def _drain(out, parts: list[list[Block]], procs, timeout: float = 10.0) -> None:
    """Collect blocks the workers still send after a stop request."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and (any(p.is_alive() for p in procs) or not out.empty()):
        try:
            kind, wid, payload = out.get(timeout=0.2)
        except queue_mod.Empty:
            continue
        except KeyboardInterrupt:
            break
        if kind == "block":
            parts[wid].append(payload)


def qdot_backward(q: np.ndarray, fps: float) -> np.ndarray:
    """Backward-difference rates [n_t, n, 3] of q (NaN at k = 0 and next to lost frames)."""
    qdot = np.full_like(q, np.nan)
    qdot[1:] = (q[1:] - q[:-1]) * fps
    return qdot


def save_tracks(path: Path, res: TrackResult, fps: float) -> Path:
    """Write the result as a compressed .npz (keys in the module docstring)."""
    n_t = res.q.shape[0]
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path, t=np.arange(n_t) / fps, q=res.q, qdot=qdot_backward(res.q, fps),
        quality=res.quality, lost=res.lost, complete=np.array(res.complete),
        fps=np.array(float(fps)),
    )
    return path


def _config(args) -> DICConfig:
    return DICConfig(margin_px=args.margin_px, min_points=args.min_points,
                     zncc_lost=args.zncc_lost, zncc_reacquire=max(args.zncc_lost, 0.9)
                     if args.zncc_reacquire is None else args.zncc_reacquire,
                     search_radius_px=args.search_radius_px,
                     prefilter_sigma_px=args.prefilter_sigma_px)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="metarig track", description=track_main.__doc__,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("source", help="folder of *.png frames (name order), a video file or an "
                   ".mcap recording with sensor_msgs/Image messages")
    p.add_argument("--units", required=True, help="JSON file with 'polygons_m' (plain units "
                   "file or a design file)")
    p.add_argument("--calibration", required=True, help="calibration JSON (fps, m_per_px, "
                   "origin_px, y_up; optional homography, rectified_size_px)")
    p.add_argument("--out", default="tracks.npz", help="output .npz")
    p.add_argument("--topic", default=None, help="MCAP image topic (default: the only one, or "
                   "the one ending in image_raw)")
    p.add_argument("--reference", default=None, help="image of the reference configuration "
                   "(default: the first frame)")
    p.add_argument("--workers", type=int, default=1,
                   help="worker processes; units are split between them (each decodes every "
                   "frame, so this pays off on many cores or slow-to-track scenes)")
    p.add_argument("--threads", type=int, default=0,
                   help="numba threads per worker (0: all cores shared out between workers)")
    p.add_argument("--max-frames", type=int, default=0, help="stop after this many (0: all)")
    p.add_argument("--block", type=int, default=8, help="frames per result block")
    p.add_argument("--margin-px", type=float, default=_DEFAULTS.margin_px,
                   help="subset distance from the unit outline, px")
    p.add_argument("--min-points", type=int, default=_DEFAULTS.min_points,
                   help="units with fewer subset pixels are not tracked")
    p.add_argument("--zncc-lost", type=float, default=_DEFAULTS.zncc_lost,
                   help="correlation below which a unit is declared lost")
    p.add_argument("--zncc-reacquire", type=float, default=None,
                   help="correlation that triggers a search / regains a lost unit "
                   "(default: max(zncc-lost, 0.9))")
    p.add_argument("--search-radius-px", type=int, default=_DEFAULTS.search_radius_px,
                   help="re-acquisition search half-width, px")
    p.add_argument("--prefilter-sigma-px", type=float, default=0.0,
                   help="Gaussian smoothing of frames before tracking, px")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def track_main(argv: list[str] | None = None) -> int:
    """Track the planar pose of every unit in recorded frames by digital image correlation."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        calib = load_calibration(args.calibration)
        polys = load_unit_polygons(args.units)
        spec = open_source(args.source, args.topic)
        cfg = _config(args)
    except (CalibrationError, UnitsError, SourceError, ValueError) as exc:
        print(f"metarig track: error: {exc}", file=sys.stderr)
        return 2
    log.info("tracking %d units in %s (%s) with %d worker process(es)", polys.shape[0],
             spec.path, spec.kind, args.workers)
    t0 = time.perf_counter()
    try:
        res = run_tracking(spec, polys, calib, cfg, args.workers, args.reference, args.block,
                           args.max_frames, progress=not args.quiet and sys.stderr.isatty(),
                           threads=args.threads)
    except SourceError as exc:
        print(f"metarig track: error: {exc}", file=sys.stderr)
        return 2
    dt = time.perf_counter() - t0
    n_t = res.q.shape[0]
    out = save_tracks(Path(args.out), res, calib.fps)
    lost_frac = float(res.lost.mean()) if res.lost.size else 0.0
    log.info("%d frames in %.1f s (%.1f frames/s); %.2f %% unit-frames lost, %d unusable "
             "frames -> %s", n_t, dt, n_t / max(dt, 1e-9), 100 * lost_frac,
             int(res.bad.sum()), out)
    if not res.complete:
        log.warning("incomplete: interrupted after %d frames; %s holds those (complete=False)",
                    n_t, out)
        return 130
    return 0
