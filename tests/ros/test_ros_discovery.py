"""Discovery stays on this machine unless the environment opens it (the house rule): every rclpy
context the project starts (node processes, the in-process rig, `metarig rig`) sets
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST where it is unset, and leaves a lab's own value."""

import os

import pytest

from ros_nodes.nodes._common import DISCOVERY_RANGE, local_discovery_by_default
from ros_nodes.nodes._launch import InProcessRig


@pytest.mark.parametrize("given, expected", [(None, "LOCALHOST"), ("", "LOCALHOST"),
                                             ("SUBNET", "SUBNET"), ("OFF", "OFF")])
def test_the_range_is_localhost_unless_the_environment_names_one(monkeypatch, given, expected):
    if given is None:
        monkeypatch.delenv(DISCOVERY_RANGE, raising=False)
    else:
        monkeypatch.setenv(DISCOVERY_RANGE, given)
    assert local_discovery_by_default() == expected == os.environ[DISCOVERY_RANGE]


def test_the_in_process_rig_starts_its_context_on_localhost(monkeypatch):
    monkeypatch.delenv(DISCOVERY_RANGE, raising=False)
    rig = InProcessRig({})
    try:
        assert os.environ[DISCOVERY_RANGE] == "LOCALHOST"
    finally:
        rig.shutdown()
