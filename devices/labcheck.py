"""Check a lab file against the devices that are there, without moving anything.

For each real device of the file: it opens, it is the one named (identity), the file's limits
are within what the device reports where it can say, and a first use that moves nothing works:
- shaker (function generator): *IDN? model and serial; the instrument's own voltage limit
  (`VOLT:LIM`) read back as max_volts; a dry-run waveform, the largest pulse the limits accept,
  turned into the volts it would need (checked against max_volts) and not played;
- stages (Zaber): both axes answer (their speed is set, no move is sent); `get deviceid`; the
  closings of min_strain and max_strain lie within each axis's travel (`limit.min`/`limit.max`);
- camera (pylon, GenICam): serial and model; the settings applied within the device's own
  ranges; one test frame grabbed (not with a hardware trigger: nothing fires it here).
Each check is one `Check` (ok, or failed with why); a device that does not open skips its
other checks.
"""

import math
from dataclasses import dataclass

import numpy as np

from devices.lab import Lab, ShakerSection, StageSection
from devices.limits import DeviceError, LimitError
from devices.shaker.port import prepare
from devices.shaker.waveform import ShakerLimits, WaveformRequest


@dataclass(frozen=True, slots=True)
class Check:
    """One line of the report: `device` ("shaker", "stage", "camera", "ros"), what was checked,
    whether it passed, and what was seen (or why it failed)."""

    device: str
    what: str
    ok: bool
    detail: str


def _why(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def dry_run_request(limits: ShakerLimits) -> WaveformRequest:
    """The largest pulse the limits accept: A = max_amplitude_m at 30 Hz, or at the frequency
    the velocity limit allows (pi A f <= max_velocity_m_s), within the frequency range."""
    a = limits.max_amplitude_m
    f = min(max(30.0, limits.min_frequency_hz), limits.max_frequency_hz)
    if a > 0:
        f = min(f, limits.max_velocity_m_s / (math.pi * a) * (1 - 1e-9))
    return WaveformRequest("pulse", amplitude_m=a, frequency_hz=f)


def _shaker(s: ShakerSection) -> list[Check]:
    from devices.connect import open_shaker, shaker_mismatch
    from devices.shaker.funcgen import arb_upload

    out = []
    try:
        drive = open_shaker(s, check_identity=False)
    except (DeviceError, ValueError, OSError) as e:
        return [Check("shaker", "opens", False, _why(e))]
    try:
        out.append(Check("shaker", "opens", True, f"{drive.identity} at {s.address}"))
        why = shaker_mismatch(s, drive)
        named = " ".join(x for x in (s.model and f"model {s.model}",
                                     s.serial and f"serial {s.serial}") if x)
        out.append(Check("shaker", "identity", not why, why or (
            f"{named} as the lab file says" if named else
            "a 33500B series generator (the lab file names no model or serial)")))
        try:
            hi, lo = (float(drive.query(q)) for q in ("VOLT:LIM:HIGH?", "VOLT:LIM:LOW?"))
            on = drive.query("VOLT:LIM:STAT?").strip() in ("1", "ON")
            good = on and math.isclose(hi, s.limits.max_volts, rel_tol=1e-6) and \
                math.isclose(lo, -s.limits.max_volts, rel_tol=1e-6)
            out.append(Check("shaker", "voltage limit", good,
                             f"the generator limits its output to {lo:g}..{hi:g} V "
                             f"({'on' if on else 'OFF'}); max_volts = {s.limits.max_volts:g} V"))
        except (DeviceError, ValueError) as e:
            out.append(Check("shaker", "voltage limit", False, _why(e)))
        req = dry_run_request(s.limits)
        try:
            wf = prepare(s.limits, req)
            up = arb_upload(s.limits, wf)
            out.append(Check("shaker", "dry-run waveform", True,
                             f"pulse A = {wf.amplitude_m:g} m, f = {wf.frequency_hz:.4g} Hz: "
                             f"{up.peak_v:.4g} V peak (max_volts {s.limits.max_volts:g} V), "
                             f"{up.values.size} points at {up.sample_rate_hz:.4g} Sa/s; "
                             "built, not played"))
        except LimitError as e:
            out.append(Check("shaker", "dry-run waveform", False,
                             f"the largest pulse the limits accept cannot be played: {_why(e)}"))
    finally:
        drive.close()
    return out


def _axis_steps(cfg, closing_m: float) -> tuple[int, int]:
    """Microstep positions of (bottom, top) at a closing (m), as the Zaber driver moves them."""
    half = round(0.5 * closing_m / cfg.microstep_m)
    return (cfg.bottom_zero_steps + cfg.bottom_direction * half,
            cfg.top_zero_steps + cfg.top_direction * half)


def _stage(s: StageSection) -> list[Check]:
    from devices.connect import open_stages, stage_mismatch

    try:
        stages = open_stages(s, check_identity=False)
    except (DeviceError, ValueError, OSError) as e:
        return [Check("stage", "opens", False, _why(e))]
    out = []
    cfg = s.limits
    try:
        strain = stages.closing_m / cfg.sample_height_m
        out.append(Check("stage", "opens", True,
                         f"both axes answer on {s.port}; closing now {stages.closing_m:.6g} m "
                         f"(strain {strain:.4g}); nothing moved"))
        try:
            ids = stages.get("deviceid")
            why = stage_mismatch(s, ids)
            out.append(Check("stage", "identity", not why, why or (
                f"device ids {ids[0]}, {ids[1]}" + ("" if s.device_id else
                                                    " (the lab file names no device_id)"))))
        except DeviceError as e:
            out.append(Check("stage", "identity", False, _why(e)))
        try:
            lo, hi = stages.get("limit.min"), stages.get("limit.max")
            ends = {name: _axis_steps(cfg, strain_ * cfg.sample_height_m)
                    for name, strain_ in (("min_strain", cfg.min_strain),
                                          ("max_strain", cfg.max_strain))}
            wrong = []
            for i, which in enumerate(("bottom", "top")):
                travel = (int(lo[i]), int(hi[i]))
                for name, steps in ends.items():
                    if not travel[0] <= steps[i] <= travel[1]:
                        wrong.append(f"{name} puts the {which} stage at {steps[i]} microsteps, "
                                     f"outside its travel {travel[0]}..{travel[1]}")
            out.append(Check("stage", "travel", not wrong, "; ".join(wrong) or (
                f"strain {cfg.min_strain:g}..{cfg.max_strain:g} is within both axes' travel "
                f"(bottom {lo[0]}..{hi[0]}, top {lo[1]}..{hi[1]} microsteps)")))
        except (DeviceError, ValueError) as e:
            out.append(Check("stage", "travel", False, _why(e)))
    finally:
        stages.close()
    return out


def _camera(lab: Lab) -> list[Check]:
    from devices.connect import camera_mismatch, open_camera

    s = lab.camera
    try:
        camera = open_camera(s, check_identity=False)
    except Exception as e:  # a vendor SDK's own errors (no camera, a producer that fails)
        return [Check("camera", "opens", False, _why(e))]
    out = [Check("camera", "opens", True, camera.identity)]
    try:
        why = camera_mismatch(s, camera)
        out.append(Check("camera", "identity", not why, why or (
            f"a {s.model}" if s.model else "(the lab file names no model)")))
        try:
            got = camera.configure(s.settings)
        except Exception as e:
            out.append(Check("camera", "settings", False, _why(e)))
            return out
        exposure = "as it is" if got.exposure_s is None else f"{got.exposure_s:g} s"
        out.append(Check("camera", "settings", True,
                         f"{got.frame_rate_hz:g} Hz, exposure {exposure}, roi {got.roi}, "
                         f"{got.pixel_format} ({camera.device_pixel_format}), "
                         f"trigger {got.trigger}"))
        if got.trigger == "hardware":
            out.append(Check("camera", "test frame", True,
                             f"not grabbed: a hardware trigger on {got.hardware_line} "
                             "(nothing fires it during a check)"))
            return out
        try:
            camera.start()
            if got.trigger == "software":
                camera.trigger()
            timeout = max(2.0, 5.0 / got.frame_rate_hz)
            frame = camera.grab(timeout)
        except Exception as e:
            out.append(Check("camera", "test frame", False, _why(e)))
            return out
        if frame is None:
            out.append(Check("camera", "test frame", False, f"no frame within {timeout:g} s"))
        else:
            h, w = frame.image.shape[:2]
            out.append(Check("camera", "test frame", True,
                             f"{w}x{h} {frame.image.dtype}, frame counter {frame.counter}, "
                             f"mean level {float(np.mean(frame.image)):.1f}"))
    finally:
        camera.close()
    return out


def check_lab(lab: Lab) -> list[Check]:
    """Every check of a lab file against the devices that are there (see the module
    docstring); the simulated devices are one line each."""
    out = []
    for device, section, run in (("shaker", lab.shaker, lambda: _shaker(lab.shaker)),
                                 ("stage", lab.stage, lambda: _stage(lab.stage)),
                                 ("camera", lab.camera, lambda: _camera(lab))):
        if section.driver == "sim":
            out.append(Check(device, "driver", True, "simulated (driver = 'sim'): nothing to open"))
        else:
            out += run()
    r = lab.ros
    if not r.given:
        out.append(Check("ros", "discovery", True, "no [ros] section: the environment's domain "
                         "and discovery range (this machine only unless it opens them)"))
        return out
    reach = {"localhost": "this machine only", "subnet": "the whole subnet: any participant "
             "on this domain may call the rig's services", "off": "no automatic discovery"}
    out.append(Check("ros", "discovery", True,
                     f"domain {r.domain_id}, discovery {r.discovery} ({reach[r.discovery]})"
                     + (f", static peers {', '.join(r.static_peers)}" if r.static_peers else "")))
    return out
