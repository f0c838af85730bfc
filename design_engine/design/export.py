"""Fabrication drawings (SVG and DXF) of a design, 1:1 in millimetres (`metarig export`'s library).

The drawing holds three layers:
- `units`: the outline of every rigid unit as a closed polygon (cut lines);
- `ligaments`: one short line per bond, between the two bonded vertices, where the flexible
  hinges go;
- `annotations`: a labelled scale bar and the design's name.

Coordinates are the design's own frame (mm, y up, the first block's grid point at the origin).
DXF keeps that frame as it is. SVG is y-down, so every SVG y is the design's y negated (the
drawing is not mirrored) and the `viewBox` is in mm with `width`/`height` in mm, so that one user
unit is one millimetre. Both files are written by this module (plain text, no third-party writer);
the DXF is ASCII DXF R2010 (AC1024) with $INSUNITS = 4 (mm).
"""

import json
import math
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

import jax.numpy as jnp
import numpy as np

from design_engine.physics.geometry import block_geometry
from design_engine.physics.lattice import Lattice


MARGIN_MM = 5.0  # blank border around everything drawn
LABEL_HEIGHT_MM = 3.5  # text height of the scale-bar label
NAME_HEIGHT_MM = 5.0  # text height of the design's name
TICK_MM = 1.0  # half height of the scale bar's end ticks
STROKE_MM = 0.1  # SVG stroke width (hairline)
SVG_COLOURS = {"units": "#ff0000", "ligaments": "#0000ff", "annotations": "#000000"}
DXF_LAYERS = {"UNITS": 1, "LIGAMENTS": 5, "ANNOTATIONS": 7}  # layer -> AutoCAD colour index


class ExportError(ValueError):
    """A request that cannot be exported (bad option, unwritable output)."""


@dataclass(frozen=True)
class TextItem:
    """One line of text: left end of its baseline at (x_mm, y_mm) (y up), cap height in mm."""

    id: str
    text: str
    x_mm: float
    y_mm: float
    height_mm: float


@dataclass(frozen=True)
class FabricationDrawing:
    """Everything a fabrication file shows, in mm, design frame (y up).

    Attributes:
        name: design name written on the drawing.
        units_mm: [n_units, n_vertices, 2] outline of every unit (counter-clockwise), mm.
        ligaments_mm: [n_bonds, 2, 2] end points (bond node 0, bond node 1) of every ligament, mm.
        scale_bar_mm: length of the scale bar, mm.
        scale_bar_lines_mm: [3, 2, 2] the bar and its two end ticks, mm.
        texts: the scale-bar label and the name.
        extent_mm: (x_min, y_min, x_max, y_max) of the page, margins included, mm.
    """

    name: str
    units_mm: np.ndarray
    ligaments_mm: np.ndarray
    scale_bar_mm: float
    scale_bar_lines_mm: np.ndarray
    texts: tuple[TextItem, ...]
    extent_mm: tuple[float, float, float, float]

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the page, mm."""
        x0, y0, x1, y1 = self.extent_mm
        return x1 - x0, y1 - y0

    @property
    def units_extent_mm(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the unit outlines alone, mm."""
        lo, hi = self.units_mm.reshape(-1, 2).min(axis=0), self.units_mm.reshape(-1, 2).max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _text_width_mm(text: str, height_mm: float) -> float:
    """Generous estimate of the advance width of `text` (sans-serif), mm; only for the page size."""
    return 0.65 * height_mm * len(text)


def fabrication_drawing(lattice: Lattice, x_mm, name: str, scale_bar_mm: float = 10.0
                        ) -> FabricationDrawing:
    """Lay out the fabrication drawing of design `x_mm` (mm) on `lattice`.

    Unit outlines are centroid + arm of `block_geometry`; each ligament joins the two vertices that
    `lattice.bonds` names (global node n = n_vertices * block + k). The scale bar and the name sit
    below the units, left-aligned with them.

    Raises:
        ExportError: for a scale bar that is not a positive finite length.
    """
    if not (math.isfinite(scale_bar_mm) and scale_bar_mm > 0.0):
        raise ExportError(f"scale bar length must be a positive number of mm, got {scale_bar_mm}")
    g = block_geometry(lattice, jnp.asarray(np.asarray(x_mm, dtype=np.float64)))
    units = np.asarray(g.centroids, dtype=np.float64)[:, None, :] + np.asarray(g.arms, np.float64)
    ligaments = units.reshape(-1, 2)[np.asarray(lattice.bonds)]
    pts = np.concatenate([units.reshape(-1, 2), ligaments.reshape(-1, 2)])
    xmin, ymin = pts.min(axis=0)
    xmax, ymax = pts.max(axis=0)

    bar_y = ymin - MARGIN_MM - TICK_MM
    bar = np.array([
        [[xmin, bar_y], [xmin + scale_bar_mm, bar_y]],
        [[xmin, bar_y - TICK_MM], [xmin, bar_y + TICK_MM]],
        [[xmin + scale_bar_mm, bar_y - TICK_MM], [xmin + scale_bar_mm, bar_y + TICK_MM]],
    ])
    label = TextItem("scale-bar-label", f"{scale_bar_mm:g} mm", xmin + scale_bar_mm + 2.0,
                     bar_y - 0.5 * LABEL_HEIGHT_MM, LABEL_HEIGHT_MM)
    name_item = TextItem("design-name", name, xmin, bar_y - TICK_MM - 2.0 - NAME_HEIGHT_MM,
                         NAME_HEIGHT_MM)
    right = max(xmax, label.x_mm + _text_width_mm(label.text, label.height_mm),
                name_item.x_mm + _text_width_mm(name_item.text, name_item.height_mm))
    extent = (float(xmin - MARGIN_MM), float(name_item.y_mm - 0.4 * NAME_HEIGHT_MM - MARGIN_MM),
              float(right + MARGIN_MM), float(ymax + MARGIN_MM))
    return FabricationDrawing(name=name, units_mm=units, ligaments_mm=ligaments,
                              scale_bar_mm=float(scale_bar_mm), scale_bar_lines_mm=bar,
                              texts=(label, name_item), extent_mm=extent)


def _num(v: float) -> str:
    """A length for the file: fixed point, 1e-9 mm resolution, no trailing zeros, no '-0'."""
    s = f"{float(v) + 0.0:.9f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


# ------------------------------------------------------------------------------------------ SVG


def svg_document(drawing: FabricationDrawing) -> str:
    """The drawing as an SVG document (text). SVG coordinates are (x, -y) of the design frame."""
    x0, y0, x1, y1 = drawing.extent_mm
    w, h = x1 - x0, y1 - y0
    out = [
        '<?xml version="1.0" encoding="UTF-8" standalone="no"?>',
        ('<svg xmlns="http://www.w3.org/2000/svg" '
         'xmlns:inkscape="http://www.inkscape.org/namespaces/inkscape" version="1.1" '
         f'width="{_num(w)}mm" height="{_num(h)}mm" '
         f'viewBox="{_num(x0)} {_num(-y1)} {_num(w)} {_num(h)}">'),
        f"<title>{escape(drawing.name)}</title>",
        ("<desc>metarig fabrication drawing, 1 user unit = 1 mm; units: cut outlines, ligaments: "
         "hinge positions</desc>"),
    ]

    def layer(name: str, **attrs) -> str:
        extra = "".join(f' {k.replace("_", "-")}={quoteattr(str(v))}' for k, v in attrs.items())
        return (f'<g id="{name}" inkscape:groupmode="layer" inkscape:label="{name}"{extra}>')

    stroke = {"stroke_width": _num(STROKE_MM), "stroke_linejoin": "round"}
    out.append(layer("units", fill="none", stroke=SVG_COLOURS["units"], **stroke))
    for b, poly in enumerate(drawing.units_mm):
        pts = " ".join(f"{_num(px)},{_num(-py)}" for px, py in poly)
        out.append(f'<polygon id="unit-{b}" points="{pts}"/>')
    out.append("</g>")
    out.append(layer("ligaments", fill="none", stroke=SVG_COLOURS["ligaments"], **stroke))
    for i, ((ax, ay), (bx, by)) in enumerate(drawing.ligaments_mm):
        out.append(f'<line id="ligament-{i}" x1="{_num(ax)}" y1="{_num(-ay)}" x2="{_num(bx)}" '
                   f'y2="{_num(-by)}"/>')
    out.append("</g>")
    out.append(layer("annotations", fill=SVG_COLOURS["annotations"], font_family="sans-serif"))
    d = " ".join(f"M {_num(a[0])},{_num(-a[1])} L {_num(b[0])},{_num(-b[1])}"
                 for a, b in drawing.scale_bar_lines_mm)
    out.append(f'<path id="scale-bar" d="{d}" fill="none" stroke="{SVG_COLOURS["annotations"]}" '
               f'stroke-width="{_num(2 * STROKE_MM)}"/>')
    for t in drawing.texts:
        # SVG font-size is the em size; cap height of sans-serif fonts is about 0.7 em
        out.append(f'<text id="{t.id}" x="{_num(t.x_mm)}" y="{_num(-t.y_mm)}" '
                   f'font-size="{_num(t.height_mm / 0.7)}">{escape(t.text)}</text>')
    out.append("</g>")
    out.append("</svg>")
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------------------------------ DXF


class _Dxf:
    """Minimal ASCII DXF R2010 writer: group-code/value pairs and a handle counter."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._next = 1

    def handle(self) -> str:
        h = f"{self._next:X}"
        self._next += 1
        return h

    @property
    def handseed(self) -> str:
        return f"{self._next:X}"

    def tag(self, code: int, value) -> None:
        if isinstance(value, float):
            value = _num(value)
        self.lines.append(f"{code:>3}")
        self.lines.append(str(value))

    def tags(self, *pairs) -> None:
        for code, value in pairs:
            self.tag(code, value)

    def point(self, x: float, y: float, code: int = 10) -> None:
        self.tags((code, float(x)), (code + 10, float(y)), (code + 20, 0.0))


def _dxf_text(s: str) -> str:
    """One DXF text line: no control characters (they would break the tag structure)."""
    return "".join(c if c.isprintable() else " " for c in s)


def dxf_document(drawing: FabricationDrawing) -> str:
    """The drawing as ASCII DXF R2010 (text), mm, design frame.

    Units are closed LWPOLYLINEs on layer UNITS, ligaments LINEs on layer LIGAMENTS, the scale bar
    (LINEs) and the texts (TEXT) on layer ANNOTATIONS. The file carries the tables, blocks and
    objects that DXF R13 and later require (VPORT, LTYPE, LAYER, STYLE, VIEW, UCS, APPID, DIMSTYLE,
    BLOCK_RECORD, the model/paper space blocks and the root dictionary).
    """
    body = _Dxf()
    h = {name: body.handle() for name in (
        "vport_t", "vport", "ltype_t", "byblock", "bylayer", "continuous", "layer_t", "style_t",
        "style", "view_t", "ucs_t", "appid_t", "acad", "dimstyle_t", "dimstyle", "brec_t",
        "ms_rec", "ps_rec", "ms_blk", "ms_end", "ps_blk", "ps_end", "root", "groups")}
    layer_h = {name: body.handle() for name in ("0", *DXF_LAYERS)}
    x0, y0, x1, y1 = drawing.extent_mm

    def table(name: str, count: int, owner_key: str) -> None:
        body.tags((0, "TABLE"), (2, name), (5, h[owner_key]), (330, 0), (100, "AcDbSymbolTable"),
                  (70, count))

    def record(kind: str, handle: str, owner_key: str, subclass: str, name: str,
               handle_code: int = 5) -> None:
        body.tags((0, kind), (handle_code, handle), (330, h[owner_key]),
                  (100, "AcDbSymbolTableRecord"), (100, subclass), (2, name), (70, 0))

    body.tags((0, "SECTION"), (2, "TABLES"))
    table("VPORT", 1, "vport_t")
    record("VPORT", h["vport"], "vport_t", "AcDbViewportTableRecord", "*Active")
    body.tags((10, 0.0), (20, 0.0))
    body.tags((11, 1.0), (21, 1.0))
    body.tags((12, 0.5 * (x0 + x1)), (22, 0.5 * (y0 + y1)))
    body.tags((13, 0.0), (23, 0.0), (14, 10.0), (24, 10.0), (15, 10.0), (25, 10.0))
    body.tags((16, 0.0), (26, 0.0), (36, 1.0), (17, 0.0), (27, 0.0), (37, 0.0))
    body.tags((40, float(y1 - y0)), (41, float(max((x1 - x0) / (y1 - y0), 1e-3))), (42, 50.0),
              (43, 0.0), (44, 0.0), (50, 0.0), (51, 0.0))
    body.tags((71, 0), (72, 100), (73, 1), (74, 3), (75, 0), (76, 0), (77, 0), (78, 0))
    body.tags((0, "ENDTAB"))

    table("LTYPE", 3, "ltype_t")
    for key, name in (("byblock", "ByBlock"), ("bylayer", "ByLayer"), ("continuous", "Continuous")):
        record("LTYPE", h[key], "ltype_t", "AcDbLinetypeTableRecord", name)
        body.tags((3, "Solid line" if key == "continuous" else ""), (72, 65), (73, 0), (40, 0.0))
    body.tags((0, "ENDTAB"))

    table("LAYER", 1 + len(DXF_LAYERS), "layer_t")
    for name, colour in (("0", 7), *DXF_LAYERS.items()):
        record("LAYER", layer_h[name], "layer_t", "AcDbLayerTableRecord", name)
        body.tags((62, colour), (6, "Continuous"), (370, -3))
    body.tags((0, "ENDTAB"))

    table("STYLE", 1, "style_t")
    record("STYLE", h["style"], "style_t", "AcDbTextStyleTableRecord", "Standard")
    body.tags((40, 0.0), (41, 1.0), (50, 0.0), (71, 0), (42, LABEL_HEIGHT_MM), (3, "txt"), (4, ""))
    body.tags((0, "ENDTAB"))

    table("VIEW", 0, "view_t")
    body.tags((0, "ENDTAB"))
    table("UCS", 0, "ucs_t")
    body.tags((0, "ENDTAB"))

    table("APPID", 1, "appid_t")
    record("APPID", h["acad"], "appid_t", "AcDbRegAppTableRecord", "ACAD")
    body.tags((0, "ENDTAB"))

    table("DIMSTYLE", 1, "dimstyle_t")
    body.tags((100, "AcDbDimStyleTable"), (71, 0))
    record("DIMSTYLE", h["dimstyle"], "dimstyle_t", "AcDbDimStyleTableRecord", "Standard",
           handle_code=105)
    body.tags((340, h["style"]))
    body.tags((0, "ENDTAB"))

    table("BLOCK_RECORD", 2, "brec_t")
    for key, name in (("ms_rec", "*Model_Space"), ("ps_rec", "*Paper_Space")):
        record("BLOCK_RECORD", h[key], "brec_t", "AcDbBlockTableRecord", name)
        body.tags((280, 1), (281, 0))
    body.tags((0, "ENDTAB"))
    body.tags((0, "ENDSEC"))

    body.tags((0, "SECTION"), (2, "BLOCKS"))
    for blk, end, rec, name, paper in (("ms_blk", "ms_end", "ms_rec", "*Model_Space", False),
                                       ("ps_blk", "ps_end", "ps_rec", "*Paper_Space", True)):
        body.tags((0, "BLOCK"), (5, h[blk]), (330, h[rec]), (100, "AcDbEntity"))
        if paper:
            body.tag(67, 1)
        body.tags((8, "0"), (100, "AcDbBlockBegin"), (2, name), (70, 0))
        body.point(0.0, 0.0)
        body.tags((3, name), (1, ""))
        body.tags((0, "ENDBLK"), (5, h[end]), (330, h[rec]), (100, "AcDbEntity"))
        if paper:
            body.tag(67, 1)
        body.tags((8, "0"), (100, "AcDbBlockEnd"))
    body.tags((0, "ENDSEC"))

    def entity(kind: str, layer: str, subclass: str) -> None:
        body.tags((0, kind), (5, body.handle()), (330, h["ms_rec"]), (100, "AcDbEntity"),
                  (8, layer), (100, subclass))

    body.tags((0, "SECTION"), (2, "ENTITIES"))
    for poly in drawing.units_mm:
        entity("LWPOLYLINE", "UNITS", "AcDbPolyline")
        body.tags((90, len(poly)), (70, 1), (43, 0.0))
        for px, py in poly:
            body.tags((10, float(px)), (20, float(py)))
    for a, b in drawing.ligaments_mm:
        entity("LINE", "LIGAMENTS", "AcDbLine")
        body.point(*a)
        body.point(*b, code=11)
    for a, b in drawing.scale_bar_lines_mm:
        entity("LINE", "ANNOTATIONS", "AcDbLine")
        body.point(*a)
        body.point(*b, code=11)
    for t in drawing.texts:
        entity("TEXT", "ANNOTATIONS", "AcDbText")
        body.point(t.x_mm, t.y_mm)
        body.tags((40, float(t.height_mm)), (1, _dxf_text(t.text)), (7, "Standard"),
                  (100, "AcDbText"))
    body.tags((0, "ENDSEC"))

    body.tags((0, "SECTION"), (2, "OBJECTS"))
    body.tags((0, "DICTIONARY"), (5, h["root"]), (330, 0), (100, "AcDbDictionary"), (281, 1),
              (3, "ACAD_GROUP"), (350, h["groups"]))
    body.tags((0, "DICTIONARY"), (5, h["groups"]), (330, h["root"]), (100, "AcDbDictionary"),
              (281, 1))
    body.tags((0, "ENDSEC"), (0, "EOF"))

    head = _Dxf()
    head.tags((0, "SECTION"), (2, "HEADER"), (9, "$ACADVER"), (1, "AC1024"),
              (9, "$DWGCODEPAGE"), (3, "ANSI_1252"), (9, "$INSBASE"))
    head.point(0.0, 0.0)
    head.tag(9, "$EXTMIN")
    head.point(x0, y0)
    head.tag(9, "$EXTMAX")
    head.point(x1, y1)
    head.tags((9, "$LIMMIN"), (10, float(x0)), (20, float(y0)),
              (9, "$LIMMAX"), (10, float(x1)), (20, float(y1)))
    head.tags((9, "$INSUNITS"), (70, 4), (9, "$MEASUREMENT"), (70, 1), (9, "$LUNITS"), (70, 2),
              (9, "$HANDSEED"), (5, body.handseed), (0, "ENDSEC"))
    head.tags((0, "SECTION"), (2, "CLASSES"), (0, "ENDSEC"))
    return "\n".join(head.lines + body.lines) + "\n"


# ------------------------------------------------------------------------------------------ CLI


def write_svg(path: str | Path, drawing: FabricationDrawing) -> Path:
    """Write the SVG file; returns its path."""
    path = Path(path)
    path.write_text(svg_document(drawing), encoding="utf-8")
    return path


def write_dxf(path: str | Path, drawing: FabricationDrawing) -> Path:
    """Write the DXF file (UTF-8, as DXF R2007 and later are); returns its path."""
    path = Path(path)
    path.write_text(dxf_document(drawing), encoding="utf-8")
    return path


def design_name(path: str | Path) -> str:
    """Name of a design file: its "name" key, else its "task" key, else the file stem."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        doc = None
    if isinstance(doc, dict):
        for key in ("name", "task"):
            value = doc.get(key)
            if isinstance(value, str) and value.strip():
                return value.strip()
    return path.stem
