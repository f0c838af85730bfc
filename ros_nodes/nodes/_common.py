"""Shared QoS profiles and the uniform `main()` of every node."""

import signal
import threading
from collections.abc import Callable

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import (ExternalShutdownException, MultiThreadedExecutor,
                              SingleThreadedExecutor)
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# commands and set-points: reliable, a short queue
COMMAND = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     history=HistoryPolicy.KEEP_LAST)
# latched: the sample layout, rig configuration, current targets (late joiners get the last one)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)
# measured streams (joint states, frames, poses): reliable publishers with a deep queue; live
# viewers may subscribe best-effort (`rclpy.qos.qos_profile_sensor_data`)
STREAM = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    history=HistoryPolicy.KEEP_LAST)
CLOCK = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                   history=HistoryPolicy.KEEP_LAST)


def run_node(make: Callable[..., object], args=None, threads: int = 2, **node_kwargs) -> int:
    """Init rclpy, build one node, spin it until Ctrl-C/shutdown (multi-threaded executor with
    `threads` threads; 1: the cheaper single-threaded executor)."""
    # SIGTERM stops a node like Ctrl-C does (files are finished, devices brought to rest)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    # This rclpy (Jazzy 7.1) has no context-manager form of init(); try_shutdown is the `with`.
    try:
        rclpy.init(args=args)
        try:
            node = make(**node_kwargs)
            executor = (SingleThreadedExecutor() if threads <= 1
                        else MultiThreadedExecutor(num_threads=threads))
            executor.add_node(node)
            try:
                executor.spin()
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
            import sys

            print(e.code, file=sys.stderr)
            return 2
        raise
    return 0
