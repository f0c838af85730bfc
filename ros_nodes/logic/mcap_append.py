"""Add topics to a finished recording: a copy of every record plus new messages, atomically.

An MCAP file is finished once (summary, index); results computed after the capture (tracked
poses, the comparison) are added by writing a new file with everything the old one held plus
the new channels, then replacing the target in one rename. The source is never modified in
place, so an interrupted run leaves the old recording whole.
"""

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from ros_nodes.logic import msgdefs
from ros_nodes.logic.recorder import LIBRARY


@dataclass(frozen=True)
class NewMessage:
    """One serialized message for `append_messages`: topic, log time (ns, rig clock), CDR."""

    topic: str
    log_ns: int
    cdr: bytes


def _current(name: str, data: bytes) -> bool:
    """Whether a schema's text is the definition this build serialises with."""
    try:
        return msgdefs.schema_text(name).encode() == bytes(data)
    except msgdefs.UnknownMessageType:
        return False


def append_messages(src: str | Path, dst: str | Path, types: dict[str, str],
                    messages: list[NewMessage], replace: tuple[str, ...] = (),
                    metadata: dict[str, dict[str, str]] | None = None) -> Path:
    """Write `dst` = all of `src` + `messages` on the topics of `types` ({topic: pkg/msg/Type}).

    Messages already in `src` on the `replace` topics are left out (re-running a comparison
    replaces its results instead of doubling them); on any other topic that `src` already has,
    the new messages join its channel. `dst` may equal `src`.

    Raises:
        ValueError: `src` is not a finished MCAP file, or a message names an unknown topic.
    """
    src, dst = Path(src), Path(dst)
    unknown = {m.topic for m in messages} - set(types)
    if unknown:
        raise ValueError(f"no type given for topics {sorted(unknown)}")
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    try:
        with open(src, "rb") as f, open(tmp, "wb") as out:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                raise ValueError(f"{src}: MCAP file has no summary (unfinished recording? run "
                                 "`metarig recover` on it first)")
            header = reader.get_header()
            w = Writer(out, chunk_size=1 << 20, compression=CompressionType.ZSTD)
            w.start(profile=header.profile or "ros2", library=header.library or LIBRARY)
            schema_ids = {sid: w.register_schema(s.name, s.encoding, s.data)
                          for sid, s in summary.schemas.items()}
            channel_ids, existing = {}, {}
            for cid, ch in summary.channels.items():
                if ch.topic in replace:
                    continue
                channel_ids[cid] = w.register_channel(ch.topic, ch.message_encoding,
                                                      schema_ids.get(ch.schema_id, 0),
                                                      dict(ch.metadata))
                existing[ch.topic] = channel_ids[cid]
            seq = 0
            for _schema, channel, msg in reader.iter_messages(log_time_order=True):
                if channel.id in channel_ids:
                    w.add_message(channel_ids[channel.id], msg.log_time, msg.data,
                                  msg.publish_time, msg.sequence)
                    seq = max(seq, msg.sequence + 1)
            # a schema of the source is reused only where it is today's definition (an older
            # recording's definition of a message that has gained fields is kept for its own
            # messages; the new ones get today's)
            by_name = {s.name: sid for sid, s in zip(schema_ids.values(), summary.schemas.values())
                       if _current(s.name, s.data)}
            new_channels = dict(existing)
            for topic, type_name in types.items():
                if topic in new_channels:
                    continue
                pkg, name = msgdefs.normalize(type_name)
                full = f"{pkg}/msg/{name}"
                if full not in by_name:
                    by_name[full] = w.register_schema(full, "ros2msg",
                                                      msgdefs.schema_text(full).encode())
                new_channels[topic] = w.register_channel(topic, "cdr", by_name[full], {})
            for m in sorted(messages, key=lambda m: m.log_ns):
                w.add_message(new_channels[m.topic], int(m.log_ns), m.cdr, int(m.log_ns), seq)
                seq += 1
            for meta in reader.iter_metadata():
                w.add_metadata(meta.name, dict(meta.metadata))
            for att in reader.iter_attachments():
                w.add_attachment(att.create_time, att.log_time, att.name, att.media_type,
                                 att.data)
            for name, values in (metadata or {}).items():
                w.add_metadata(name, {str(k): str(v) for k, v in values.items()})
            w.finish()
        os.replace(tmp, dst)
    except Exception as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, (OSError, ValueError)):
            raise
        raise ValueError(f"{src}: cannot copy the recording ({exc})") from None
    return dst
