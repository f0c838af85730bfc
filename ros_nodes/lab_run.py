"""What `metarig rig --hardware lab` settles before any node starts (pure: no rclpy).

The experiment sequence is the simulated rig's (`logic.experiment`), run on the devices of a
lab file on the system clock. Before a node starts, and so before anything can move:
- `lab_for_rig`: the lab file, read and checked (`devices.lab`), naming a real camera (the
  simulated camera renders the simulated specimen on simulated time only);
- `check_plan`: the plan against the lab file's limits, the port checks the nodes make again
  (strain, the pulse, its volts at the drive calibration, the camera's frame rate), one line;
- `apply_ros`: the file's [ros] section into this process's environment, which every rclpy
  context reads at its start and the node processes inherit;
- `preflight`: `devices.labcheck` on every device (it opens, is the one named, its limits fit,
  a test frame, a dry-run waveform; nothing moves);
- `nominal_design_json`: the sample as designed, which the sequencer publishes on
  `/rig/design` (on the simulated rig the camera publishes it).
Each raises `LabRunError` (one line) or returns what failed. A node started on its own on a
lab file applies the file's [ros] too (`lab_file_in_ros_args`, from `nodes._common.run_node`).
"""

import dataclasses
import os
from pathlib import Path

from devices.lab import Lab, RosSection, read_lab, ros_environment
from devices.limits import LimitError
from ros_nodes.logic.sequence import SIM_ONLY, ExperimentPlan


class LabRunError(ValueError):
    """A lab run that cannot start; the message is one line."""


def refuse_sim_flags(given: set[str], flag_of) -> None:
    """Flags of the simulated rig only (`SIM_ONLY`, by plan field) given for a lab run.

    flag_of: plan field -> its command-line flag, for the message."""
    sim = sorted(flag_of(n) for n in given if n.split(".")[0] in SIM_ONLY)
    if sim:
        raise LabRunError(f"{', '.join(sim)}: only for the simulated rig (--hardware sim); on "
                          "lab devices the camera's settings are the lab file's [camera]")


def lab_for_rig(path: Path) -> Lab:
    """The lab file at `path` (`LabFileError`, one line), with a real camera."""
    lab = read_lab(path)
    if lab.camera.driver == "sim":
        raise LabRunError(f"{path}: [camera] driver 'sim': the simulated camera films the "
                          "simulated specimen on simulated time only (metarig rig --hardware "
                          "sim); name the lab's camera (driver 'pylon' or 'genicam')")
    return lab


def check_plan(plan: ExperimentPlan, lab: Lab, frame_rate_hz: float) -> None:
    """The plan's requests against the lab file's limits, before any node starts.

    frame_rate_hz: the camera rate asked for (0: the lab file's)."""
    from devices.camera.port import check_settings
    from devices.shaker.port import prepare
    from devices.shaker.waveform import WaveformRequest
    from devices.stage.port import check_strain

    try:
        check_strain(lab.stage.limits, plan.strain)
    except LimitError as e:
        raise LabRunError(f"{lab.path}: [stage]: {e}") from None
    try:
        wf = prepare(lab.shaker.limits,
                     WaveformRequest(plan.waveform, amplitude_m=plan.amplitude_m,
                                     frequency_hz=plan.frequency_hz, cycles=plan.cycles),
                     plan.pre_trigger_s)
        if lab.shaker.driver == "keysight33500b":
            from devices.shaker.funcgen import arb_upload

            arb_upload(lab.shaker.limits, wf)
    except LimitError as e:
        raise LabRunError(f"{lab.path}: [shaker]: {e}") from None
    if plan.compensate and lab.shaker.driver != "sim":
        raise LabRunError(f"{lab.path}: [shaker]: --compensate needs the shaker's measured "
                          f"motion, and the '{lab.shaker.driver}' drive measures nothing (its "
                          "readings are its command); run without --compensate")
    settings = lab.camera.settings
    if frame_rate_hz > 0:
        settings = dataclasses.replace(settings, frame_rate_hz=frame_rate_hz)
    try:
        check_settings(settings, lab.camera.limits)
    except ValueError as e:
        raise LabRunError(f"{lab.path}: [camera]: {e}") from None


ROS_VARIABLES = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS")


def apply_ros(ros: RosSection) -> dict[str, str]:
    """Put this process (and the processes it starts) where the lab file's [ros] says: its
    domain, discovery range and static peers replace the environment's (no peers in the
    file: none from the environment either). A file without [ros] keeps the environment's,
    with discovery on this machine unless the environment opens it. Call before any rclpy
    context starts. Returns the ROS variables in force."""
    if ros.given:
        for name in ROS_VARIABLES:
            os.environ.pop(name, None)
        os.environ.update(ros_environment(ros))
    elif not os.environ.get(ROS_VARIABLES[1]):
        os.environ[ROS_VARIABLES[1]] = "LOCALHOST"
    return {name: os.environ[name] for name in ROS_VARIABLES if os.environ.get(name)}


def preflight(lab: Lab, report) -> list[str]:
    """`devices.labcheck.check_lab` on the lab's devices; `report(line)` gets every check as
    `metarig devices --lab` prints it. Returns the failed checks, one line each."""
    from devices.labcheck import check_lab

    failed = []
    for c in check_lab(lab):
        line = f"{c.device} {c.what}: {c.detail}"
        report(f"{'ok' if c.ok else 'FAILED':<7}{line}")
        if not c.ok:
            failed.append(line)
    return failed


def nominal_design_json(plan: ExperimentPlan) -> str:
    """The sample as designed (scene, lattice or design file, material file): the design file
    the simulated camera would publish, without the simulated specimen's imperfections."""
    from hardware_sim.specimen import NOMINAL, SpecimenConfig, build

    return build(SpecimenConfig(scene=plan.scene, nx=plan.nx, ny=plan.ny,
                                design_path=plan.design, material_path=plan.material,
                                material_si=plan.material_si,
                                imperfections=NOMINAL)).design_json()


def lab_file_in_ros_args(argv: list[str]) -> str | None:
    """The lab file a node is started on: `hardware` "lab" and `lab_file` given as ROS
    arguments (`-p name:=value`, `--param`, or in a `--params-file`, whose node entries are all
    read; `-p` wins), or None."""
    files, given = [], {}
    args = iter(argv)
    for a in args:
        if a in ("-p", "--param"):
            key, _, value = next(args, "").partition(":=")
            given[key] = value
        elif a == "--params-file":
            files.append(next(args, ""))
    values = {}
    for f in files:
        values.update(_lab_params_in_file(f))
    values.update(given)
    if values.get("hardware") == "lab" and values.get("lab_file"):
        return str(values["lab_file"])
    return None


def _lab_params_in_file(path: str) -> dict:
    """`hardware` and `lab_file` of any node entry of a ROS 2 parameter file ({} if none or
    unreadable: the node reports a bad file itself)."""
    import yaml

    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return {}
    out = {}
    for entry in (doc.values() if isinstance(doc, dict) else ()):
        params = entry.get("ros__parameters") if isinstance(entry, dict) else None
        if isinstance(params, dict):
            out.update({k: params[k] for k in ("hardware", "lab_file") if k in params})
    return out
