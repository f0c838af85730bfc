"""Stopping long commands: Ctrl-C and SIGTERM both raise KeyboardInterrupt in the main thread,
so every command finishes its files the same way whichever way it is stopped (a terminal's
Ctrl-C, `kill`, a batch scheduler's SIGTERM at the end of a job)."""

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def stop_on_signals() -> None:
    """Make Ctrl-C and SIGTERM raise KeyboardInterrupt in the main thread.

    Set explicitly, not inherited: a non-interactive shell starts background jobs with SIGINT
    ignored, and Python then keeps ignoring it (a `metarig rig ... &` never stopped on SIGINT).
    """
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            signal.signal(sig, signal.default_int_handler)


def note_stop_signals() -> threading.Event:
    """Make Ctrl-C and SIGTERM set the returned event instead of raising (in the main thread;
    elsewhere the event is never set).

    For a ROS node's process: set before `rclpy.init`, rclpy's own handler (which chains to this
    one) shuts the context down and wakes the executor, so the spin ends between callbacks. A
    KeyboardInterrupt raised wherever the main thread happened to be could cut an rclpy object
    in half (a Task without its fields, reported as a traceback at exit).
    """
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            signal.signal(sig, lambda _n, _f: stop.set())
    return stop


@contextmanager
def deferred_stop() -> Iterator[None]:
    """Hold Ctrl-C/SIGTERM until the block is done, then raise KeyboardInterrupt.

    Around start-up steps that must not be cut in half: a KeyboardInterrupt inside `Popen`
    (after the fork) would leave a node process that nobody stops.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    old = {sig: signal.signal(sig, lambda n, _f: got.append(n)) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    if got:
        raise KeyboardInterrupt
