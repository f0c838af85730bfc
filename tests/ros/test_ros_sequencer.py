"""The sequencer's own waits over real DDS: a query that may be repeated is asked again."""

import threading
import time

import pytest

pytest.importorskip("rclpy")

from lifecycle_msgs.srv import GetState  # noqa: E402
from rclpy.callback_groups import ReentrantCallbackGroup  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402

from ros_nodes.nodes.sequencer_node import RigError, ask, until  # noqa: E402


def test_an_unanswered_state_query_is_asked_again(ros_context):
    """A lifecycle node that has just started may drop its first answer (Fast DDS: "failed to
    send response (timeout)" when it has not yet matched the client's reader). Here the server
    holds the first request for up to 60 s and answers later ones at once: `ask` has the answer of its
    second request within about `resend_s`, and refuses in one line when nothing answers."""
    import rclpy

    server = rclpy.create_node("stage", context=ros_context)
    client_node = rclpy.create_node("sequencer", context=ros_context)
    release, seen = threading.Event(), []

    def on_get_state(request, response):
        seen.append(time.monotonic())
        if len(seen) == 1:
            release.wait(60.0)  # the dropped answer (held past any stall of a loaded machine)
        response.current_state.label = "active"
        return response

    server.create_service(GetState, "/stage/get_state", on_get_state,
                          callback_group=ReentrantCallbackGroup())
    client = client_node.create_client(GetState, "/stage/get_state")
    silent = client_node.create_client(GetState, "/nobody/get_state")
    executor = MultiThreadedExecutor(num_threads=3, context=ros_context)
    executor.add_node(server)
    executor.add_node(client_node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        until(client.service_is_ready, "the service", 30.0)  # discovery is not what is timed
        t0 = time.monotonic()
        answer = ask(client, GetState.Request(), timeout_s=40.0, resend_s=1.0)
        assert answer.current_state.label == "active"
        # (a third request only where DDS itself dropped one, the case `ask` is for); answered
        # by a resend long before the held request could have been (a process stalled 8 s in a
        # loaded suite is on record)
        assert len(seen) >= 2 and time.monotonic() - t0 < 30.0
        with pytest.raises(RigError, match=r"^timed out waiting for service /nobody/get_state$"):
            ask(silent, GetState.Request(), timeout_s=0.5, resend_s=0.2)
    finally:
        release.set()  # the held request is answered (to a client that gave up on it) ...
        time.sleep(0.5)  # ... while the executor still spins, not into its shutdown
        executor.shutdown()
        spinner.join(timeout=5.0)
        server.destroy_node()
        client_node.destroy_node()
