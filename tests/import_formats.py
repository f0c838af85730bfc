"""A recorded experiment written out in a lab's file formats, for the `metarig import` tests
(helper, not a test).

`export_run` takes a run folder apart (frames, frame stamps, shaker record); the writers put
the frames into a PNG folder, a Photron MRAW with its CIH (`pyMRAW.save_mraw`) or CIHX, an
ImageJ TIFF stack (`tifffile`), and the signal into a CSV table or a TDMS file (`nptdms`). The
trigger is the run's rig-clock zero, so the frames' trigger offset is the first frame's stamp.
"""

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

GROUP, CHANNEL = "Drive", "Shaker"


@dataclass(frozen=True)
class Experiment:
    """A run folder's content: frames [n, h, w] uint8, stamps [n] s, shaker (t s, u m) on a
    regular grid of `dt_s`, fps, and the folder."""

    run: Path
    frames: np.ndarray
    frame_t_s: np.ndarray
    signal_t_s: np.ndarray
    signal_u_m: np.ndarray
    fps: float

    @property
    def start_frame(self) -> int:
        """The first frame's number after the trigger (rig time 0)."""
        return int(round(self.frame_t_s[0] * self.fps))


def export_run(run: Path, dt_s: float = 5e-4) -> Experiment:
    """The frames and the shaker record of a run folder, the record resampled to `dt_s` (a
    TDMS waveform is regularly sampled; every route gets the same samples)."""
    from ros_nodes.logic.recording import read_recording
    from tracking.frame_sources import mcap_frames

    rec = read_recording(run)
    frames = np.stack([f for _t, f in mcap_frames(rec.path, "/camera/image_raw")])
    k0 = int(np.ceil(rec.shaker_t_s[0] / dt_s))
    t = dt_s * np.arange(k0, int(rec.shaker_t_s[-1] / dt_s) + 1)
    u = np.interp(t, rec.shaker_t_s, rec.shaker_u_m)
    fps = 1.0 / float(np.median(np.diff(rec.frame_t_s)))
    return Experiment(run, frames, rec.frame_t_s, t, u, round(fps, 6))


def write_png(frames: np.ndarray, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for k, f in enumerate(frames):
        assert cv2.imwrite(str(folder / f"frame{k:05d}.png"), f)
    return folder


def write_mraw(frames: np.ndarray, path: Path, fps: float, start_frame: int,
               bits: int = 8) -> Path:
    """MRAW + CIH (pyMRAW's writer); returns the .cih path."""
    import pyMRAW

    _mraw, cih = pyMRAW.save_mraw(frames, str(path), bit_depth=bits, info_dict={
        "Record Rate(fps)": f"{fps:g}", "Start Frame": str(start_frame)})
    return Path(cih)


def write_cihx(path: Path, n: int, width: int, height: int, bits: int, fps: float,
               start_frame: int) -> Path:
    """A Photron CIHX header (XML) with the fields `pyMRAW.get_cih` and the importer read."""
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8" standalone="yes" ?>\n<cih>\n'
        "<fileInfo><date>2025/01/01</date></fileInfo>\n"
        "<deviceInfo><deviceName>FASTCAM test</deviceName></deviceInfo>\n"
        f"<recordInfo><recordRate>{fps:g}</recordRate><shutterSpeed>{1 / fps:g}</shutterSpeed>"
        "</recordInfo>\n"
        f"<frameInfo><totalFrame>{n}</totalFrame><recordedFrame>{n}</recordedFrame>"
        f"<startFrame>{start_frame}</startFrame></frameInfo>\n"
        f"<imageDataInfo><resolution><width>{width}</width><height>{height}</height>"
        f"</resolution><colorInfo><type>Mono</type><bit>{bits}</bit></colorInfo>"
        f"<effectiveBit><depth>{min(bits, 12)}</depth><side>Lower</side></effectiveBit>"
        "</imageDataInfo>\n<imageFileInfo><fileFormat>MRaw</fileFormat></imageFileInfo>\n"
        "<basicInfo><comment></comment></basicInfo>\n</cih>\n")
    return path


def write_tiff(frames: np.ndarray, path: Path, fps: float) -> Path:
    """An ImageJ TIFF stack whose frame interval gives the rate."""
    import tifffile

    tifffile.imwrite(path, frames, imagej=True, metadata={"axes": "TYX", "finterval": 1 / fps})
    return path


def write_csv(t_s: np.ndarray, u_m: np.ndarray, path: Path) -> Path:
    """Time in ms and displacement in mm, units in the header."""
    with open(path, "w") as f:
        f.write("time (ms),shaker (mm)\n")
        for t, u in zip(t_s, u_m):
            f.write(f"{float(t) * 1e3!r},{float(u) * 1e3!r}\n")
    return path


def write_tdms(t_s: np.ndarray, u_m: np.ndarray, path: Path, unit: str | None = "mm") -> Path:
    """One waveform channel GROUP/CHANNEL (values in mm) with its timing properties."""
    from nptdms import ChannelObject, TdmsWriter

    dt = float(np.median(np.diff(t_s)))
    props = {"wf_increment": dt, "wf_start_offset": float(t_s[0])}
    if unit:
        props["unit_string"] = unit
    with TdmsWriter(str(path)) as w:
        w.write_segment([ChannelObject(GROUP, CHANNEL, u_m * 1e3, properties=props)])
    return path
