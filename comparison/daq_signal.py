"""A measured input signal from a data-acquisition file: one channel of a CSV table or of a
LabVIEW TDMS file, as times (s) and displacements (m).

Only the samples inside a requested time window are kept, and files are read a line (CSV) or
a slice (TDMS) at a time, so a long high-rate record never has to fit in memory. Units come
from the caller (`unit`) or from the file (a CSV column header `name (mm)` / `name [mm]`, a TDMS
channel's `unit_string` property); where both are given they must agree. Times: a CSV time
column (`time_column`, default the first column) or a TDMS waveform's `wf_start_offset` +
k `wf_increment` (or a time channel of the same file).
"""

import csv
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}
TDMS_SLICE = 1 << 20  # samples read from a TDMS channel at a time


class SignalError(ValueError):
    """A signal file or channel that cannot be used (one line naming it)."""


@dataclass(frozen=True)
class DaqSignal:
    """One measured channel.

    Attributes:
        t_s: [n] sample times on the file's own time axis, s, increasing.
        u_m: [n] displacement, m.
        source: `FILE:CHANNEL`.
        unit: the unit the file's values were in.
    """

    t_s: np.ndarray
    u_m: np.ndarray
    source: str
    unit: str


def _scale(unit: str, table: dict[str, float], what: str, where: str) -> float:
    key = unit.strip()
    if key not in table:
        raise SignalError(f"{where}: unknown {what} unit {unit!r} (one of: {', '.join(table)})")
    return table[key]


def _unit_of(given: str | None, in_file: str | None, where: str) -> str:
    if given and in_file and _scale(given, LENGTH_UNITS, "length", where) != \
            _scale(in_file, LENGTH_UNITS, "length", where):
        raise SignalError(f"{where}: the file says the values are in {in_file}, --signal-unit "
                          f"says {given}")
    unit = given or in_file
    if not unit:
        raise SignalError(f"{where}: the file gives no unit: say it with --signal-unit "
                          f"({', '.join(LENGTH_UNITS)})")
    _scale(unit, LENGTH_UNITS, "length", where)
    return unit


def read_signal(path: str | Path, channel: str | None = None, unit: str | None = None,
                time_column: str | None = None, time_unit: str = "s",
                window_s: tuple[float, float] = (-math.inf, math.inf)) -> DaqSignal:
    """The samples of one channel of a `.csv` or `.tdms` file within `window_s` (file time, s).

    Args:
        channel: CSV column name, or TDMS `Group/Channel` (default: a CSV's second column
            when it has two, a TDMS file's only channel).
        unit: unit of the values (one of `LENGTH_UNITS`); default from the file.
        time_column: CSV time column name (default the first) or TDMS time channel
            (`Group/Channel`; default the waveform timing of the channel).
        time_unit: unit of the time column (one of `TIME_UNITS`).

    Raises:
        SignalError: missing file, unknown channel or unit, no timing, non-numbers, samples
            out of order, fewer than two samples in the window.
    """
    p = Path(path)
    if not p.is_file():
        raise SignalError(f"{p}: no such signal file")
    suffix = p.suffix.lower()
    if suffix == ".csv":
        sig = _read_csv(p, channel, unit, time_column, time_unit, window_s)
    elif suffix == ".tdms":
        sig = _read_tdms(p, channel, unit, time_column, time_unit, window_s)
    else:
        raise SignalError(f"{p}: not a .csv or .tdms signal file")
    if sig.t_s.size >= 2 and np.any(np.diff(sig.t_s) <= 0):
        raise SignalError(f"{sig.source}: sample times do not increase")
    if sig.t_s.size < 2:
        raise SignalError(f"{sig.source}: {sig.t_s.size} samples between {window_s[0]:.6g} s "
                          f"and {window_s[1]:.6g} s of the file's time, where the frames are "
                          "(check --signal-trigger and the time unit)")
    return sig


_UNIT_IN_HEADER = re.compile(r"^\s*(.*?)\s*[\(\[]\s*([^\)\]]+?)\s*[\)\]]\s*$")


def _header_name(text: str) -> tuple[str, str | None]:
    """`x (mm)` / `x [mm]` -> ("x", "mm"); `x` -> ("x", None)."""
    m = _UNIT_IN_HEADER.match(text)
    return (m.group(1), m.group(2)) if m else (text.strip(), None)


def _read_csv(p: Path, channel, unit, time_column, time_unit, window) -> DaqSignal:
    with open(p, newline="", encoding="utf-8-sig", errors="replace") as f:
        sample = f.read(4096)
        f.seek(0)
        try:
            dialect = csv.Sniffer().sniff(sample, delimiters=",;\t")
        except csv.Error:
            dialect = csv.excel
        rows = csv.reader(f, dialect)
        header = next(rows, None)
        if not header or len(header) < 2:
            raise SignalError(f"{p}: no header row with a time and a value column")
        names = [_header_name(h) for h in header]
        plain = [n for n, _ in names]
        ti = _column(p, plain, header, time_column, 0, "time")
        if channel is None and len(header) != 2:
            raise SignalError(f"{p}: choose the value column with --channel (columns: "
                              f"{', '.join(header)})")
        vi = _column(p, plain, header, channel, 1, "value")
        where = f"{p}:{header[vi]}"
        unit = _unit_of(unit, names[vi][1], where)
        t_unit = time_unit if time_column is not None or not names[ti][1] else names[ti][1]
        ts = _scale(t_unit, TIME_UNITS, "time", f"{p}:{header[ti]}")
        t, u = [], []
        for line, row in enumerate(rows, start=2):
            if not row or not "".join(row).strip():
                continue
            try:
                tv, uv = float(row[ti]) * ts, float(row[vi])
            except (ValueError, IndexError):
                raise SignalError(f"{p}: line {line} is not numbers in columns {header[ti]} "
                                  f"and {header[vi]}: {','.join(row)[:60]!r}") from None
            if window[0] <= tv <= window[1]:
                t.append(tv)
                u.append(uv)
            elif tv > window[1]:
                break
    scale = _scale(unit, LENGTH_UNITS, "length", where)
    return DaqSignal(np.asarray(t, np.float64), np.asarray(u, np.float64) * scale, where, unit)


def _column(p: Path, plain: list[str], header: list[str], name, default: int, what: str) -> int:
    if name is None:
        return default
    for i, (h, n) in enumerate(zip(header, plain)):
        if name in (h, n):
            return i
    raise SignalError(f"{p}: no {what} column {name!r} (columns: {', '.join(header)})")


def _tdms_channel(p: Path, tdms, name: str | None, what: str):
    channels = [(g.name, c.name, c) for g in tdms.groups() for c in g.channels()]
    listing = ", ".join(f"{g}/{c}" for g, c, _ in channels) or "none"
    if name is None:
        if len(channels) != 1:
            raise SignalError(f"{p}: choose the {what} channel with --channel GROUP/CHANNEL "
                              f"(channels: {listing})")
        return channels[0][2]
    for g, c, ch in channels:
        if name == f"{g}/{c}" or (name == c and sum(cc == c for _, cc, _ in channels) == 1):
            return ch
    raise SignalError(f"{p}: no channel {name!r} (channels: {listing})")


def _read_tdms(p: Path, channel, unit, time_channel, time_unit, window) -> DaqSignal:
    from nptdms import TdmsFile

    try:
        with TdmsFile.open(p) as tdms:
            ch = _tdms_channel(p, tdms, channel, "signal")
            where = f"{p}:{ch.group_name}/{ch.name}"
            unit = _unit_of(unit, str(ch.properties.get("unit_string", "")).strip() or None,
                            where)
            n = len(ch)
            if time_channel is not None:
                tch = _tdms_channel(p, tdms, time_channel, "time")
                ts = _scale(str(tch.properties.get("unit_string", "")).strip() or time_unit,
                            TIME_UNITS, "time", f"{p}:{tch.group_name}/{tch.name}")
                if len(tch) != n:
                    raise SignalError(f"{where}: {n} samples, its time channel {tch.name} "
                                      f"{len(tch)}")
                t_parts, u_parts = [], []
                for k in range(0, n, TDMS_SLICE):
                    m = min(TDMS_SLICE, n - k)
                    t = np.asarray(tch.read_data(k, m), np.float64) * ts
                    keep = (t >= window[0]) & (t <= window[1])
                    if keep.any():
                        t_parts.append(t[keep])
                        u_parts.append(np.asarray(ch.read_data(k, m), np.float64)[keep])
                t = np.concatenate(t_parts) if t_parts else np.zeros(0)
                u = np.concatenate(u_parts) if u_parts else np.zeros(0)
            else:
                dt = ch.properties.get("wf_increment")
                if not dt or not float(dt) > 0:
                    raise SignalError(f"{where}: no waveform timing (wf_increment): name the "
                                      "time channel with --time-channel")
                t0, dt = float(ch.properties.get("wf_start_offset", 0.0)), float(dt)
                lo = max(0, math.ceil((window[0] - t0) / dt - 1e-9)) if math.isfinite(
                    window[0]) else 0
                hi = min(n, math.floor((window[1] - t0) / dt + 1e-9) + 1) if math.isfinite(
                    window[1]) else n
                lo = min(lo, n)
                hi = max(hi, lo)
                u = np.concatenate([np.asarray(ch.read_data(k, min(TDMS_SLICE, hi - k)),
                                               np.float64) for k in range(lo, hi, TDMS_SLICE)]
                                   ) if hi > lo else np.zeros(0)
                t = t0 + dt * np.arange(lo, hi, dtype=np.float64)
    except SignalError:
        raise
    except Exception as exc:  # noqa: BLE001 - nptdms raises assorted types on a bad file
        raise SignalError(f"{p}: not a readable TDMS file ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    scale = _scale(unit, LENGTH_UNITS, "length", where)
    return DaqSignal(t, u * scale, where, unit)
