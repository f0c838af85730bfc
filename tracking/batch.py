"""Batch DIC tracking of every unit through a frame source, on all cores (`metarig track`).

Parallel over units: within a process the units of a frame are solved on numba threads while a
reader thread decodes and prepares the next frame; with `workers = N` the unit ids are also
split into N contiguous blocks, one per process, each reading the frames itself. Every path
runs the same tracker (`tracking.dic`) as the live node and units are independent, so results
do not depend on the split. Results stream back in blocks of frames; Ctrl-C stops the workers
and keeps what every worker has finished.

The result is a `metarig.trajectory.Trajectory`: t = k / fps, q NaN where lost, rates by
backward difference, quality = ZNCC, complete = False when interrupted.
"""

import logging
import multiprocessing as mp
import queue as queue_mod
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numba
import numpy as np

from metarig.cores import usable_cores
from metarig.trajectory import Trajectory
from tracking.calibration import Calibration
from tracking.dic import (
    DICConfig,
    DICTracker,
    acquire_radius,
    FrameError,
    PreparedFrame,
    all_lost,
    init_state,
    prepare_frame,
    track_frame,
)
from tracking.frame_sources import (
    BadFrame,
    SourceError,
    SourceSpec,
    count_frames,
    iter_frames,
    recorded_reference,
)
from tracking.reference import unit_subsets

log = logging.getLogger("metarig.track")


@dataclass(frozen=True, slots=True)
class TrackJob:
    """One worker's share of the tracking.

    Attributes:
        spec: the frame source. polygons_m: [n, nv, 2] outlines of this worker's units (m).
        calib: calibration. cfg: tracker settings.
        reference: image file showing the reference configuration (None: the first frame).
        block: frames per result block. max_frames: stop after this many (0: all).
        threads: numba threads for this job's units (0: leave the process default).
        bonds: [nb, 4] ligaments between this job's units (its own unit ids), None: none.
    """

    spec: SourceSpec
    polygons_m: np.ndarray
    calib: Calibration
    cfg: DICConfig
    reference: str | None
    block: int
    max_frames: int
    threads: int = 0
    bonds: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class Block:
    """Results of consecutive frames k0 .. k0 + len - 1 for one worker's units.

    Attributes:
        k0: first frame index. q: [m, n, 3]. quality: [m, n]. lost: [m, n]. bad: [m] bool
        frame unusable (all units lost). sigma: [m, n, 3] standard errors of q.
    """

    k0: int
    q: np.ndarray
    quality: np.ndarray
    lost: np.ndarray
    bad: np.ndarray
    sigma: np.ndarray


def reference_image(spec: SourceSpec, reference: str | None = None) -> np.ndarray:
    """The frame showing the reference configuration: the image file `reference`, else the
    recording's reference image (the unloaded sample, `recorded_reference`), else the
    source's first frame.

    Raises:
        SourceError: it cannot be read.
    """
    if reference is not None:
        img = cv2.imread(reference, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SourceError(f"{reference}: cannot read the reference image")
        return img
    recorded = recorded_reference(spec)
    if recorded is not None:
        log.info("reference: %s of %s", spec.reference_topic, spec.path)
        return recorded
    for _, item in iter_frames(spec):
        if isinstance(item, BadFrame):
            raise SourceError(f"{spec.path}: the first frame (the reference) is unreadable: "
                              f"{item.reason}")
        return item
    raise SourceError(f"{spec.path}: holds no frames")


class OutlineMismatch(SourceError):
    """The unit outlines do not match the frames (another design, or the wrong calibration)."""


def check_outlines(tracker: DICTracker, reference: np.ndarray,
                   texture_frac: float = 0.1) -> None:
    """Refuse outlines that cannot belong to the frames, before any tracking.

    Most outlines (more than half) must lie inside the (rectified) frame, and most must show
    speckle texture in the reference frame: a subset whose grey-level standard deviation is at
    least `texture_frac` of the frame's 1-99 percentile range.

    Raises:
        OutlineMismatch: one line saying which test failed, for how many units.
        SourceError: the reference frame is unusable (blank, not an image).
    """
    try:
        prep = prepare_frame(tracker, reference)
    except FrameError as exc:
        raise SourceError(f"reference frame unusable: {exc}") from None
    h, w = prep.img.shape
    n = tracker.n_units
    p = tracker.polys_px
    inside = np.all((p[..., 0] >= 0) & (p[..., 0] <= w - 1) & (p[..., 1] >= 0)
                    & (p[..., 1] <= h - 1), axis=1)
    hint = "(outlines of another design, or the wrong calibration?)"
    if 2 * int(inside.sum()) < n:
        raise OutlineMismatch(f"the unit outlines do not fit the frames: {n - int(inside.sum())} "
                              f"of {n} units lie outside the {w}x{h} px frame {hint}")
    lo, hi = np.percentile(prep.img, [1.0, 99.0])
    outside = n - int(inside.sum())
    flat = 0
    subsets = unit_subsets(p, tracker.cfg.margin_px, (h, w))  # kept for the first reference
    for b in np.flatnonzero(inside):
        pts = subsets[b]
        if pts.shape[0] and prep.img[pts[:, 1], pts[:, 0]].std() < texture_frac * (hi - lo):
            flat += 1
    if 2 * (outside + flat) > n:
        where = "lie outside the frame or " if outside else ""
        raise OutlineMismatch(f"the unit outlines do not match the frames: {outside + flat} of "
                              f"{n} units {where}show no speckle texture in the reference frame "
                              f"{hint}")


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
    tracker = DICTracker(job.polygons_m, job.calib, job.cfg, job.bonds)
    try:
        state = init_state(tracker, reference_image(job.spec, job.reference))
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
        buf.append((poses.q, poses.quality, poses.lost, bool(poses.error), poses.sigma))
        if len(buf) >= job.block:
            yield _pack(k0, buf)
            k0 += len(buf)
            buf = []
            if stop():
                return
    if buf:
        yield _pack(k0, buf)


def _pack(k0: int, buf: list[tuple]) -> Block:
    q, qual, lost, bad, sigma = zip(*buf, strict=True)
    return Block(k0, np.array(q), np.array(qual), np.array(lost), np.array(bad), np.array(sigma))


def _worker(wid: int, job: TrackJob, out: "mp.Queue", stop: "mp.Event") -> None:
    """Process entry: stream blocks (or an error) to the parent; Ctrl-C is the parent's job."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        for blk in track_blocks(job, stop.is_set):
            out.put(("block", wid, blk))
        out.put(("done", wid, None))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which decides
        out.put(("error", wid, f"{type(exc).__name__}: {exc}"))


def _assemble(parts: list[list[Block]], splits: list[np.ndarray], n_units: int, fps: float,
              complete: bool) -> tuple[Trajectory, np.ndarray]:
    """Join per-worker block lists into a trajectory and the per-frame unusable flags [n_t],
    keeping only the frames every worker did."""
    n_t = min((sum(b.q.shape[0] for b in p) for p in parts), default=0)
    q = np.full((n_t, n_units, 3), np.nan)
    sigma = np.full((n_t, n_units, 3), np.nan)
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
            sigma[sl, ids] = b.sigma[:m]
            bad[sl] |= b.bad[:m]
    traj = Trajectory.from_positions(np.arange(n_t) / fps, q, quality=qual, lost=lost,
                                     complete=complete, sigma=sigma)
    return traj, bad


def run_tracking(
    spec: SourceSpec, polygons_m: np.ndarray, calib: Calibration, cfg: DICConfig,
    workers: int = 1, reference: str | None = None, block: int = 8, max_frames: int = 0,
    progress: bool = False, threads: int = 0, bonds: np.ndarray | None = None,
) -> Trajectory:
    """Track all units through the source; the trajectory of `track_source`."""
    return track_source(spec, polygons_m, calib, cfg, workers, reference, block, max_frames,
                        progress, threads, bonds)[0]


def threads_per_worker(workers: int) -> int:
    """The numba threads each of `workers` tracker processes takes by default: the cores this
    process may use, shared out (at least one)."""
    return max(1, usable_cores() // workers)


def track_source(
    spec: SourceSpec, polygons_m: np.ndarray, calib: Calibration, cfg: DICConfig,
    workers: int = 1, reference: str | None = None, block: int = 8, max_frames: int = 0,
    progress: bool = False, threads: int = 0, bonds: np.ndarray | None = None,
) -> tuple[Trajectory, np.ndarray]:
    """Track all units, in this process (workers = 1) or split over worker processes.

    Args:
        spec: the frame source. polygons_m: [n, nv, 2] reference outlines (m).
        calib: calibration (its fps gives t = k / fps). cfg: tracker settings.
        workers: processes; the units are split between them.
        reference: image file of the reference configuration (None: the first frame).
        block: frames per result block. max_frames: stop after this many (0: all).
        progress: show a progress bar. threads: numba threads per worker (0: the cores this
            process may use, shared out between the workers, `threads_per_worker`), while a
            reader thread decodes and prepares frames.
        bonds: [nb, 4] the lattice's ligaments (`tracking.units.load_unit_bonds`) for the check
            of every pose against its neighbours (None: no such check); a worker checks the
            ligaments between its own units.

    Returns:
        The trajectory [n_t frames, n units] and bad [n_t]: True for frames that could not be
        used at all (every unit lost). Ctrl-C (KeyboardInterrupt) returns what every worker
        finished, with complete = False.

    Raises:
        OutlineMismatch: the outlines do not match the frames (checked before tracking).
        SourceError: the source or the reference frame cannot be read.
    """
    from tqdm import tqdm

    n = polygons_m.shape[0]
    whole = DICTracker(polygons_m, calib, cfg)
    check_outlines(whole, reference_image(spec, reference))
    # the first frame's search covers the whole sample's strain, whichever units a worker has
    cfg = replace(cfg, acquire_radius_px=acquire_radius(whole))
    log.info("tracking %d units in %s (%s) with %d worker process(es)", n, spec.path,
             spec.kind, workers)
    workers = max(1, min(int(workers), n))
    splits = np.array_split(np.arange(n), workers)
    threads = threads or threads_per_worker(workers)
    jobs = [TrackJob(spec, polygons_m[ids], calib, cfg, reference, block, max_frames, threads,
                     _job_bonds(bonds, ids, n)) for ids in splits]
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
    return _assemble(parts, splits, n, calib.fps, complete)


def _job_bonds(bonds: np.ndarray | None, ids: np.ndarray, n: int) -> np.ndarray | None:
    """The ligaments [nb, 4] between units `ids` (of n), renumbered to their place in `ids`."""
    if bonds is None:
        return None
    local = np.full(n, -1)
    local[ids] = np.arange(ids.size)
    b = np.asarray(bonds, np.int64).reshape(-1, 4)
    b = b[(local[b[:, 0]] >= 0) & (local[b[:, 2]] >= 0)]
    return np.stack([local[b[:, 0]], b[:, 1], local[b[:, 2]], b[:, 3]], axis=1)


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


def save_tracks(path: Path, traj: Trajectory, fps: float) -> Path:
    """Write the trajectory atomically as a compressed .npz: t, q, qdot, quality, lost,
    complete (the `Trajectory` keys) and fps."""
    return traj.save_npz(path, fps=np.array(float(fps)))
