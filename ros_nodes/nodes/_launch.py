"""In-process launch: every rig node in one process on one MultiThreadedExecutor."""

import logging
import sys
import threading

import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter

from ros_nodes.nodes._common import local_discovery_by_default
from ros_nodes.registry import NODES

log = logging.getLogger("metarig.rig")

# Every node's executor work is Python holding the GIL; with the default 5 ms switch interval the
# sequencer's clock thread waited tens of ms per 1 ms tick behind the executor threads (0.1 s of
# simulated time took 6-7 s of wall time instead of 0.2 s); 0.5 ms lets it keep its pace.
GIL_SWITCH_INTERVAL_S = 0.0005


def overrides(params: dict) -> list[Parameter]:
    return [Parameter(k, value=list(v) if isinstance(v, tuple) else v) for k, v in params.items()]


class InProcessRig:
    """Nodes of `node_params` (name -> parameters) spinning in a background thread."""

    def __init__(self, node_params: dict[str, dict], args=None):
        sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_INTERVAL_S))
        self.context = Context()
        local_discovery_by_default()
        rclpy.init(args=args, context=self.context)
        self.executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self.nodes = {}
        for name, params in node_params.items():
            node = NODES[name].node()(context=self.context, parameter_overrides=overrides(params))
            self.nodes[name] = node
            self.executor.add_node(node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._closing = False  # set by shutdown(): the executor may then fail under its nodes

    def add(self, node) -> None:
        self.nodes[node.get_name()] = node
        self.executor.add_node(node)

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # expected when the context is shut down under it
            if not self._closing:  # a callback failed: nothing answers any more, say why
                log.exception("executor stopped")

    def start(self) -> None:
        self._thread.start()

    def shutdown(self) -> None:
        self._closing = True
        for node in self.nodes.values():
            close = getattr(node, "close", None)
            if close is not None:
                close()
        self.executor.shutdown(timeout_sec=2.0)
        for node in self.nodes.values():
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)
