"""The allow-list of the motion services, read from the ROS graph (`logic.command_guard`)."""

import time

from rclpy.node import Node

from ros_nodes.logic.command_guard import UNKNOWN_NODE, full_name, refusal, request_topic

SETTLE_S = 2.0  # how long a request waits for discovery to name every client, s
POLL_S = 0.02


def motion_refusal(node: Node, service: str, allowed: tuple[str, ...]) -> str | None:
    """Why `node` refuses a motion request on `service` (None: accept), from the nodes that
    have a client on it now; a client the graph cannot name yet is waited for up to SETTLE_S."""
    deadline = time.monotonic() + SETTLE_S
    while True:
        infos = node.get_publishers_info_by_topic(request_topic(service), no_mangle=True)
        clients = [full_name(i.node_namespace, i.node_name) for i in infos]
        why = refusal(service, clients, allowed)
        if why is None or (clients and UNKNOWN_NODE not in clients) \
                or time.monotonic() > deadline:
            return why
        time.sleep(POLL_S)
