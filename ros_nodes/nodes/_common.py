"""Shared QoS profiles, the discovery range, and the uniform `main()` of every node."""

import os
import sys
from collections.abc import Callable

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from metarig.signals import note_stop_signals
from ros_nodes import topics


def qos_profile(q: topics.Qos, depth: int | None = None) -> QoSProfile:
    """The rclpy `QoSProfile` of a `topics.Qos` (keep-last; `depth` overrides its depth)."""
    return QoSProfile(
        depth=q.depth if depth is None else depth, history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.RELIABLE if q.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if q.latched
                    else DurabilityPolicy.VOLATILE))


DISCOVERY_RANGE = "ROS_AUTOMATIC_DISCOVERY_RANGE"


def local_discovery_by_default() -> str:
    """Keep DDS discovery on this machine unless the environment opens it: sets
    `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST` where it is unset or empty. Called before every
    rclpy context starts (rcl reads the variable then), so that no participant elsewhere on the
    network can call the rig's services (`/shaker/fire`, `/stage/set_strain`). A lab that wants
    other machines in sets the variable itself (e.g. `SUBNET`). Returns the range in force."""
    if not os.environ.get(DISCOVERY_RANGE):
        os.environ[DISCOVERY_RANGE] = "LOCALHOST"
    return os.environ[DISCOVERY_RANGE]


# the shared profiles (meaning: `ros_nodes.topics`)
COMMAND = qos_profile(topics.COMMAND)
LATCHED = qos_profile(topics.LATCHED)
STREAM = qos_profile(topics.STREAM)
CLOCK = qos_profile(topics.CLOCK_QOS)

def take_queued(sub, limit: int) -> list[tuple]:
    """What is still queued on subscription `sub` (at most `limit` messages, oldest first), as
    its callback gets them (`(msg, info)`; bytes with `raw`). rclpy's executors take one
    message per subscription per wait cycle; where a publisher sends bursts (a device node's
    timer catching up on a busy host) faster than the cycles come, the subscription's
    keep-last queue fills and overwrites its oldest messages. A callback that must miss
    nothing takes the rest of the queue with this."""
    out = []
    with sub.handle:
        while len(out) < limit:
            item = sub.handle.take_message(sub.msg_type, sub.raw)
            if item is None:
                break
            out.append(item)
    return out


def apply_lab_ros(argv: list[str]) -> None:
    """A node started on a lab file (`-p hardware:=lab -p lab_file:=FILE`, or in a params
    file) joins the ROS domain, discovery range and static peers of the file's [ros]
    (`ros_nodes.lab_run.apply_ros`) before its context starts; a lab file that cannot be read
    is left to the node, which reports it when it opens its device."""
    from devices.lab import LabFileError, read_lab
    from ros_nodes.lab_run import apply_ros, lab_file_in_ros_args

    path = lab_file_in_ros_args(list(argv))
    if path is None:
        return
    try:
        apply_ros(read_lab(path).ros)
    except LabFileError:
        pass


STOP_POLL_S = 0.5  # longest wait of a node's spin before it looks at its stop event


def run_node(make: Callable[..., object], args=None, threads: int = 2, **node_kwargs) -> int:
    """Init rclpy, build one node, spin it until Ctrl-C/shutdown (multi-threaded executor with
    `threads` threads; 1: the cheaper single-threaded executor)."""
    # SIGTERM stops a node like Ctrl-C does (files are finished, devices brought to rest), and
    # SIGINT does even where the node was started with it ignored (a shell's background job):
    # rclpy's handler shuts the context down, which ends the spin (no KeyboardInterrupt)
    stop = note_stop_signals()
    # This rclpy (Jazzy 7.1) has no context-manager form of init(); try_shutdown is the `with`.
    try:
        apply_lab_ros(sys.argv if args is None else args)
        local_discovery_by_default()
        rclpy.init(args=args)
        try:
            if stop.is_set():  # stopped before rclpy's handler was there to hear it
                return 0
            try:
                node = make(**node_kwargs)
            except Exception:
                if stop.is_set():  # the context went down under a node being built
                    return 0
                raise
            executor = (SingleThreadedExecutor() if threads <= 1
                        else MultiThreadedExecutor(num_threads=threads))
            executor.add_node(node)
            try:
                # rclpy's handler wakes the spin on Ctrl-C; under load it was seen to miss that
                # (a node still waiting in its wait set 15 s after SIGINT, its fault handler's
                # dump), so the wait is bounded and `stop` (chained, set in this thread between
                # waits) ends the spin within one poll
                while rclpy.ok() and not stop.is_set():
                    executor.spin_once(timeout_sec=STOP_POLL_S)
            except RCLError:
                # Ctrl-C/SIGTERM shut the context down while the executor was building its
                # wait set: that is the requested stop, not a failure
                if rclpy.ok():
                    raise
            finally:
                close = getattr(node, "close", None)
                if close is not None:
                    close()
                executor.shutdown(timeout_sec=1.0)
                node.destroy_node()
        finally:
            rclpy.try_shutdown()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as e:  # a configuration error raised while building the node
        if isinstance(e.code, str):
            print(e.code, file=sys.stderr)
            return 2
        raise
    return 0
