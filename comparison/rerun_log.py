"""A Rerun recording (.rrd) of an experiment-vs-simulation comparison, with its blueprint.

Everything lies on one timeline, `t` = time since the pulse onset (a duration), so the tracked
lattice, the simulated lattice, the camera frames and the error curves scrub together. The
recording goes through an explicit `rr.RecordingStream` (no global recording) saved to a file.

Entity layout (module constants):
    experiment/units, simulation/units   LineStrips2D: every unit as a closed outline at its
                                         pose, coloured by speed (grey: excluded unit)
    experiment/speed, simulation/speed   Points2D: a speed-coloured disc inside every unit
    experiment/target, simulation/target LineStrips2D: the target units, thick magenta
    camera/image                         Image: the greyscale camera frame (when given)
    camera/outlines, camera/target       LineStrips2D: the tracked outlines in pixels
    series/target_ke/{experiment,simulation}  Scalars: target kinetic energy, J
    series/velocity_error                Scalars: RMS velocity difference / RMS simulated speed
    series/displacement_error/max        Scalars: max |(u, v) measured - simulated|, m
    summary                              TextDocument (markdown): metrics and colour scale
Lattice views are in mm with y negated, since Rerun's 2D views put y down and the sample frame
has y up; the camera view is in image pixels (pixel centres at +0.5, Rerun's convention).
"""

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from matplotlib import colormaps

from comparison.metrics import Comparison
from comparison.plots import SPEED_CMAP, posed_outlines, speed_range
from metarig.polygon import area_centroids, signed_areas

APPLICATION_ID = "metarig_comparison"
TIMELINE = "t"
EXPERIMENT, SIMULATION, CAMERA = "experiment", "simulation", "camera"
UNITS, SPEED, TARGET = "units", "speed", "target"
CAMERA_IMAGE, CAMERA_OUTLINES, CAMERA_TARGET = "camera/image", "camera/outlines", "camera/target"
SERIES = "series"
TARGET_KE = "series/target_ke"
VELOCITY_ERROR = "series/velocity_error"
DISPLACEMENT_ERROR = "series/displacement_error"
SUMMARY = "summary"

MM_PER_M = 1e3
EXCLUDED_RGBA = (150, 150, 150, 255)
TARGET_RGBA = (255, 0, 255, 255)
EXP_RGBA, SIM_RGBA = (214, 39, 40, 255), (31, 119, 180, 255)
OUTLINE_UI_POINTS, TARGET_UI_POINTS = 0.8, 2.0


def speed_colours(speed_m_s: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """RGBA uint8 [..., 4] of speeds [...] (m/s) on the shared colour map (grey where NaN)."""
    s = np.asarray(speed_m_s, np.float64)
    x = np.clip((np.nan_to_num(s, nan=vmin) - vmin) / (vmax - vmin), 0.0, 1.0)
    rgba = (colormaps[SPEED_CMAP](x) * 255).round().astype(np.uint8)
    rgba[~np.isfinite(s)] = EXCLUDED_RGBA
    return rgba


def _closed(outlines: np.ndarray) -> np.ndarray:
    """Outlines [..., nv, 2] -> closed polylines [..., nv + 1, 2] (first vertex repeated)."""
    return np.concatenate([outlines, outlines[..., :1, :]], axis=-2)


def _lattice_view_xy(xy_m: np.ndarray) -> np.ndarray:
    """Sample-frame m (y up) -> lattice-view coordinates: mm, y negated, float32."""
    return (xy_m * np.array([MM_PER_M, -MM_PER_M])).astype(np.float32)


def _pixel_xy(xy_m: np.ndarray, m_per_px: float, origin_px, y_up: bool) -> np.ndarray:
    """Sample-frame m -> Rerun image coordinates (col, row) + 0.5, float32 (pixel centres at
    integers, as `hardware_sim.camera` and the tracker)."""
    sy = -1.0 if y_up else 1.0
    col = origin_px[0] + xy_m[..., 0] / m_per_px + 0.5
    row = origin_px[1] + sy * xy_m[..., 1] / m_per_px + 0.5
    return np.stack([col, row], axis=-1).astype(np.float32)


def _send_strips(rec, entity, times_s, strips, colours=None):
    """One row per sample: strips [n_t, m, nv + 1, 2], colours [n_t, m, 4] or None."""
    n_t, m = strips.shape[:2]
    fields = {"strips": strips.reshape(n_t * m, *strips.shape[2:])}
    if colours is not None:
        fields["colors"] = colours.reshape(n_t * m, 4)
    rr.send_columns(
        entity,
        indexes=[rr.TimeColumn(TIMELINE, duration=times_s)],
        columns=rr.LineStrips2D.columns(**fields).partition([m] * n_t),
        recording=rec,
    )


def _send_scalars(rec, entity, times_s, values, name, rgba):
    ok = np.isfinite(values)
    rec.log(entity, rr.SeriesLines(names=name, colors=[rgba]), static=True)
    rr.send_columns(
        entity,
        indexes=[rr.TimeColumn(TIMELINE, duration=times_s[ok])],
        columns=rr.Scalars.columns(scalars=np.asarray(values, np.float64)[ok]),
        recording=rec,
    )


def _log_lattice(rec, root, times_s, polygons_m, q, speed, target_ids, vmin, vmax):
    """Outlines, speed discs and target outlines of one side (experiment or simulation)."""
    q = np.where(np.isfinite(q), q, 0.0)  # a lost pose is drawn at the reference (grey)
    outlines = posed_outlines(polygons_m, q)  # [n_t, n, nv, 2] m
    colours = speed_colours(speed, vmin, vmax)
    strips = _closed(_lattice_view_xy(outlines))
    rec.log(
        f"{root}/{UNITS}",
        rr.LineStrips2D.from_fields(radii=rr.Radius.ui_points(OUTLINE_UI_POINTS), draw_order=10.0),
        static=True,
    )
    _send_strips(rec, f"{root}/{UNITS}", times_s, strips, colours)
    # a disc of ~0.4 sqrt(area) fits inside squares and kagome triangles alike
    disc_mm = 0.4 * np.sqrt(np.abs(signed_areas(polygons_m))) * MM_PER_M
    n_t, n = speed.shape
    centres = _lattice_view_xy(area_centroids(polygons_m) + q[..., :2]).reshape(n_t * n, 2)
    rec.log(
        f"{root}/{SPEED}",
        rr.Points2D.from_fields(radii=disc_mm.astype(np.float32), draw_order=5.0),
        static=True,
    )
    rr.send_columns(
        f"{root}/{SPEED}",
        indexes=[rr.TimeColumn(TIMELINE, duration=times_s)],
        columns=rr.Points2D.columns(
            positions=centres, colors=colours.reshape(n_t * n, 4)
        ).partition([n] * n_t),
        recording=rec,
    )
    tgt = np.asarray(target_ids, np.int64)
    rec.log(
        f"{root}/{TARGET}",
        rr.LineStrips2D.from_fields(
            radii=rr.Radius.ui_points(TARGET_UI_POINTS), colors=[TARGET_RGBA], draw_order=20.0
        ),
        static=True,
    )
    _send_strips(rec, f"{root}/{TARGET}", times_s, strips[:, tgt])
    return outlines


def _log_camera(rec, times_s, frames, strips_px, colours, target_ids, jpeg_quality):
    """Frames [n_t, H, W] per sample; outlines strips_px [n_t, n, nv + 1, 2] px, colours."""
    frames = np.asarray(frames)
    for k, t in enumerate(times_s):
        rec.set_time(TIMELINE, duration=float(t))
        img = rr.Image(frames[k], color_model="L")
        if jpeg_quality is not None and frames.dtype == np.uint8:
            img = img.compress(jpeg_quality=jpeg_quality)
        rec.log(CAMERA_IMAGE, img)
    rec.reset_time()
    rec.log(
        CAMERA_OUTLINES,
        rr.LineStrips2D.from_fields(radii=rr.Radius.ui_points(OUTLINE_UI_POINTS), draw_order=10.0),
        static=True,
    )
    _send_strips(rec, CAMERA_OUTLINES, times_s, strips_px, colours)
    rec.log(
        CAMERA_TARGET,
        rr.LineStrips2D.from_fields(
            radii=rr.Radius.ui_points(TARGET_UI_POINTS), colors=[TARGET_RGBA], draw_order=20.0
        ),
        static=True,
    )
    _send_strips(rec, CAMERA_TARGET, times_s, strips_px[:, np.asarray(target_ids, np.int64)])


def summary_markdown(comparison: Comparison, vmin: float, vmax: float) -> str:
    """The summary metrics and the speed colour scale as a markdown document."""
    lines = ["# Experiment vs simulation", "", "| metric | value |", "|---|---|"]
    for key, value in comparison.metrics.items():
        shown = f"{value:.4g}" if isinstance(value, float) else str(value)
        lines.append(f"| {key} | {shown} |")
    scale = (
        f"Speed colour scale ({SPEED_CMAP}): {vmin * 1e3:.3g} to {vmax * 1e3:.3g} mm/s, the "
        "same in the experiment, simulation and camera views; grey: excluded unit; "
        "magenta: target units."
    )
    lines += ["", scale, "", f"Timeline `{TIMELINE}`: time since the pulse onset."]
    return "\n".join(lines)


def comparison_blueprint(
    bounds_mm: tuple[float, float, float, float], vmin: float, vmax: float, with_camera: bool
) -> rrb.Blueprint:
    """Lattice views side by side (experiment, simulation, camera) over the error curves.

    Args:
        bounds_mm: (x0, x1, y0, y1) of the lattice views (their coordinates, y negated), mm.
    """
    scale = f"speed 0-{vmax * 1e3:.3g} mm/s"
    bounds = rrb.VisualBounds2D(x_range=bounds_mm[:2], y_range=bounds_mm[2:])
    views = [
        rrb.Spatial2DView(origin=EXPERIMENT, name=f"experiment ({scale})", visual_bounds=bounds),
        rrb.Spatial2DView(origin=SIMULATION, name=f"simulation ({scale})", visual_bounds=bounds),
    ]
    if with_camera:
        views.append(rrb.Spatial2DView(origin=CAMERA, name="camera + tracked outlines"))
    curves = rrb.Horizontal(
        rrb.TimeSeriesView(origin=TARGET_KE, name="target kinetic energy [J]"),
        rrb.TimeSeriesView(origin=VELOCITY_ERROR, name="velocity error [-]"),
        rrb.TimeSeriesView(origin=DISPLACEMENT_ERROR, name="max displacement error [m]"),
        rrb.TextDocumentView(origin=SUMMARY, name="summary"),
    )
    return rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(*views), curves, row_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TIMELINE, state="collapsed"),
        collapse_panels=False,
    )


def write_rrd(
    path: str | Path,
    comparison: Comparison,
    polygons_m: np.ndarray,
    q_exp: np.ndarray,
    q_sim: np.ndarray,
    target_ids: np.ndarray,
    *,
    frames: np.ndarray | None = None,
    m_per_px: float | None = None,
    origin_px: tuple[float, float] | None = None,
    y_up: bool = True,
    jpeg_quality: int | None = None,
    application_id: str = APPLICATION_ID,
    recording_id: str | None = None,
) -> Path:
    """Write the comparison as a Rerun recording with its blueprint.

    Args:
        path: the .rrd file to write (its folder is created).
        comparison: from `compare`.
        polygons_m: [n, nv, 2] reference outlines, m (sample frame, y up).
        q_exp, q_sim: [n_t, n, 3] poses on the comparison's window (`plots.window_samples`).
        target_ids: ids of the target units.
        frames: [n_t, H, W] uint8 or uint16 greyscale camera frames on the same window, or None.
        m_per_px, origin_px, y_up: the frames' pixel mapping: metres per pixel and the (col, row)
            pixel position of the sample-frame origin; y_up when image rows grow against y.
        jpeg_quality: JPEG-compress uint8 frames at this quality (None: lossless, larger).
        application_id, recording_id: of the recording (recording_id: e.g. the run id).

    Returns:
        path.

    Raises:
        ValueError: pose or frame arrays that do not match the comparison.
    """
    path = Path(path)
    n_t, n = comparison.speed_exp.shape
    for name, q in (("q_exp", q_exp), ("q_sim", q_sim)):
        if np.shape(q) != (n_t, n, 3):
            raise ValueError(f"{name} must be [n_t, n, 3] = {(n_t, n, 3)}, got {np.shape(q)}")
    if frames is not None:
        if np.ndim(frames) != 3 or np.shape(frames)[0] != n_t:
            raise ValueError(f"frames must be [n_t={n_t}, H, W], got {np.shape(frames)}")
        if m_per_px is None or origin_px is None:
            raise ValueError("frames need their pixel mapping: m_per_px and origin_px")
    times = np.asarray(comparison.t, np.float64)
    vmin, vmax = speed_range(comparison.speed_exp, comparison.speed_sim)
    ref = _lattice_view_xy(np.asarray(polygons_m, np.float64).reshape(-1, 2))
    pad = 0.06 * float(np.ptp(ref, axis=0).max())
    bounds = (
        float(ref[:, 0].min() - pad),
        float(ref[:, 0].max() + pad),
        float(ref[:, 1].min() - pad),
        float(ref[:, 1].max() + pad),
    )
    blueprint = comparison_blueprint(bounds, vmin, vmax, with_camera=frames is not None)

    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(application_id, recording_id=recording_id)
    rec.save(path, default_blueprint=blueprint)
    try:
        rec.log(
            SUMMARY,
            rr.TextDocument(
                summary_markdown(comparison, vmin, vmax), media_type=rr.MediaType.MARKDOWN
            ),
            static=True,
        )
        outlines_exp = _log_lattice(
            rec, EXPERIMENT, times, polygons_m, q_exp, comparison.speed_exp, target_ids, vmin, vmax
        )
        _log_lattice(
            rec, SIMULATION, times, polygons_m, q_sim, comparison.speed_sim, target_ids, vmin, vmax
        )
        if frames is not None:
            strips_px = _closed(_pixel_xy(outlines_exp, m_per_px, origin_px, y_up))
            colours = speed_colours(comparison.speed_exp, vmin, vmax)
            _log_camera(rec, times, frames, strips_px, colours, target_ids, jpeg_quality)
        _send_scalars(
            rec, f"{TARGET_KE}/experiment", times, comparison.target_ke_exp, "experiment", EXP_RGBA
        )
        _send_scalars(
            rec, f"{TARGET_KE}/simulation", times, comparison.target_ke_sim, "simulation", SIM_RGBA
        )
        _send_scalars(
            rec,
            VELOCITY_ERROR,
            times,
            comparison.velocity_error_t,
            "velocity error",
            (0, 0, 0, 255),
        )
        disp = comparison.displacement_error_m
        has = np.isfinite(disp).any(axis=1)
        max_disp = np.full(n_t, np.nan)
        max_disp[has] = np.nanmax(disp[has], axis=1)
        _send_scalars(
            rec,
            f"{DISPLACEMENT_ERROR}/max",
            times,
            max_disp,
            "max displacement error",
            (255, 127, 14, 255),
        )
    finally:
        rec.disconnect()  # flushes and writes the file's footer
    return path
