"""Open the real devices a lab file names (`devices.lab`), and make sure they are the ones it
names: a function generator's *IDN? model and serial, the Zaber stages' device id, a camera's
model. A device that is not the one named is closed again and refused in one line
(`DeviceError`, or `ValueError` from a camera driver).

The "sim" entries are not opened here: the simulated devices live in `hardware_sim`, which
this package does not import; the ROS nodes resolve them. Vendor packages are imported only
when their device is opened.
"""

from devices.lab import CameraSection, ShakerSection, StageSection
from devices.limits import DeviceError


def _real(section, kind: str) -> None:
    if section.driver == "sim":
        raise ValueError(f"the {kind} is simulated (driver = 'sim'): nothing to open here")


# -- the shaker ---------------------------------------------------------------------------------
def shaker_mismatch(section: ShakerSection, drive) -> str:
    """Why an open function generator is not the one `section` names ("" if it is)."""
    wrong = []
    if section.model and drive.model != section.model:
        wrong.append(f"model {drive.model!r}, not {section.model!r}")
    if section.serial and drive.serial != section.serial:
        wrong.append(f"serial {drive.serial!r}, not {section.serial!r}")
    return f"{section.address} is {drive.identity}: {', '.join(wrong)}" if wrong else ""


def open_shaker(section: ShakerSection, check_identity: bool = True):
    """The shaker drive of a [shaker] section ("keysight33500b"), open and checked."""
    _real(section, "shaker")
    from devices.shaker.funcgen import FunctionGeneratorShaker, InstrumentError

    try:
        drive = FunctionGeneratorShaker(section.address, section.limits,
                                        visa_library=section.visa_library)
    except (ValueError, OSError) as e:   # pyvisa: no VISA library, a bad backend or YAML
        library = section.visa_library or "the default VISA library"
        raise InstrumentError(f"cannot use {library} for {section.address}: "
                              f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") \
            from None
    if check_identity:
        why = shaker_mismatch(section, drive)
        if why:
            drive.close()
            raise InstrumentError(why)
    return drive


# -- the stages ---------------------------------------------------------------------------------
def stage_mismatch(section: StageSection, ids: tuple[str, str]) -> str:
    """Why stages answering `get deviceid` with `ids` (bottom, top) are not the ones
    `section` names ("" if they are, or if the section names no device id)."""
    if not section.device_id:
        return ""
    wrong = [f"{which} stage reports device id {got}" for which, got in zip(("bottom", "top"), ids)
             if got.strip() != str(section.device_id)]
    return (f"stages on {section.port}: {' and '.join(wrong)}, the lab file names "
            f"{section.device_id}") if wrong else ""


def open_stages(section: StageSection, check_identity: bool = True):
    """The stage pair of a [stage] section ("zaber"), open (the speed set, nothing moved) and
    checked."""
    _real(section, "stage")
    from devices.stage.zaber import StageControllerError, ZaberStages

    stages = ZaberStages(section.port, section.limits)
    if check_identity and section.device_id:
        try:
            why = stage_mismatch(section, stages.get("deviceid"))
        except StageControllerError:
            stages.close()
            raise
        if why:
            stages.close()
            raise StageControllerError(why)
    return stages


# -- the camera ---------------------------------------------------------------------------------
def camera_mismatch(section: CameraSection, camera) -> str:
    """Why an open camera is not the one `section` names ("" if it is): its identity (vendor,
    model, serial) must contain the section's model."""
    if section.model and section.model not in camera.identity:
        return f"the camera is {camera.identity}, not a {section.model}"
    return ""


def open_camera(section: CameraSection, check_identity: bool = True):
    """The camera of a [camera] section ("pylon" or "genicam"), open and checked (not yet
    configured: `camera.configure(section.settings)` does that, against the limits)."""
    _real(section, "camera")
    serial = section.serial or None
    if section.driver == "pylon":
        from devices.camera.pylon import PylonCamera

        camera = PylonCamera(serial=serial, index=section.index, limits=section.limits,
                             buffers=section.buffers)
    else:
        from devices.camera.genicam import GenICamCamera

        camera = GenICamCamera(section.cti, serial=serial, index=section.index,
                               limits=section.limits, buffers=section.buffers)
    camera.open()
    if check_identity:
        why = camera_mismatch(section, camera)
        if why:
            camera.close()
            raise ValueError(why)
    return camera


__all__ = ["DeviceError", "camera_mismatch", "open_camera", "open_shaker", "open_stages",
           "shaker_mismatch", "stage_mismatch"]
