"""Rosbag2-compatible MCAP recording of serialized ROS 2 messages, with gap and drop detection.

Pure logic (no rclpy): the recorder node hands over CDR bytes as they arrive. The file uses
profile `ros2`, schema encoding `ros2msg` (rosbag2-style definitions from `msgdefs`), message
encoding `cdr`, small chunks (a killed writer loses at most the chunk being filled: see
`recover`) and integer-nanosecond times. `log_time` is the header stamp for stamped messages
(acquisition time; it keeps frames in capture order when a high-speed camera downloads its
footage after the event) and the receive time otherwise; `publish_time` is always the receive
time.

Loss detection, per topic (reported, never hidden):
- publisher sequence numbers (DDS `publication_sequence_number`): a jump of k > 1 means k - 1
  messages never arrived (exact for a topic with one publisher; the numbers are per publisher
  and a message does not say which publisher sent it, so a topic that has several
  (`several_publishers`, e.g. `/diagnostics`) is not checked by sequence: `sequence_checked`
  false in its report);
- stamp steps: a step longer than `gap_factor` x the median period is a gap of
  round(step / period) - 1 missing samples (catches drops upstream of the publisher too);
- stamps that go backwards are counted.
`dropped` in the report is the transport loss (sequence numbers); `missing_by_stamp` also
counts samples that the publisher skipped or that were lost before it (camera frames).
"""

import json
import logging
import struct
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from ros_nodes.logic import msgdefs
from ros_nodes.logic.cdr import header_stamp_ns

log = logging.getLogger(__name__)
LIBRARY = "metarig recorder"
_COMPRESSION = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4,
                "zstd": CompressionType.ZSTD}


@dataclass
class TopicStats:
    """Counts and loss estimates of one recorded topic."""

    topic: str
    type: str
    count: int = 0
    bytes: int = 0
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    backwards: int = 0
    gaps: int = 0
    missing_by_stamp: int = 0
    missing_by_sequence: int = 0
    queue_overflow: int = 0
    sequence_checked: bool = True
    max_latency_ms: float = 0.0
    _deltas: list = field(default_factory=list, repr=False)
    _last_seq: int | None = field(default=None, repr=False)
    _period: float | None = field(default=None, repr=False)
    _period_n: int = field(default=-1, repr=False)

    def period_ns(self) -> float | None:
        if self._period_n != len(self._deltas):  # cached: the median only changes on append
            d = [x for x in self._deltas if x > 0]
            self._period = float(np.median(d)) if len(d) >= 5 else None
            self._period_n = len(self._deltas)
        return self._period

    def public(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if not k.startswith("_")}
        d["period_s"] = None if self.period_ns() is None else self.period_ns() * 1e-9
        # transport loss (exact, from DDS sequence numbers); stamp gaps are reported apart:
        # they also count samples the publisher itself skipped or lost upstream
        # plus messages the recorder itself refused because its write queue was full
        d["dropped"] = self.missing_by_sequence + self.queue_overflow
        return d


class McapRecorder:
    """Writes serialized messages to an MCAP file; a context manager (closing is idempotent)."""

    def __init__(self, path: str | Path, *, chunk_size: int = 1 << 20, compression: str = "none",
                 gap_factor: float = 1.5, metadata: dict[str, dict[str, str]] | None = None):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {', '.join(_COMPRESSION)}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=_COMPRESSION[compression])
        self._writer.start(profile="ros2", library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._stamped: dict[str, bool] = {}
        self.stats: dict[str, TopicStats] = {}
        self.gap_factor = gap_factor
        self._closed = False
        self._seq = 0
        for name, values in (metadata or {}).items():
            self.add_metadata(name, values)

    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def add_topic(self, topic: str, type_name: str, qos_yaml: str = "") -> None:
        """Register a topic (its schema once per type). `type_name` is `pkg/msg/Type`."""
        if topic in self._channels:
            return
        pkg, name = msgdefs.normalize(type_name)
        full = f"{pkg}/msg/{name}"
        if full not in self._schemas:
            self._schemas[full] = self._writer.register_schema(
                name=full, encoding="ros2msg", data=msgdefs.schema_text(full).encode())
        meta = {"offered_qos_profiles": qos_yaml} if qos_yaml else {}
        self._channels[topic] = self._writer.register_channel(
            topic=topic, message_encoding="cdr", schema_id=self._schemas[full], metadata=meta)
        self._stamped[topic] = msgdefs.has_header(full)
        self.stats[topic] = TopicStats(topic, full)

    def write(self, topic: str, cdr: bytes, receive_ns: int, pub_seq: int | None = None) -> None:
        """Record one serialized message received at `receive_ns` (node clock)."""
        if self._closed:
            return
        st = self.stats[topic]
        stamp = header_stamp_ns(cdr) if self._stamped[topic] else None
        log_ns = stamp if stamp else receive_ns
        self._track(st, stamp, receive_ns, pub_seq)
        self._writer.add_message(channel_id=self._channels[topic], log_time=int(log_ns),
                                 data=cdr, publish_time=int(receive_ns), sequence=self._seq)
        self._seq += 1
        st.count += 1
        st.bytes += len(cdr)

    def several_publishers(self, topic: str) -> None:
        """`topic` has (had) more than one publisher: its sequence numbers say nothing about
        loss (two interleaved counts look like gaps and hide each other's real ones), so the
        count so far is discarded and no more is kept."""
        st = self.stats.get(topic)
        if st is not None:
            st.sequence_checked = False
            st.missing_by_sequence = 0

    def note_overflow(self, topic: str, pub_seq: int | None = None) -> None:
        """Count a message that reached the recorder but was dropped before writing."""
        st = self.stats[topic]
        st.queue_overflow += 1
        if pub_seq is not None and pub_seq > 0:
            self._track(st, None, 0, pub_seq)

    def _track(self, st: TopicStats, stamp: int | None, receive_ns: int, pub_seq) -> None:
        if pub_seq is not None and pub_seq > 0 and st.sequence_checked:
            if st._last_seq is not None and pub_seq > st._last_seq + 1:
                st.missing_by_sequence += pub_seq - st._last_seq - 1
            st._last_seq = pub_seq if st._last_seq is None else max(st._last_seq, pub_seq)
        if stamp is None:
            return
        if stamp and receive_ns >= stamp:
            st.max_latency_ms = max(st.max_latency_ms, (receive_ns - stamp) * 1e-6)
        if st.last_stamp_ns is not None:
            delta = stamp - st.last_stamp_ns
            if delta < 0:
                st.backwards += 1
            else:
                period = st.period_ns()
                if period and delta > self.gap_factor * period:
                    st.gaps += 1
                    st.missing_by_stamp += int(round(delta / period)) - 1
                elif len(st._deltas) < 200:
                    st._deltas.append(delta)
        if st.first_stamp_ns is None:
            st.first_stamp_ns = stamp
        st.last_stamp_ns = stamp if st.last_stamp_ns is None else max(st.last_stamp_ns, stamp)

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        """An MCAP metadata record (string -> string map)."""
        if not self._closed:
            self._writer.add_metadata(name, {str(k): str(v) for k, v in values.items()})

    def add_attachment(self, name: str, data: bytes, media_type: str = "application/json") -> None:
        if not self._closed:
            now = time.time_ns()
            self._writer.add_attachment(create_time=now, log_time=now, name=name,
                                        media_type=media_type, data=data)

    def report(self) -> dict:
        """Per-topic counts and losses, plus totals."""
        topics = {t: s.public() for t, s in self.stats.items()}
        return {"path": str(self.path), "messages": sum(s.count for s in self.stats.values()),
                "dropped": sum(t["dropped"] for t in topics.values()),
                "queue_overflow": sum(t["queue_overflow"] for t in topics.values()),
                "stamp_gaps": sum(t["gaps"] for t in topics.values()),
                "missing_by_stamp": sum(t["missing_by_stamp"] for t in topics.values()),
                "backwards": sum(t["backwards"] for t in topics.values()), "topics": topics}

    def close(self) -> dict:
        """Finish the file (summary, index, footer); returns `report()`. Idempotent."""
        if not self._closed:
            self._closed = True
            rep = self.report()
            self._writer.add_metadata("recording_report", {"json": json.dumps(rep)})
            self._writer.finish()
            self._file.close()
        return self.report()


class QueuedRecorder:
    """A writer thread in front of a `McapRecorder`: `put` never blocks and never loses silently.

    Receive callbacks hand over (topic, bytes, receive ns, sequence) and return at once; the
    thread stamps, tracks and writes. The queue holds at most `max_queue` messages: a message
    that finds it full is counted in its topic's `queue_overflow` (part of `dropped` in the
    report), never dropped unseen. `close()` writes everything queued, then finishes the file.
    Other calls (`add_topic`, `add_metadata`, ...) go through the queue too, so they keep
    their order relative to the messages and the MCAP writer is only touched by one thread.
    """

    def __init__(self, recorder: McapRecorder, max_queue: int = 2000):
        self.rec = recorder
        self.max_queue = max(1, int(max_queue))
        self._q: deque = deque()
        self._wake = threading.Event()
        self._closing = False
        self._lock = threading.Lock()  # serialises close() against itself
        self._report: dict | None = None
        self.error: str = ""
        self.high_water = 0
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()

    @property
    def path(self) -> Path:
        return self.rec.path

    @property
    def stats(self) -> dict[str, TopicStats]:
        return self.rec.stats

    @property
    def closed(self) -> bool:
        return self._closing

    def queued(self) -> int:
        return len(self._q)

    def put(self, topic: str, cdr: bytes, receive_ns: int, pub_seq: int | None = None) -> bool:
        """Queue one message; False (and counted) if the queue is full or closing."""
        if self._closing:  # stopped: a message still in flight is simply not part of this file
            return False
        if len(self._q) >= self.max_queue:
            # the pixels are dropped; a tiny marker keeps the count (and the sequence number,
            # so the gap it leaves is not counted a second time as transport loss)
            self._q.append((2, topic, None, receive_ns, pub_seq))
            return False
        self._q.append((0, topic, cdr, receive_ns, pub_seq))
        if len(self._q) > self.high_water:
            self.high_water = len(self._q)
        self._wake.set()
        return True

    def call(self, method: str, *args) -> None:
        """Run `McapRecorder.<method>(*args)` on the writer thread, in queue order."""
        if not self._closing:
            self._q.append((1, method, args, None, None))
            self._wake.set()

    def _run(self) -> None:
        q, rec = self._q, self.rec
        while True:
            try:
                item = q.popleft()
            except IndexError:
                if self._closing:
                    return
                self._wake.wait(0.05)
                self._wake.clear()
                continue
            try:
                if item[0] == 0:
                    rec.write(item[1], item[2], item[3], item[4])
                elif item[0] == 2:
                    rec.note_overflow(item[1], item[4])
                else:
                    getattr(rec, item[1])(*item[2])
            except Exception as e:  # noqa: BLE001 - kept and reported; the thread goes on
                self.error = f"{type(e).__name__}: {e}"
                log.error("recorder writer: %s", self.error)

    def report(self) -> dict:
        return self.rec.report()

    def close(self, timeout_s: float = 60.0) -> dict:
        """Write what is queued, finish the file, return the report (idempotent)."""
        with self._lock:
            if self._report is not None:
                return self._report
            self._closing = True
            self._wake.set()
            self._thread.join(timeout_s)
            left = len(self._q)
            if self._thread.is_alive():  # writer stuck (disk): count what it never wrote
                log.error("recorder writer did not drain in %.0f s (%d queued)", timeout_s, left)
            self._report = self.rec.close()
            self._report["writer_queue_high_water"] = self.high_water
            if self.error:
                self._report["writer_error"] = self.error
            return self._report


@dataclass(frozen=True)
class RecoveryReport:
    """What `recover` salvaged."""

    source: str
    output: str
    messages: int
    channels: int
    metadata: int
    complete: bool
    error: str

    def as_dict(self) -> dict:
        return asdict(self)


def recover(src: str | Path, dst: str | Path, *, chunk_size: int = 1 << 20) -> RecoveryReport:
    """Copy every intact record of a (possibly truncated) MCAP file into a new, valid file.

    Reads records in file order and stops at the first damaged one (a chunk cut short by a
    killed writer); schemas, channels, messages and metadata read before that are written to
    `dst` with a fresh summary and index. Raises ValueError if `src` is not MCAP at all.
    """
    src, dst = Path(src), Path(dst)
    with open(src, "rb") as f:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise ValueError(f"{src} is not an MCAP file (bad magic)")
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    new_schema: dict[int, int] = {}
    new_channel: dict[int, int] = {}
    n_msg = n_meta = 0
    complete, error = False, ""
    profile = "ros2"
    with open(src, "rb") as f, open(dst, "wb") as out:
        w = Writer(out, chunk_size=chunk_size, compression=CompressionType.NONE)
        started = False
        reader = StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True)
        try:
            for rec in reader.records:
                name = type(rec).__name__
                if name == "Header":
                    profile = rec.profile or profile
                    w.start(profile=profile, library=f"{LIBRARY} (recovered)")
                    started = True
                elif isinstance(rec, Schema):
                    if rec.id not in schemas:
                        schemas[rec.id] = rec
                        new_schema[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    if rec.id not in channels:
                        channels[rec.id] = rec
                        new_channel[rec.id] = w.register_channel(
                            rec.topic, rec.message_encoding, new_schema.get(rec.schema_id, 0),
                            dict(rec.metadata))
                elif isinstance(rec, Message):
                    if rec.channel_id in new_channel:
                        w.add_message(new_channel[rec.channel_id], rec.log_time, rec.data,
                                      rec.publish_time, rec.sequence)
                        n_msg += 1
                elif name == "Metadata":
                    w.add_metadata(rec.name, dict(rec.metadata))
                    n_meta += 1
                elif name == "DataEnd":
                    complete = True
                    break
        except (McapError, EOFError, struct.error, ValueError, IndexError) as e:
            error = f"{type(e).__name__}: {e}"
        except Exception as e:  # noqa: BLE001 - any decoding failure ends the salvage, reported
            error = f"{type(e).__name__}: {e}"
        if not started:
            w.start(profile=profile, library=f"{LIBRARY} (recovered)")
        w.add_metadata("recovery", {"source": str(src), "messages": str(n_msg), "error": error})
        w.finish()
    return RecoveryReport(str(src), str(dst), n_msg, len(channels), n_meta, complete, error)


