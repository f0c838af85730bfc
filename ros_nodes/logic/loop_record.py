"""What a closed loop shows of its rounds: `loop.rrd` (each round's design over its target energy,
measured and predicted, side by side) and the table of the rounds' objectives."""

import json
from pathlib import Path

import numpy as np

TIMELINE = "t"  # time since the pulse onset
APPLICATION_ID = "metarig_loop"
ROUND_ENTITY = "round-{k}"
MM_PER_M = 1e3
MEASURED_RGBA, PREDICTED_RGBA = (214, 39, 40, 255), (31, 119, 180, 255)
OUTLINE_RGBA, TARGET_RGBA = (90, 90, 90, 255), (255, 0, 255, 255)


def write_loop_rrd(path: Path, rounds: list[dict], objective_dirs: dict[int, Path]) -> Path:
    """`loop.rrd`: per round side by side, its design (unit outlines, target units magenta)
    over the target's kinetic energy measured and predicted on the rounds' shared time axis
    (since the pulse onset); below them the objectives of every round as a table. Each round's
    `objective.json` and `target_ke.npz` are read from `objective_dirs[round]`. Written to a
    temporary file and renamed, so `path` is whole or absent."""
    import rerun as rr
    import rerun.blueprint as rrb

    data, columns = {}, []
    for r in rounds:
        k = r["round"]
        data[k] = (np.load(objective_dirs[k] / "target_ke.npz"),
                   json.loads((objective_dirs[k] / "objective.json").read_text()))
        root = ROUND_ENTITY.format(k=k)
        columns.append(rrb.Vertical(
            rrb.Spatial2DView(origin=f"{root}/design", name=f"round {k}: design"),
            rrb.TimeSeriesView(origin=f"{root}/target_ke",
                               name=f"round {k}: target kinetic energy [J]"),
        ))
    blueprint = rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(*columns),
                     rrb.TextDocumentView(origin="summary", name="rounds"), row_shares=[4, 1]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TIMELINE, state="collapsed"), collapse_panels=False)
    tmp = path.with_name(f".{path.name}.part")
    rec = rr.RecordingStream(APPLICATION_ID)
    rec.save(tmp, default_blueprint=blueprint)
    try:
        rec.log("summary", rr.TextDocument(loop_markdown(rounds),
                                           media_type=rr.MediaType.MARKDOWN), static=True)
        for k, (arrays, objective) in data.items():
            root = ROUND_ENTITY.format(k=k)
            poly = arrays["polygons_m"] * np.array([MM_PER_M, -MM_PER_M])  # Rerun: y down
            strips = np.concatenate([poly, poly[:, :1]], axis=1).astype(np.float32)
            colours = np.tile(np.array([OUTLINE_RGBA], np.uint8), (len(strips), 1))
            for term in objective["terms"].values():
                colours[np.asarray(term["ids"], np.int64)] = TARGET_RGBA
            rec.log(f"{root}/design", rr.LineStrips2D(strips, colors=colours), static=True)
            t = np.asarray(arrays["t_s"], np.float64)
            for side, rgba in (("measured", MEASURED_RGBA), ("predicted", PREDICTED_RGBA)):
                entity = f"{root}/target_ke/{side}"
                rec.log(entity, rr.SeriesLines(names=side, colors=[rgba]), static=True)
                rr.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=t)],
                                columns=rr.Scalars.columns(
                                    scalars=np.asarray(arrays[f"target_ke_{side}_J"])),
                                recording=rec)
    finally:
        rec.disconnect()  # flushes and writes the footer
    tmp.replace(path)
    return path


def loop_markdown(rounds: list[dict]) -> str:
    """The rounds' objectives as a markdown table."""
    lines = ["| round | design objective (J) | predicted (J) | measured (J) | measured / "
             "predicted |", "|---|---|---|---|---|"]
    for r in rounds:
        d = r["design_objective_J"]
        lines.append(f"| {r['round']} | {d:.4g} | {r['predicted_objective_J']:.4g} | "
                     f"{r['measured_objective_J']:.4g} | {r['measured_over_predicted']:.3f} |"
                     if d is not None else
                     f"| {r['round']} | - | {r['predicted_objective_J']:.4g} | "
                     f"{r['measured_objective_J']:.4g} | {r['measured_over_predicted']:.3f} |")
    return "\n".join(lines)
