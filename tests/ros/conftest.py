"""Fixtures for tests that run real ROS 2 nodes on an isolated, localhost-only DDS domain.

Every test session picks its own `ROS_DOMAIN_ID` (from the pid) and sets
`ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST` before any rclpy context exists; subprocesses started
by the tests inherit both through `ros_env`.
"""

import os

import pytest

DOMAIN_ID = str(1 + (os.getpid() * 7 + int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0))
                % 200)
os.environ["ROS_DOMAIN_ID"] = DOMAIN_ID
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "1")


@pytest.fixture
def ros_env() -> dict[str, str]:
    """Environment for node subprocesses: the test's isolated domain, unbuffered output."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    return env


@pytest.fixture
def ros_context():
    """A fresh rclpy context for one test, shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    if ctx.ok():
        rclpy.shutdown(context=ctx)
