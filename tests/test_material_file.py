"""Material files (metarig-material/1): round trip, the default file, bad files, and `--material`
in `metarig simulate`, `metarig design` and `metarig rig` (specimen and comparison)."""

import dataclasses
import json
import math

import pytest

from design_engine.physics.lattice import kagome, quads
from design_engine.physics.material import Material
from design_engine.physics.material_file import (DEFAULT_PATH, FORMAT, SI_UNITS, MaterialFileError,
                                                 default_material, load_material,
                                                 load_material_file, material_for_scene,
                                                 material_from_si, material_to_si,
                                                 read_material_file, save_material, with_material)

FIELDS = [f.name for f in dataclasses.fields(Material)]


def _same(a: Material, b: Material) -> bool:
    return all(getattr(a, n) == getattr(b, n) and type(getattr(a, n)) is type(getattr(b, n))
               for n in FIELDS)


def _stiffer(path, factor=2.0):
    v = {k: factor * material_to_si(Material.paper(quads(4, 3)))[k]
         for k in ("k_stretch", "k_shear", "k_bend")}
    return save_material(path, v, source="test", notes=f"{factor}x stiffer ligaments")


@pytest.mark.parametrize("lattice", [quads(4, 3), quads(24, 16), kagome(3, 2)], ids=str)
def test_the_default_file_is_material_paper_bit_for_bit(lattice):
    assert _same(default_material(lattice), Material.paper(lattice))
    # and the spec section 10 literals, as Material.paper had them before the file
    m = Material.paper(lattice)
    assert (m.k_stretch, m.k_shear, m.k_bend, m.k_contact, m.density) == (120.0, 1.19, 1.5, 1.5,
                                                                         6.18e-3)
    assert (m.contact_min, m.contact_cutoff) == (math.radians(-15.0), math.radians(-10.0))
    s = lattice.spacing
    assert m.damping_u == 2.0 * 0.0186 * math.sqrt(6.18e-3 * lattice.unit_area_hat * s**2 * 1.19)
    assert m.damping_theta == 2.0 * 0.0186 * math.sqrt(6.18e-3 * lattice.unit_inertia_hat * s**4
                                                       * 1.5)


def test_the_default_file_is_valid_si_with_the_spec_damping():
    values, stderr = load_material_file(DEFAULT_PATH)
    assert values["k_stretch"] == 1.2e5 and values["damping_ratio"] == 0.0186 and stderr == {}
    si = material_to_si(Material.paper(quads(24, 16)))
    assert si["damping_u"] == pytest.approx(2.8761e-2, rel=1e-4)  # spec 10, kg/s
    assert si["damping_theta"] == pytest.approx(1.18850e-7, rel=1e-5)  # kg m^2/s
    m = Material.paper(quads(4, 3), contact_min_deg=-10.0, contact_cutoff_deg=-5.0)
    assert m.contact_min == math.radians(-10.0) and m.contact_cutoff == math.radians(-5.0)


def test_save_load_round_trip_values_stderrs_units(tmp_path):
    m = Material.paper(kagome(3, 2))
    values = material_to_si(m)
    assert set(values) <= set(SI_UNITS)
    stderr = {"k_shear": 25.0, "damping_u": 1e-3}
    path = save_material(tmp_path / "sub" / "m.toml", values, stderr, source="fit", notes="x")
    text = path.read_text()
    assert f'format = "{FORMAT}"' in text and 'unit = "N m s"' in text and "created = " in text
    got, got_err = load_material_file(path)
    assert got_err == stderr
    for k, v in values.items():
        assert got[k] == v  # repr round trip: exact
    assert got["damping_ratio"] == 0.0186  # not in the file: the default's
    back = load_material(path, kagome(3, 2))
    for n in FIELDS:
        assert getattr(back, n) == pytest.approx(getattr(m, n), rel=1e-14)
    assert not list(tmp_path.glob("sub/.*.tmp"))  # atomic write leaves no temporary


def test_missing_parameters_take_the_default_and_damping_is_rederived(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(f'format = "{FORMAT}"\n[parameters]\nk_shear = 2380.0\n')
    lat = quads(4, 3)
    m, d = load_material(path, lat), Material.paper(lat)
    assert m.k_shear == 2.38 and m.k_stretch == d.k_stretch and m.k_bend == d.k_bend
    assert m.damping_u == pytest.approx(d.damping_u * math.sqrt(2.0), rel=1e-14)
    assert m.damping_theta == d.damping_theta
    # explicit damping wins over the ratio; no lattice needed then
    m2 = material_from_si({"damping_u": 0.05, "damping_theta": 2e-7})
    assert m2.damping_u == 0.05 and m2.damping_theta == pytest.approx(0.2)
    with pytest.raises(MaterialFileError, match="damping_ratio"):
        material_from_si({"k_shear": 1000.0})


@pytest.mark.parametrize("text, message", [
    ('format = "metarig-material/1"\n[parameters\n', "not valid TOML"),
    ('format = "metarig-material/1"\n[parameters]\nk_shearr = 1.0\n', "k_shearr: unknown"),
    ('format = "metarig-material/1"\n[parameters]\nk_bend = -1e-3\n', "k_bend: must be > 0"),
    ('format = "metarig-material/2"\n', "format: expected"),
    ('[parameters]\nk_bend = 1e-3\n', "format: expected"),
    (('format = "metarig-material/1"\n[parameters]\ncontact_min_deg = -5.0\n'
      'contact_cutoff_deg = -10.0\n'), "contact_min_deg: must be below contact_cutoff_deg"),
    ('format = "metarig-material/1"\n[parameters.k_shear]\nvalue = 1.19\nunit = "N/mm"\n',
     "k_shear: unit must be 'N/m'"),
    ('format = "metarig-material/1"\n[parameters.k_shear]\nvalue = 1190.0\nstderr = -1.0\n',
     "k_shear: stderr must be >= 0"),
    ('format = "metarig-material/1"\n[parameters.k_shear]\nvalue = "stiff"\n',
     "k_shear: value must be a number"),
    ('format = "metarig-material/1"\n[parameters.k_shear]\nvalue = nan\n', "k_shear: value must be finite"),
    ('format = "metarig-material/1"\ncolour = "red"\n', "colour: unknown key"),
    ('format = "metarig-material/1"\n[parameters.density]\nvalu = 6.0\n', "density.valu: unknown"),
    # the default file cut after its header (half its bytes): no parameter left
    ('format = "metarig-material/1"\nsource = "x"\n# [parameters.k_stretch]\n',
     "sets no parameter"),
])
def test_bad_files_give_one_line_naming_the_file_and_key(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(MaterialFileError) as e:
        load_material(path, quads(4, 3))
    msg = str(e.value)
    assert message in msg and str(path) in msg and "\n" not in msg
    assert isinstance(e.value, ValueError)


def test_missing_file_and_json_files(tmp_path):
    with pytest.raises(MaterialFileError, match="no such material file"):
        load_material_file(tmp_path / "nope.toml")
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"format": FORMAT, "parameters": {"k_shear": {"value": 1000.0,
                                                                             "stderr": 5.0}}}))
    values, stderr = load_material_file(path)
    assert values["k_shear"] == 1000.0 and stderr == {"k_shear": 5.0}


def test_a_scene_keeps_its_contact_angles_unless_the_file_sets_them(tmp_path):
    from design_engine.physics.scenes import build_scene

    scene = build_scene("focusing-24x16", nx=4, ny=3, contact_deg=(-10.0, -5.0))
    m = with_material(scene, _stiffer(tmp_path / "s.toml")).material
    assert m.k_shear == 2 * 1.19 and m.contact_min == scene.material.contact_min
    assert m.contact_cutoff == scene.material.contact_cutoff
    path = tmp_path / "c.toml"
    path.write_text(f'format = "{FORMAT}"\n[parameters]\ncontact_min_deg = -20.0\n'
                    'contact_cutoff_deg = -12.0\n')
    m, given = material_for_scene(scene, path)
    assert m.contact_min == math.radians(-20.0) and given == read_material_file(path)[0]


def _simulate(tmp_path, name, *extra):
    """`metarig simulate` of a 4x3 scene. Fixed-step Verlet at the default step: the material
    is an argument of that one compiled program, while the automatic choice compiled its
    frequency estimate (the material a constant in it) and a step of its own per material."""
    from design_engine.commands.simulate import simulate_main

    out = tmp_path / name
    assert simulate_main(["--nx", "4", "--ny", "3", "--amplitude", "0.002", "--samples", "40",
                          "--solver", "verlet", "--max-dt", "5e-6", "--out", str(out), "--no-plots", "--quiet",
                          *extra]) == 0
    return json.loads((out / "summary.json").read_text())


def test_simulate_material_flag_changes_the_result(tmp_path, capsys):
    base = _simulate(tmp_path, "base")
    stiff = _simulate(tmp_path, "stiff", "--material", str(_stiffer(tmp_path / "s.toml")))
    assert stiff["material_si"]["k_shear"] == pytest.approx(2 * base["material_si"]["k_shear"])
    assert stiff["target_ke_mean_J"] != pytest.approx(base["target_ke_mean_J"], rel=1e-3)
    # the default file gives the default result
    same = _simulate(tmp_path, "same", "--material", str(DEFAULT_PATH))
    assert same["target_ke_mean_J"] == base["target_ke_mean_J"]
    bad = tmp_path / "bad.toml"
    bad.write_text(f'format = "{FORMAT}"\n[parameters]\nk_stretch = -1.0\n')
    from design_engine.commands.simulate import simulate_main

    assert simulate_main(["--nx", "4", "--ny", "3", "--material", str(bad), "--out",
                          str(tmp_path / "bad"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "k_stretch" in err[0] and str(bad) in err[0]


def test_task_material_reaches_every_scene_and_the_record(tmp_path):
    from design_engine.design.task import TaskError, load_task

    path = _stiffer(tmp_path / "s.toml")
    task = load_task("focus-vs-protect", size=(8, 6), material=path)
    ref = load_task("focus-vs-protect", size=(8, 6))
    assert len(task.scenes) == 2
    for k, s in task.scenes.items():
        assert s.material.k_shear == 2 * 1.19
        assert s.material.contact_min == ref.scenes[k].material.contact_min == math.radians(-10.0)
    assert task.document["material"]["si"] == read_material_file(path)[0]
    assert "material" not in ref.document
    bad = tmp_path / "bad.toml"
    bad.write_text('format = "x"\n')
    with pytest.raises(TaskError, match="material: .*format"):
        load_task("focusing", size=(8, 6), material=bad)


def test_design_material_flag_is_accepted(tmp_path):
    from design_engine.commands.design import design_main

    out = tmp_path / "run"
    path = _stiffer(tmp_path / "s.toml")
    assert design_main(["focusing", "--size", "8x6", "--max-evals", "1", "--out", str(out),
                        "--material", str(path), "--quiet", "--no-plots"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["task"]["material"]["si"]["k_shear"] == 2 * 1190.0


def test_rig_specimen_and_comparison_use_the_material_file(tmp_path):
    from comparison.experiment import scene_of_design
    from hardware_sim.specimen import NOMINAL, SpecimenConfig, build

    path = _stiffer(tmp_path / "s.toml")
    # the material file's way to the truth and to the comparison: a specimen without the
    # imperfections of a fabricated sample, whose material is the file's (scalars) exactly
    cfg = SpecimenConfig(scene="focusing-24x16", nx=6, ny=4, material_path=str(path),
                         imperfections=NOMINAL)
    s = build(cfg)
    assert s.scene.material.k_shear == 2 * 1.19
    assert _same(s.scene.material, with_material(build(dataclasses.replace(
        cfg, material_path="")).scene, path).material)
    doc = json.loads(s.design_json())
    assert doc["material_si"] == read_material_file(path)[0]
    assert _same(scene_of_design(doc).material, s.scene.material)
    # a perturbed specimen: the comparison still gets the file's nominal material
    p = build(dataclasses.replace(cfg, perturb=0.1, seed=3))
    assert p.scene.material.k_shear != s.scene.material.k_shear
    assert _same(scene_of_design(json.loads(p.design_json())).material, s.scene.material)
    # without a file: the default, and no material keys in the document
    d = build(dataclasses.replace(cfg, material_path=""))
    assert "material_si" not in json.loads(d.design_json())
    assert _same(scene_of_design(json.loads(d.design_json())).material, d.scene.material)


def test_rig_material_flag_reaches_the_camera_node(tmp_path):
    from ros_nodes.cli_rig import _node_params, _parser, _plan

    path = _stiffer(tmp_path / "s.toml")
    plan = _plan(_parser().parse_args(["--material", str(path)]))
    assert plan.material == str(path.resolve())
    params = _node_params(plan, tmp_path, None)
    assert params["camera"]["material_path"] == str(path.resolve())
    assert json.loads(params["camera"]["material_si"]) == read_material_file(path)[0]
    bad = tmp_path / "bad.toml"
    bad.write_text(f'format = "{FORMAT}"\n[parameters]\nk_bend = 0\n')
    with pytest.raises(ValueError, match="k_bend"):
        _plan(_parser().parse_args(["--material", str(bad)]))
    assert _plan(_parser().parse_args([])).material == ""


def test_the_rig_reads_a_material_file_once(tmp_path, monkeypatch):
    """`metarig rig --material F`: the command reads and checks F, and the camera node's
    specimen takes the values it read (the node may run in another process) without reading
    the file again; the specimen's material is the file's."""
    from design_engine.physics import material_file as mf
    from hardware_sim.specimen import NOMINAL, SpecimenConfig, build
    from ros_nodes.cli_rig import _node_params, _parser, _plan

    path = _stiffer(tmp_path / "s.toml")
    reads = []
    real = mf.read_material_file
    monkeypatch.setattr(mf, "read_material_file", lambda p: (reads.append(p), real(p))[1])
    plan = _plan(_parser().parse_args(["--material", str(path), "--nx", "6", "--ny", "4",
                                       "--scene", "focusing-24x16"]))
    cam = _node_params(plan, tmp_path, None)["camera"]
    specimen = build(SpecimenConfig(scene=cam["scene"], nx=cam["nx"], ny=cam["ny"],
                                    material_path=cam["material_path"],
                                    material_si=cam["material_si"], imperfections=NOMINAL))
    assert len(reads) == 1
    assert specimen.scene.material.k_shear == 2 * 1.19
    assert json.loads(specimen.design_json())["material_si"] == real(path)[0]


def test_a_material_file_is_validated_once_where_it_is_read(tmp_path, monkeypatch):
    """The values are checked when the file is read (`MaterialValues`); scenes, the simulator's
    material and the task take them as they are, and nobody can change them afterwards."""
    from design_engine.physics import material_file as mf
    from design_engine.physics.scenes import build_scene

    path = _stiffer(tmp_path / "s.toml")
    calls = []
    real = mf.check_values
    monkeypatch.setattr(mf, "check_values", lambda *a, **k: calls.append(a) or real(*a, **k))
    given, _ = read_material_file(path)
    assert isinstance(given, mf.MaterialValues) and len(calls) == 2  # the values, then complete
    for name in ("focusing-24x16", "spin-24x16"):
        scene = build_scene(name, nx=4, ny=3)
        assert with_material(scene, given).material == material_for_scene(scene, given)[0]
    assert len(calls) == 2  # nothing validated again downstream
    with pytest.raises(TypeError, match="read-only"):
        given["k_shear"] = 1.0
    with pytest.raises(MaterialFileError, match="k_bend"):
        material_for_scene(scene, {"k_bend": -1.0})  # a plain dict is validated where it comes in
