"""`metarig export`: SVG and DXF written by us, read back with independent parsers (svgelements,
ezdxf; both in the `dev` extra) and checked against the design's own geometry, plus clear
one-line errors."""

import json
import math
import subprocess
import sys

import ezdxf
import numpy as np
import pytest
import svgelements as se
from ezdxf import recover as ezdxf_recover

from design_engine.commands.export import export_main
from design_engine.design.design_io import save_design
from design_engine.physics.lattice import periodic_design, quads, vertex_offsets

# svgelements reports lengths in its pixels: its own inch per mm (0.0393701) at 96 per inch
PX_PER_MM = se.Length("1mm").in_inches() * se.DEFAULT_PPI


@pytest.fixture(scope="module")
def design(tmp_path_factory):
    """A perturbed 4x3 rotating-squares design on file, and its expected vertices (mm)."""
    lattice = quads(4, 3)
    rng = np.random.default_rng(7)
    x = periodic_design(lattice, math.radians(25)) + rng.normal(0.0, 0.15, lattice.n_design)
    path = save_design(tmp_path_factory.mktemp("design") / "d.json", lattice, x, name="test design")
    # expected outlines from the lattice map directly (grid point + vertex offset), not via the
    # centroid + arm route the exporter takes
    verts = lattice.grid_points[:, None, :] + np.asarray(vertex_offsets(lattice, np.asarray(x)))
    return path, lattice, verts


@pytest.fixture(scope="module")
def exported(design, tmp_path_factory):
    path, _, _ = design
    out = tmp_path_factory.mktemp("out")
    rc = export_main([str(path), "--svg", str(out / "d.svg"), "--dxf", str(out / "d.dxf")])
    assert rc == 0
    return out / "d.svg", out / "d.dxf"


def _svg_to_design_mm(svg, pts_px: np.ndarray) -> np.ndarray:
    """Page pixels (svgelements, viewBox applied) -> design frame mm (y up)."""
    vb = svg.viewbox
    mm = pts_px / PX_PER_MM + np.array([vb.x, vb.y])
    return mm * np.array([1.0, -1.0])


def test_svg_units_ligaments_scale_and_name(design, exported):
    _, lattice, verts = design
    svg_path, _ = exported
    svg = se.SVG.parse(str(svg_path))
    # physical size in mm, and the viewBox spans the same numbers: 1 user unit = 1 mm
    root = se.SVG.parse(str(svg_path), reify=False)
    assert root.values["width"].endswith("mm") and root.values["height"].endswith("mm")
    assert float(root.values["width"][:-2]) == pytest.approx(svg.viewbox.width, abs=1e-9)
    assert float(root.values["height"][:-2]) == pytest.approx(svg.viewbox.height, abs=1e-9)
    assert svg.width == pytest.approx(svg.viewbox.width * PX_PER_MM, rel=1e-12)

    units = list(svg.get_element_by_id("units"))
    assert len(units) == lattice.n_blocks
    for b in range(lattice.n_blocks):
        el = svg.get_element_by_id(f"unit-{b}")
        assert isinstance(el, se.Polygon) and el in units
        assert el.fill is None or el.fill.value is None  # stroke only: cut lines
        assert el.stroke is not None and el.stroke.value is not None
        pts = _svg_to_design_mm(svg, np.array([[p.x, p.y] for p in el.points]))
        np.testing.assert_allclose(pts, verts[b], atol=1e-6)
        # counter-clockwise after undoing the flip: the drawing is not mirrored
        q = np.roll(pts, 1, axis=0)
        assert np.sum(q[:, 0] * pts[:, 1] - q[:, 1] * pts[:, 0]) > 0

    ligs = [e for e in svg.get_element_by_id("ligaments") if isinstance(e, se.SimpleLine)]
    assert len(ligs) == lattice.n_bonds
    flat = verts.reshape(-1, 2)
    for i, el in enumerate(ligs):
        assert el.values["id"] == f"ligament-{i}"
        ends = _svg_to_design_mm(svg, np.array([[el.x1, el.y1], [el.x2, el.y2]]))
        np.testing.assert_allclose(ends, flat[lattice.bonds[i]], atol=1e-6)
        assert np.linalg.norm(ends[1] - ends[0]) == pytest.approx(lattice.ligament_length, abs=1e-6)
    assert ligs[0].stroke != units[0].stroke  # another colour

    ann = list(svg.get_element_by_id("annotations"))
    texts = {e.values["id"]: e.text for e in ann if isinstance(e, se.Text)}
    assert texts == {"scale-bar-label": "10 mm", "design-name": "test design"}
    bar = next(e for e in ann if isinstance(e, se.Path))
    seg = [s for s in bar.segments() if isinstance(s, se.Line)]
    lengths = sorted(s.length() / PX_PER_MM for s in seg)
    assert lengths[-1] == pytest.approx(10.0, abs=1e-6)  # the bar itself, 10 mm on paper
    # everything drawn lies inside the page
    bbox = svg.bbox()
    assert bbox[0] >= 0 and bbox[1] >= 0 and bbox[2] <= svg.width and bbox[3] <= svg.height


def test_dxf_layers_units_ligaments_and_header(design, exported):
    _, lattice, verts = design
    _, dxf_path = exported
    doc, auditor = ezdxf_recover.readfile(str(dxf_path))
    assert not auditor.has_errors and not auditor.has_fixes, [e.message for e in auditor.errors]
    assert doc.dxfversion >= "AC1015"
    assert doc.header["$INSUNITS"] == 4  # millimetres
    assert {"UNITS", "LIGAMENTS", "ANNOTATIONS"} <= {layer.dxf.name for layer in doc.layers}
    msp = doc.modelspace()

    polys = msp.query('LWPOLYLINE[layer=="UNITS"]')
    assert len(polys) == lattice.n_blocks == len(msp.query("LWPOLYLINE"))
    for b, pl in enumerate(polys):
        assert pl.closed
        np.testing.assert_allclose(np.array(list(pl.get_points("xy"))), verts[b], atol=1e-6)

    lines = msp.query('LINE[layer=="LIGAMENTS"]')
    assert len(lines) == lattice.n_bonds
    flat = verts.reshape(-1, 2)
    for i, ln in enumerate(lines):
        ends = np.array([[ln.dxf.start.x, ln.dxf.start.y], [ln.dxf.end.x, ln.dxf.end.y]])
        np.testing.assert_allclose(ends, flat[lattice.bonds[i]], atol=1e-6)

    texts = sorted(t.dxf.text for t in msp.query("TEXT"))
    assert texts == ["10 mm", "test design"]
    assert all(t.dxf.layer == "ANNOTATIONS" for t in msp.query("TEXT"))
    bar = msp.query('LINE[layer=="ANNOTATIONS"]')
    longest = max(math.dist(ln.dxf.start, ln.dxf.end) for ln in bar)
    assert longest == pytest.approx(10.0, abs=1e-9)
    # the annotations sit below the units, not on them
    assert max(ln.dxf.start.y for ln in bar) < verts[..., 1].min()


def test_name_falls_back_to_task_then_stem(tmp_path):
    lattice = quads(2, 2)
    x = periodic_design(lattice, math.radians(20))
    task = save_design(tmp_path / "a.json", lattice, x, task="focusing")
    stem = save_design(tmp_path / "plain-design.json", lattice, x)
    for path, expected in ((task, "focusing"), (stem, "plain-design")):
        out = tmp_path / f"{path.stem}.dxf"
        assert export_main([str(path), "--dxf", str(out)]) == 0
        assert [t.dxf.text for t in ezdxf.readfile(str(out)).modelspace().query("TEXT")] == [
            "10 mm", expected]


def _one_line_error(capsys, *fragments):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("metarig export: error: ")
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0]


def test_damaged_and_foreign_design_files_are_refused(tmp_path, capsys):
    damaged = tmp_path / "damaged.json"
    damaged.write_text('{"format": "metarig-design/1", "lattice": ')
    assert export_main([str(damaged), "--svg", str(tmp_path / "o.svg")]) == 2
    _one_line_error(capsys, "damaged.json", "not readable JSON")
    foreign = tmp_path / "foreign.json"
    foreign.write_text(json.dumps({"format": "something-else"}))
    assert export_main([str(foreign), "--svg", str(tmp_path / "o.svg")]) == 2
    _one_line_error(capsys, "not a metarig-design/1")
    assert export_main([str(tmp_path / "missing.json"), "--dxf", str(tmp_path / "o.dxf")]) == 2
    _one_line_error(capsys, "does not exist")
    assert not (tmp_path / "o.svg").exists() and not (tmp_path / "o.dxf").exists()


def test_inconsistent_design_is_refused(tmp_path, capsys):
    lattice = quads(2, 2)
    path = save_design(tmp_path / "d.json", lattice, periodic_design(lattice, 0.3))
    doc = json.loads(path.read_text())
    doc["design_m"] = doc["design_m"][:-1]
    path.write_text(json.dumps(doc))
    assert export_main([str(path), "--svg", str(tmp_path / "o.svg")]) == 2
    _one_line_error(capsys, "needs", "values")


def test_no_output_requested_and_unwritable_output(design, tmp_path, capsys):
    path, _, _ = design
    assert export_main([str(path)]) == 2
    _one_line_error(capsys, "--svg", "--dxf")
    assert export_main([str(path), "--svg", str(tmp_path / "no" / "such" / "dir" / "o.svg")]) == 2
    _one_line_error(capsys, "does not exist")
    assert export_main([str(path), "--dxf", str(tmp_path)]) == 2
    _one_line_error(capsys, "directory")
    assert export_main([str(path), "--svg", "--dxf"]) == 2  # argparse usage error, one line too
    _one_line_error(capsys)
    assert export_main([str(path), "--svg", str(tmp_path / "o.svg"), "--scale-bar", "-1"]) == 2
    _one_line_error(capsys, "scale bar")


def test_command_line_refuses_an_inverted_design_in_one_line(tmp_path):
    """As a separate process (`python -m metarig export`): nothing but the error line on
    stderr, even once JAX has started (its start-up logging must not leak out)."""
    lattice = quads(2, 2)
    path = save_design(tmp_path / "d.json", lattice, periodic_design(lattice, 0.3))
    doc = json.loads(path.read_text())
    doc["design_m"][4] = -0.02  # x-shift of block 0's vertex 0: 20 mm to the left, through the unit
    path.write_text(json.dumps(doc))
    r = subprocess.run([sys.executable, "-m", "metarig", "export", str(path), "--svg",
                        str(tmp_path / "o.svg")], capture_output=True, text=True, timeout=300,
                       check=False)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("metarig export: error: "), r.stderr
    assert "block 0" in r.stderr and not (tmp_path / "o.svg").exists()
