"""The lifecycle every device node shares (shaker, stages): one skeleton, the device's own
parts as hooks.

configure: the node's publishers and the device behind its port (parameter `hardware`: "sim",
or "lab" with `lab_file`, `ros_nodes.hardware`); a lab file or device that cannot be used fails
the transition with one logged line and a `/diagnostics` error, and leaves the node
unconfigured (a later configure starts afresh). activate: the device clock starts and the node
samples it every 1 / `rate_hz` on a timer. deactivate: the device is brought to rest, the timer
goes. cleanup: publishers destroyed, the device released (whatever it answers). `/rig/stop`
brings the device to rest in any state. With `hardware` "lab" the lab file's limits hold:
`device.*` parameter changes at run time do not reach the device. `close()` (the node going
down) brings the device to rest and releases it.

The timer has a callback group of its own, so a node that falls behind its sampling (a loaded
machine: the timer is due again whenever it returns, and rclpy serves timers first) still
answers its services, `/rig/stop` and lifecycle transitions, on the executor's other thread.
Everything that touches the device runs under one lock, which the timer holds for each call:
a request waits for at most one sampling call, and never runs beside one. A large message (a
long burst's commanded waveform) is built and published on the node's outbox thread, off that
lock and after the request's answer (`_publish_later`), so that a stop does not wait for it.
"""

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn
from std_msgs.msg import Empty

from devices.lab import LabFileError
from devices.limits import DeviceError
from ros_nodes import convert
from ros_nodes import topics as T
from ros_nodes.nodes._common import COMMAND
from ros_nodes.nodes._params import TypedParams


class DeviceNode(LifecycleNode):
    """A lifecycle node over one device port. Subclasses set `NAME` (the node's name),
    `CONFIG` (its config dataclass, with `seed`, `rate_hz`, `autostart`, `hardware`,
    `device`) and `DEVICE` (the device in words, "the shaker"), and supply the hooks below."""

    NAME: str
    CONFIG: type
    DEVICE: str

    def __init__(self, **kwargs):
        super().__init__(self.NAME, **kwargs)
        # the timer's readings vs requests, transitions and close() (other threads); reentrant:
        # a failed configure and close() clean up under it
        self._device_lock = threading.RLock()
        self._sampling = MutuallyExclusiveCallbackGroup()  # the timer's own group
        self._params = TypedParams(self, self.CONFIG, on_change=self._locked(self._reconfigured))
        self._active = False
        self._device = None
        self._timer = None
        self._pubs: dict = {}
        # large messages, built and published in order off the device lock (`_publish_later`)
        self._outbox = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{self.NAME}-outbox")
        for srv_type, name, callback in self._device_services():
            self.create_service(srv_type, name, self._locked(callback))
        self.create_subscription(Empty, T.RIG_STOP.name, self._locked(lambda _m: self._rig_stop()),
                                 COMMAND)
        if self._params.config.autostart and \
                self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self.trigger_activate()

    # hooks -------------------------------------------------------------------------------
    def _device_services(self) -> list[tuple]:
        """The node's services as (type, name, callback), created at construction; each is
        answered under the device lock."""
        return []

    def _create_publishers(self) -> dict:
        """The node's own publishers (configure), by key; "diag" (`/diagnostics`) is added."""
        return {}

    def _open(self, cfg, rng: np.random.Generator):
        """The device behind the port `cfg.hardware` names; raises on a device it cannot use."""
        raise NotImplementedError

    def _halt(self) -> None:
        """Bring the device to rest (deactivate, shutdown, `/rig/stop`)."""

    def _sample(self) -> None:
        """The timer's work, under the device lock, with a device open."""

    def _configured(self) -> None:
        """After a successful configure."""

    def _activated(self) -> None:
        """After activate."""

    def _deactivated(self) -> None:
        """After deactivate."""

    def _diag_values(self) -> dict:
        """The values every `/diagnostics` report of `_report` carries."""
        return {}

    def _rig_stop(self) -> None:
        """`/rig/stop`."""
        self._halt()

    # lifecycle ---------------------------------------------------------------------------
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        with self._device_lock:
            return self._configure(state)

    def _configure(self, state: State) -> TransitionCallbackReturn:
        cfg = self._params.config
        self._rng = np.random.default_rng(cfg.seed)
        self._pubs = {**self._create_publishers(), "diag": self.create_publisher(
            convert.DiagnosticArray, T.DIAGNOSTICS.name, COMMAND)}
        try:
            self._device = self._open(cfg, self._rng)
        except (LabFileError, DeviceError, ValueError, OSError) as e:
            self.get_logger().error(f"cannot configure {self.DEVICE}: {e}")
            self._report("error", f"cannot configure {self.DEVICE}: {e}")
            self.on_cleanup(state)  # back to unconfigured: a later configure starts afresh
            return TransitionCallbackReturn.FAILURE
        self._configured()
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        with self._device_lock:
            self._device.start(self._now_s())
            self._timer = self.create_timer(1.0 / self._params.config.rate_hz, self._tick,
                                            callback_group=self._sampling)
            self._active = True
            self._activated()
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        with self._device_lock:
            self._active = False
            self._halt()
            if self._timer is not None:
                self.destroy_timer(self._timer)
                self._timer = None
            self._deactivated()
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        with self._device_lock:
            for p in self._pubs.values():
                self.destroy_publisher(p)
            self._pubs = {}
            if self._device is not None:
                try:  # released whatever: a device that stopped answering cannot be told more
                    self._device.close()
                except (DeviceError, OSError) as e:
                    self.get_logger().error(f"{self.DEVICE} did not stop on release: {e}")
                self._device = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        with self._device_lock:
            self._active = False
            self._halt()
        return TransitionCallbackReturn.SUCCESS

    # shared ------------------------------------------------------------------------------
    def _reconfigured(self, cfg) -> None:
        if self._device is None:
            return
        if cfg.hardware == "lab":  # the lab file's limits stand
            self.get_logger().warning("hardware 'lab': the limits are the lab file's; device.* "
                                      "parameters do not change them")
            return
        self._device.reconfigure(cfg.device)  # new limits hold from the next command

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _locked(self, callback):
        """`callback` run under the device lock."""
        def locked(*args):
            with self._device_lock:
                return callback(*args)
        return locked

    def _tick(self) -> None:
        with self._device_lock:
            if self._device is not None:  # not closed
                self._sample()

    def _report(self, level: str, message: str, values: dict | None = None) -> None:
        """A `/diagnostics` line of this node, stamped now."""
        if "diag" in self._pubs:
            self._pubs["diag"].publish(convert.diagnostics(
                self.get_clock().now().nanoseconds, self.NAME, level, message,
                {**self._diag_values(), **(values or {})}))

    def _publish_later(self, key: str, build) -> None:
        """Publish the message `build()` returns on publisher `key`, from the node's outbox
        thread (in the order asked): off the device lock, so a large message does not hold up
        a stop. A 50 s burst's commanded waveform (100 000 points), built inside the request,
        held its answer, and every request and stop, 14-15 s beside four busy loops.
        A publisher gone meanwhile (cleanup) drops the message, with a warning."""
        pub = self._pubs.get(key)
        if pub is None:
            return

        def send():
            try:
                pub.publish(build())
            except Exception as e:  # noqa: BLE001 - on a thread of its own: logged, not lost
                self.get_logger().warning(f"{self.DEVICE}: {key} message not published: {e}")

        self._outbox.submit(send)

    def close(self) -> None:
        """Bring the device to rest and release it (the node is going down)."""
        self._active = False
        self._outbox.shutdown(wait=False, cancel_futures=True)
        with self._device_lock:
            self._closing()
            if self._timer is not None:
                self.destroy_timer(self._timer)
            self._timer = None
            self.on_cleanup(None)

    def _closing(self) -> None:
        """What reaches the device before it is released in `close` (under the lock)."""

