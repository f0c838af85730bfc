"""MCAP recorder node: records rig topics (serialized, never decoded) into a rosbag2-style MCAP.

Interfaces (node name `recorder`):
- services `~/start` and `~/stop` (std_srvs/Trigger): open `path` and record / finish the file;
  the stop response carries the loss report (JSON) in `message`; `autostart` records at once.
- `~/report` (std_msgs/String, latched): the report of the last finished recording (JSON).
- `~/status` (std_msgs/String, 5 Hz): whether recording, whether every subscription has matched
  its publishers (`matched`), messages written per topic (`counts`) and the newest stamp
  written per topic (`last_stamp_s`, s) (JSON).
Topics in `topics` are subscribed as they appear (types discovered from the graph), with the
publishers' reliability and durability (latched topics stay latched). The strings on
`/rig/design` and `/rig/config` are also stored as MCAP metadata records. Ctrl-C or SIGTERM
finishes the file properly; a SIGKILL leaves all but the last chunk for `metarig recover`.
"""

import json

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.logic.cdr import string_text
from ros_nodes.logic.recorder import McapRecorder, QueuedRecorder
from ros_nodes.nodes._common import COMMAND, LATCHED, run_node, take_queued
from ros_nodes.nodes._params import TypedParams
from ros_nodes.params import RecorderNodeConfig

NAME = "recorder"
METADATA_TOPICS = {T.RIG_DESIGN.name: "design", T.RIG_CONFIG.name: "rig_config"}


def _qos_yaml(qos: QoSProfile) -> str:
    return (f"- history: 3\n  depth: 0\n  reliability: {int(qos.reliability)}\n"
            f"  durability: {int(qos.durability)}\n  deadline:\n    sec: 0\n    nsec: 0\n"
            "  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n"
            "  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
            "  avoid_ros_namespace_conventions: false\n")


class RecorderNode(Node):
    """Thin adapter over `ros_nodes.logic.recorder.McapRecorder`."""

    def __init__(self, **kwargs):
        super().__init__(NAME, **kwargs)
        self._params = TypedParams(self, RecorderNodeConfig)
        self._rec: QueuedRecorder | None = None
        self._subs: dict = {}
        self._latched: dict[str, tuple[bytes, int, int | None]] = {}
        self._qos: dict[str, QoSProfile] = {}
        self._registered: set[str] = set()  # topics whose channel is (being) registered
        self._several: set[str] = set()  # topics seen with several publishers while recording
        self._report_pub = self.create_publisher(String, T.RECORDER_REPORT.name, LATCHED)
        self._status_pub = self.create_publisher(String, T.RECORDER_STATUS.name, COMMAND)
        # wall-clock timers: they must run while simulated time is paused
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._status_timer = self.create_timer(0.2, self._status, clock=steady)
        self.create_service(Trigger, T.RECORDER_START.name, self._on_start)
        self.create_service(Trigger, T.RECORDER_STOP.name, self._on_stop)
        self._timer = self.create_timer(self._params.config.discovery_period_s, self._discover,
                                        clock=steady)
        if self._params.config.autostart:
            self.start()

    # pure-ish helpers used by callbacks and by the in-process launcher ----------------------
    def _subs_latched(self, topic: str) -> bool:
        qos = self._qos.get(topic)
        return qos is not None and qos.durability == DurabilityPolicy.TRANSIENT_LOCAL

    def start(self) -> str:
        if self._rec is not None:
            return f"already recording to {self._rec.path}"
        cfg = self._params.config
        rec = McapRecorder(cfg.path, chunk_size=cfg.chunk_size, gap_factor=cfg.gap_factor,
                           compression=cfg.compression)
        rec.add_metadata("recorder", {k: json.dumps(v) for k, v in
                                      {"topics": list(cfg.topics), "path": cfg.path,
                                       "chunk_size": cfg.chunk_size,
                                       "compression": cfg.compression,
                                       "write_queue": cfg.write_queue}.items()})
        # receive callbacks only enqueue bytes; a writer thread owns the MCAP writer
        self._rec = QueuedRecorder(rec, cfg.write_queue)
        self._registered, self._several = set(), set()
        self._discover()
        # latched topics (design, config, targets) seen before the start go in first
        for topic, (data, receive_ns, seq) in list(self._latched.items()):
            self._write(self._rec, topic, data, receive_ns, seq)
        self.get_logger().info(f"recording to {cfg.path}")
        return f"recording to {cfg.path}"

    def stop(self) -> dict | None:
        rec, self._rec = self._rec, None
        if rec is None:
            return None
        try:  # a publisher that joined since the last discovery; the graph may be gone
            self._note_publishers(rec)
        except RuntimeError:  # rclpy's RCLError, InvalidHandle
            pass
        report = rec.close()
        self._report_pub.publish(String(data=json.dumps(report)))
        lost = report["dropped"]
        msg = (f"recording finished: {report['messages']} messages, {lost} dropped "
               f"-> {report['path']}")
        if lost:
            self.get_logger().warning(msg + " (see the report: gaps per topic)")
        else:
            self.get_logger().info(msg)
        return report

    def close(self) -> None:
        self.stop()

    def message_counts(self) -> dict[str, int]:
        rec = self._rec
        return {} if rec is None else {t: s.count for t, s in list(rec.stats.items())}

    def last_stamps(self) -> dict[str, float]:
        """The newest stamp written per topic, s."""
        rec = self._rec
        return {} if rec is None else {t: s.last_stamp_ns * 1e-9 for t, s in
                                       list(rec.stats.items()) if s.last_stamp_ns is not None}

    # callbacks ------------------------------------------------------------------------------
    def matched(self) -> bool:
        """True when every recorded topic's subscription has matched all its publishers (until
        then a message sent now may never reach the file)."""
        return all(entry[2].get_publisher_count() >= self.count_publishers(topic)
                   for topic, entry in list(self._subs.items()) if entry is not None)

    def _status(self) -> None:
        self._status_pub.publish(String(data=json.dumps(
            {"recording": self._rec is not None, "matched": self.matched(),
             "counts": self.message_counts(), "last_stamp_s": self.last_stamps()})))

    def _discover(self) -> None:
        wanted = set(self._params.config.topics)
        for topic, types in self.get_topic_names_and_types():
            if topic not in wanted or topic in self._subs or not types:
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            offered = [i.qos_profile for i in infos]
            reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
            latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
            # never shallower than the publisher's queue where the topic table knows it (the
            # joint states: 5 s at 1 kHz); latched topics too: a late joiner still gets only
            # what the publisher keeps (the last one), and a queue of 1 lost a /rig/phase
            # published while the callback took a long queue of another topic
            known = T.BY_NAME.get(topic)
            depth = max(self._params.config.queue_depth, known.qos.depth if known else 0)
            qos = QoSProfile(depth=depth,
                             reliability=ReliabilityPolicy.RELIABLE if reliable
                             else ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                             else DurabilityPolicy.VOLATILE)
            try:
                cls = convert.message_class(types[0])
            except (ImportError, AttributeError, ValueError) as e:
                self.get_logger().warning(f"cannot record {topic} ({types[0]}): {e}")
                self._subs[topic] = None
                continue
            self._qos[topic] = qos
            self._subs[topic] = (types[0], qos, self.create_subscription(
                cls, topic, self._callback(topic), qos, raw=True))
        rec = self._rec
        if rec is not None:
            for topic, entry in self._subs.items():
                if entry is not None and topic not in self._registered:
                    self._registered.add(topic)
                    rec.call("add_topic", topic, entry[0], _qos_yaml(entry[1]))
            self._note_publishers(rec)

    def _note_publishers(self, rec: QueuedRecorder) -> None:
        """Tell the recorder which topics have had several publishers (their sequence numbers
        are per publisher, and a message does not say which one sent it)."""
        for topic, entry in list(self._subs.items()):
            if entry is not None and topic not in self._several and \
                    self.count_publishers(topic) > 1:
                self._several.add(topic)
                rec.call("several_publishers", topic)

    def _write(self, rec: QueuedRecorder, topic: str, data: bytes, receive_ns: int, seq) -> None:
        if topic not in self._registered:
            self._registered.add(topic)
            entry = self._subs[topic]
            rec.call("add_topic", topic, entry[0], _qos_yaml(entry[1]))
        rec.put(topic, data, receive_ns, seq)
        if topic in METADATA_TOPICS:
            text = string_text(data)
            if text is not None:
                rec.call("add_metadata", METADATA_TOPICS[topic], {"json": text})

    def _callback(self, topic: str):
        clock = self.get_clock()
        latched = self._subs_latched(topic)
        metadata = topic in METADATA_TOPICS

        def on_message(data: bytes, info) -> None:
            receive(data, info)
            # the executor hands over one message per wait cycle: take the rest of the queue
            # now (one cycle over every node of the in-process lab rig took so long on a busy
            # host that the shaker's 500 Hz samples overflowed the queue: thousands lost)
            entry = self._subs.get(topic)
            if entry is not None:
                for more in take_queued(entry[2], entry[1].depth):
                    receive(*more)

        def receive(data: bytes, info) -> None:
            # hot path (up to ~1000 frames/s): stamp, enqueue, return; no decoding
            now = clock.now().nanoseconds
            seq = info.get("publication_sequence_number")
            if latched:
                self._latched[topic] = (data, now, seq)
            rec = self._rec
            if rec is None:
                return
            if metadata or topic not in self._registered:
                self._write(rec, topic, data, now, seq)
            else:
                rec.put(topic, data, now, seq)

        return on_message

    def _on_start(self, req, res):
        res.message = self.start()
        res.success = True
        return res

    def _on_stop(self, req, res):
        report = self.stop()
        res.success = report is not None
        res.message = json.dumps(report) if report is not None else "not recording"
        return res


def main(args=None) -> int:
    # one executor thread: the receive callbacks are tiny and the writer has its own thread
    # (the multi-threaded executor's per-callback overhead capped the frame rate)
    return run_node(RecorderNode, args=args, threads=1)


if __name__ == "__main__":
    raise SystemExit(main())
