"""Bookkeeping of the speed-accuracy studies (selection rule, RHS counts)."""

import diffrax

from design_engine.solve.fixed_step import FixedStepVerlet
from design_engine.solve.implicit_step import ImplicitNewmark
from design_engine.solve.simulate import SolverConfig
from design_engine.studies.methods import rhs_evaluations
from design_engine.studies.work_precision import acceptable, fastest_acceptable


def _row(t, j=1e-4, g=1e-3, cos=0.99999, **kw):
    return {"family": "x", "value_and_grad_s": t, "J_rel_err": j, "grad_rel_err": g,
            "grad_cosine": cos, **kw}


def test_selection_takes_the_fastest_method_acceptable_on_every_scene():
    results = {"scenes": {
        "a": {"methods": {"fast-but-wrong": _row(0.1, j=2e-2), "slow": _row(9.0), "mid": _row(1.0),
                          "mid-fails-b": _row(0.5)}},
        "b": {"methods": {"fast-but-wrong": _row(0.1), "slow": _row(9.0), "mid": _row(1.5),
                          "mid-fails-b": {"family": "x", "error": "SimulationError: diverged"}}},
    }}
    assert not acceptable(results["scenes"]["a"]["methods"]["fast-but-wrong"])
    assert not acceptable(_row(1.0, cos=0.99))
    assert fastest_acceptable(results)[0] == "mid"


def test_rhs_evaluation_counts():
    assert rhs_evaluations(SolverConfig(), 100) == 100 * 6 + 1  # Dopri5: 7 stages, FSAL
    assert rhs_evaluations(SolverConfig(solver=diffrax.Tsit5()), 10) == 61
    assert rhs_evaluations(SolverConfig(solver=FixedStepVerlet(max_dt=0.01)), 500) == 501
    # one force evaluation per chord iteration, plus the initial acceleration
    assert rhs_evaluations(SolverConfig(solver=ImplicitNewmark(iterations=3)), 200) == 601


def test_a_damaged_results_file_or_cache_ends_the_bench_in_one_line(tmp_path, capsys):
    """A cut work_precision.json (the study's resume state) or reference cache is refused,
    named, before any solve, and left as it is."""
    from design_engine.commands.bench import bench_main

    cases = {"work_precision.json": b'{"scenes": {"focusing-24x16": {"J_ref": 1.',
             "reference_focusing-24x16.npz": b"PK\x03\x04\x14\x00\x00\x00"}
    for name, data in cases.items():
        out = tmp_path / name.split(".")[0]
        out.mkdir()
        (out / name).write_bytes(data)
        code = bench_main(["work-precision", "--out", str(out), "--quick", "--scene",
                           "focusing-24x16"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert err[0].startswith(f"metarig bench: error: {out / name}: damaged"), err
        assert [p.name for p in out.iterdir()] == [name] and (out / name).read_bytes() == data
