"""`metarig calibrate SOURCE... --out DIR`: fit material constants to a recorded test.

SOURCE (kind auto-detected, or `--kind`):
- hinge: Instron-style hinge-test files (`.csv`/`.txt`, 3 header lines, then time s,
  displacement m, force N; see `hardware_sim.characterisation`), or a folder of them;
  fits k_stretch, k_shear, k_bend (spec 12.1);
- oscillation: a free-oscillation tracks `.npz` (`metarig.trajectory` format, the free unit's
  rotation at 960 fps); fits the damping (log-decrement of spec 12.2 and a fit through the
  engine) and k_bend;
- pulse: a rig run folder or `.mcap` recording; fits the chosen parameters to the tracked unit
  positions through the engine under the measured input.

Writes `DIR/calibration.json` (`{"parameters": {name: {"value", "stderr", "unit"}}, "residual":
rms SI, "source": ...}`, SI, engine material names; a pulse fit's stderr includes its
`model_error`, the misfit beyond the tracking noise), `DIR/material.toml` (metarig-material/1)
and `DIR/calibration.png` (data against the fitted model). Bad inputs: one line, exit code 2.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from metarig.argtypes import positive, text
from ros_nodes.recorded_run import InputError, pulse_inputs

KINDS = ("auto", "hinge", "oscillation", "pulse")
HINGE_SUFFIXES = (".csv", ".txt", ".dat")


def detect_kind(sources: list[Path]) -> tuple[str, list[Path]]:
    """(kind, files) of the inputs: folders with an .mcap are runs, other folders hold hinge
    files; .mcap -> pulse, .npz -> oscillation, .csv/.txt/.dat -> hinge."""
    files, kinds = [], set()
    for s in sources:
        if s.is_dir():
            if sorted(s.glob("*.mcap")):
                kinds.add("pulse")
                files.append(s)
                continue
            found = sorted(p for p in s.iterdir() if p.suffix.lower() in HINGE_SUFFIXES)
            if not found:
                raise InputError(f"{s}: the folder holds neither an .mcap recording nor hinge-test "
                                 "files (.csv, .txt)")
            kinds.add("hinge")
            files.extend(found)
        elif not s.exists():
            raise InputError(f"{s}: no such file or folder")
        elif s.suffix.lower() == ".mcap":
            kinds.add("pulse")
            files.append(s)
        elif s.suffix.lower() == ".npz":
            kinds.add("oscillation")
            files.append(s)
        elif s.suffix.lower() in HINGE_SUFFIXES:
            kinds.add("hinge")
            files.append(s)
        else:
            raise InputError(f"{s}: unknown input type (expected a run folder, .mcap, .npz "
                             "tracks or .csv hinge-test files)")
    if len(kinds) != 1:
        raise InputError(f"the inputs mix test kinds ({', '.join(sorted(kinds))}); calibrate "
                         "one kind at a time")
    return kinds.pop(), files


def _start_material(path, lattice):
    if path is None:
        return None
    from design_engine.physics.material_file import load_material

    return load_material(path, lattice)


# --- the three kinds -------------------------------------------------------------------------


class Progress:
    """A tqdm bar over the model evaluations of a fit (stderr): stage, count, current rms."""

    def __init__(self, enabled: bool = True):
        self.enabled, self.bar, self.stage = enabled, None, None

    def __call__(self, stage: str, evaluation: int, rms: float):
        if not self.enabled:
            return
        if stage != self.stage:
            self.close()
            from tqdm import tqdm

            self.bar, self.stage = tqdm(desc=f"calibrate ({stage})", unit="eval",
                                        file=sys.stderr, leave=True), stage
        self.bar.update(1)
        self.bar.set_postfix_str(f"rms {rms:.4g}")

    def close(self):
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def calibrate_hinge(files, fit, material_path=None, progress=None):
    from design_engine.calibration.fit import STIFFNESSES
    from design_engine.calibration.hinge import fit_hinge, hinge_sample, read_hinge_file

    sample = hinge_sample()
    records = [read_hinge_file(f) for f in files]
    out = fit_hinge(records, fit or STIFFNESSES,
                        _start_material(material_path, sample.lattice), sample, progress=progress)
    return out, {}


def read_oscillation_tracks(path: Path):
    """(t s [n], theta rad [n]) of the free unit in a tracks .npz (invalid frames dropped)."""
    from metarig.readback import READ_ERRORS
    from metarig.trajectory import Trajectory

    try:
        traj = Trajectory.load_npz(path)  # TrajectoryFileError is a ValueError
        with np.load(path) as f:
            unit = int(f["free_unit"]) if "free_unit" in f.files else None
    except READ_ERRORS as exc:
        raise InputError(str(exc).splitlines()[0] if str(exc) else f"{path}: unreadable") from None
    if traj.n_units > 2:
        raise InputError(f"{path}: {traj.n_units} units tracked; a free-oscillation record holds "
                         "the free unit (and the held one)")
    ok = traj.valid
    if unit is None:
        th = np.where(ok, traj.q[..., 2], np.nan)
        unit = int(np.nanargmax(np.nanstd(th, axis=0))) if traj.n_units > 1 else 0
    if not 0 <= unit < traj.n_units:
        raise InputError(f"{path}: free_unit {unit} is not a tracked unit")
    keep = ok[:, unit]
    return traj.t[keep], traj.q[keep, unit, 2]


def calibrate_oscillation(files, fit, material_path=None, progress=None):
    from design_engine.calibration.oscillation import (DEFAULT_OSC_FIT, fit_oscillation,
                                                       oscillation_sample)

    if len(files) != 1:
        raise InputError("give one free-oscillation tracks file")
    t, theta = read_oscillation_tracks(files[0])
    sample = oscillation_sample()
    out = fit_oscillation(t, theta, fit or DEFAULT_OSC_FIT,
                              _start_material(material_path, sample.lattice), sample,
                              progress=progress)
    return out, {}


def calibrate_pulse(files, fit, material_path=None, poses_source="auto", calibration=None,
                    workers=None, progress=None):
    from design_engine.calibration.pulse import DEFAULT_PULSE_FIT, fit_pulse

    if len(files) != 1:
        raise InputError("give one run folder or .mcap recording")
    scene, poses, t0, (t_in, u_in), stage = pulse_inputs(files[0], poses_source, calibration,
                                                         workers)
    out = fit_pulse(scene, poses.t + t0, poses.q, poses.valid, t_in, u_in,
                        *(stage or (None, None)), fit=fit or DEFAULT_PULSE_FIT,
                        start=_start_material(material_path, scene.lattice), progress=progress,
                        tracked_sigma=poses.sigma)
    return out, {"n_frames": poses.n_t, "n_units": poses.n_units,
                 "weighted_by_pose_sigma": out.extra["weighted_by_pose_sigma"],
                 "solver": out.extra["config"], "windows_frames": out.extra["windows"],
                 "min_void_margin_rad": out.extra["min_void_margin"],
                 "model_error": out.extra["model_error"],
                 "stderr_statistical": out.extra["stderr_statistical"]}


# --- outputs ----------------------------------------------------------------------------------


def calibration_document(fit, kind: str, sources, extra: dict) -> dict:
    """The `calibration.json` document (SI)."""
    doc = {
        "parameters": fit.parameters_json(),
        "residual": fit.rms,
        "residual_unit": fit.residual_unit,
        "residual_sigma": fit.sigma,
        "n_residuals": fit.n,
        "dof": fit.dof,
        "source": ", ".join(str(s) for s in sources),
        "kind": kind,
        "fit": list(fit.names),
        "undetermined": fit.undetermined,
        "start": {n: float(v) for n, v in fit.start.items()},
        "correlation": np.round(fit.correlation, 6).tolist(),
        "stderr_gauss_newton": {n: float(v) for n, v in
                                fit.extra.get("stderr_gauss_newton", {}).items()},
        "iterations": fit.iterations,
        "converged": bool(fit.converged),
        "method": "Levenberg-Marquardt on log(value), Jacobian by jax.jacfwd through the "
                  "engine; stderr from s^2 (J^T J)^-1 (Gauss-Newton; pulse: cluster-robust, "
                  "one cluster per unit), delta method",
        "wall_s": fit.wall_s,
    }
    if "derived" in fit.extra:
        doc["derived"] = fit.extra["derived"]
    if "log_decrement" in fit.extra:
        ld = fit.extra["log_decrement"]
        doc["log_decrement"] = {k: (float(v) if isinstance(v, (int, float, np.floating)) else v)
                                for k, v in ld.items() if not isinstance(v, np.ndarray)}
    doc.update(extra)
    return doc


def material_values(fit) -> tuple[dict, dict]:
    """(values, stderr) of the fitted material parameters (SI) for the material file."""
    from design_engine.physics.material_file import SI_UNITS

    vals, errs = {}, {}
    for n in fit.names:
        if n in SI_UNITS and n != "damping_ratio":
            vals[n], errs[n] = fit.values[n], fit.stderr[n]
    for n, d in fit.extra.get("derived", {}).items():
        vals[n], errs[n] = d["value"], d["stderr"]
    return vals, errs


def plot(fit, kind: str, path: Path) -> Path:
    """Data against the fitted (and start) model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if kind == "hinge":
        curves = fit.extra["curves"]
        tests = list(dict.fromkeys(c[0] for c in curves))
        fig, axes = plt.subplots(1, len(tests), figsize=(4.2 * len(tests), 3.6), squeeze=False)
        for ax, test in zip(axes[0], tests):
            for i, (_, d, data, f, s) in enumerate(c for c in curves if c[0] == test):
                ax.plot(d * 1e3, data, ".", ms=2, color="0.4", label="data" if i == 0 else None)
                ax.plot(d * 1e3, s, "--", color="tab:orange", label="start" if i == 0 else None)
                ax.plot(d * 1e3, f, "-", color="tab:blue", label="fitted" if i == 0 else None)
            ax.set(title=test, xlabel="displacement (mm)", ylabel="force (N)")
            ax.legend(fontsize=8)
    elif kind == "oscillation":
        c = fit.extra["curves"]
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
        a1.plot(c["t_s"], np.degrees(c["data"]), ".", ms=2, color="0.4", label="tracked")
        a1.plot(c["t_s"], np.degrees(c["fitted"]), "-", lw=0.8, color="tab:blue", label="fitted")
        a1.set(ylabel="rotation (deg)")
        a1.legend(fontsize=8)
        a2.plot(c["t_s"], np.degrees(c["data"] - c["fitted"]), ".", ms=2, color="tab:red")
        a2.set(xlabel="time (s)", ylabel="residual (deg)")
    else:
        c = fit.extra["curves"]
        used = c["used"]
        # the units whose motion the fit changed most (where the data say most about the
        # material; the units next to the input merely follow it)
        moved = np.abs(c["fitted"][..., :2] - c["start"][..., :2])
        amp = np.max(np.where(used[..., None], moved, 0), axis=(0, 2))
        units = np.argsort(amp)[-4:][::-1]
        fig, axes = plt.subplots(len(units), 1, figsize=(8, 2.0 * len(units)), sharex=True,
                                 squeeze=False)
        for ax, b in zip(axes[:, 0], units):
            for d, col in ((0, "tab:blue"), (1, "tab:green")):
                ax.plot(c["t_s"], c["data"][:, b, d] * 1e3, ".", ms=2, color=col)
                ax.plot(c["t_s"], c["fitted"][:, b, d] * 1e3, "-", lw=0.8, color=col)
                ax.plot(c["t_s"], c["start"][:, b, d] * 1e3, ":", lw=0.8, color=col)
            ax.set_ylabel(f"unit {b}\nu, v (mm)")
        axes[-1, 0].set_xlabel("rig time (s)  [dots: tracked, line: fitted, dotted: start]")
    fig.suptitle("; ".join(f"{n} = {fit.values[n]:.4g} ± {fit.stderr[n]:.2g} {fit.units[n]}"
                           for n in fit.names[:4]), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def calibrate(sources, out: Path, fit=None, kind: str = "auto", material=None,
              poses: str = "auto", calibration=None, workers=None, progress=None) -> dict:
    """Run one calibration and write its outputs; returns the calibration document.

    Raises:
        InputError (or design_engine.calibration.calibrate.CalibrationError): unusable inputs, one line.
    """
    from design_engine.physics.material_file import save_material

    t0 = time.perf_counter()
    mine = Path(out) / "calibration.json"
    if mine.exists():
        try:
            ours = "parameters" in json.loads(mine.read_text())
        except (ValueError, OSError):
            ours = False
        if not ours:
            raise InputError(f"{mine} exists and is not a material calibration (a camera "
                             "calibration?): choose another --out folder")
    found, files = detect_kind([Path(s) for s in sources])
    if kind not in ("auto", found):
        raise InputError(f"--kind {kind} but the inputs look like a {found} test")
    kind = found
    if kind == "hinge":
        result, extra = calibrate_hinge(files, fit, material, progress)
    elif kind == "oscillation":
        result, extra = calibrate_oscillation(files, fit, material, progress)
    else:
        result, extra = calibrate_pulse(files, fit, material, poses, calibration, workers,
                                        progress)
    out.mkdir(parents=True, exist_ok=True)
    doc = calibration_document(result, kind, files, extra)
    doc["wall_s_total"] = time.perf_counter() - t0
    vals, errs = material_values(result)
    save_material(out / "material.toml", vals, errs,
                  f"metarig calibrate ({kind}): {doc['source']}")
    plot(result, kind, out / "calibration.png")
    (out / "calibration.json").write_text(json.dumps(doc, indent=2) + "\n")
    return doc


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="metarig calibrate", description=calibrate_main.__doc__)
    p.add_argument("source", nargs="+", help="run folder / .mcap (pulse), tracks .npz "
                   "(free oscillation) or hinge-test files / a folder of them")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--fit", default=None, help="comma-separated parameters to fit (hinge: "
                   "k_stretch,k_shear,k_bend; oscillation: damping_ratio,k_bend; pulse: "
                   "k_stretch,k_shear,k_bend,damping_ratio by default, or damping_u and "
                   "damping_theta separately)")
    p.add_argument("--kind", choices=KINDS, default="auto", help="test kind (auto-detected)")
    p.add_argument("--material", type=text("--material"), default=None,
                   help="start material file (default: the default material)")
    p.add_argument("--poses", default="auto", choices=("auto", "dic", "track", "truth"),
                   help="pulse: which poses to fit (as `metarig compare --poses`)")
    p.add_argument("--calibration", type=text("--calibration"), default=None,
                   help="pulse: camera calibration for tracking")
    p.add_argument("--workers", type=positive(int), default=None,
                   help="pulse: tracker processes")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def calibrate_main(argv: list[str] | None = None) -> int:
    """Fit material constants (stiffnesses, damping) to a recorded test, with standard errors."""
    from design_engine.calibration.fit import CalibrationError
    from design_engine.physics.material_file import MaterialFileError

    args = build_parser().parse_args(argv)
    fit = None if args.fit is None else [s.strip() for s in args.fit.split(",") if s.strip()]
    progress = Progress(not args.quiet)
    try:
        if fit == []:
            raise InputError(f"--fit names no parameter ({args.fit!r}); leave it out for the "
                             "default set")
        doc = calibrate(args.source, args.out, fit, args.kind, args.material, args.poses,
                        args.calibration, args.workers, progress)
    except KeyboardInterrupt:
        progress.close()
        print("metarig calibrate: interrupted; nothing written", file=sys.stderr)
        return 130
    except (InputError, CalibrationError, MaterialFileError) as exc:
        progress.close()
        print(f"metarig calibrate: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    progress.close()
    for n, p in doc["parameters"].items():
        print(f"{n:<14} {p['value']:.6g} ± {p['stderr']:.3g} {p['unit']}"
              + ("  (not determined by these data)" if n in doc["undetermined"] else ""))
    print(f"residual rms {doc['residual']:.4g} {doc['residual_unit']} over {doc['n_residuals']} "
          f"points; wrote {args.out}/calibration.json, material.toml, calibration.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(calibrate_main())
