"""Fixtures for tests that run real ROS 2 nodes on the isolated, localhost-only DDS domain that
tests/conftest.py gives each test process; subprocesses inherit it through `ros_env`.
"""

import os

import pytest
from rostools import node_command, popen

DOMAIN_ID = os.environ["ROS_DOMAIN_ID"]


@pytest.fixture
def ros_env() -> dict[str, str]:
    """Environment for node subprocesses: the test's isolated domain, unbuffered output, and
    the fault handler on (`stop_process` makes a hung node say where it hung)."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1")
    return env


@pytest.fixture
def lab_env(ros_env):
    """`ros_env` with one emulated pylon camera (serial 0815-0000) for the node processes."""
    return {**ros_env, "PYLON_CAMEMU": "1"}


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


@pytest.fixture
def ros_node(ros_context):
    """A client node and its single-threaded executor on the test's context: (node, executor)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    node = rclpy.create_node("test_client", context=ros_context)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    yield node, ex
    ex.shutdown()
    node.destroy_node()


@pytest.fixture
def start_node(ros_env):
    """`start_node(cmd, *ros_args, env=None)`: start a node entry point (console script name
    or argv) in the isolated domain, output in one text pipe; any process still running at
    the end of the test is killed."""
    procs = []

    def start(cmd, *ros_args, env=None):
        proc = popen(node_command(cmd, *ros_args), ros_env if env is None else env)
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        if proc.stdout is not None and not proc.stdout.closed:
            proc.stdout.close()
