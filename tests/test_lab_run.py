"""What `metarig rig --hardware lab` and a node started on a lab file take from it, without
ROS: the lab file named in a node's ROS arguments, and the [ros] section put into the
environment."""

import os

from devices.lab import RosSection
from ros_nodes.lab_run import apply_ros, lab_file_in_ros_args


def test_the_lab_file_of_a_node_started_on_one(tmp_path):
    argv = ["metarig-stage", "--ros-args", "-p", "hardware:=lab", "-p", "lab_file:=lab.toml"]
    assert lab_file_in_ros_args(argv) == "lab.toml"
    assert lab_file_in_ros_args(argv[:4]) is None                 # no lab_file
    assert lab_file_in_ros_args(["--param", "lab_file:=lab.toml"]) is None  # hardware sim
    params = tmp_path / "p.yaml"
    params.write_text("stage:\n  ros__parameters:\n    hardware: lab\n    lab_file: a.toml\n")
    assert lab_file_in_ros_args(["--params-file", str(params)]) == "a.toml"
    # -p wins over the file, whatever the order
    assert lab_file_in_ros_args(["-p", "lab_file:=b.toml", "--params-file", str(params)]) == \
        "b.toml"
    params.write_text(": not yaml [")
    assert lab_file_in_ros_args(["--params-file", str(params)]) is None


def test_the_ros_section_replaces_the_environment(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "5")
    monkeypatch.setenv("ROS_STATIC_PEERS", "somewhere")
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    env = apply_ros(RosSection(42, "subnet", (), given=True))
    assert env == {"ROS_DOMAIN_ID": "42", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    assert os.environ["ROS_DOMAIN_ID"] == "42" and "ROS_STATIC_PEERS" not in os.environ
    apply_ros(RosSection(7, "localhost", ("rig-pc",), given=True))
    assert os.environ["ROS_STATIC_PEERS"] == "rig-pc"
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def test_a_lab_file_without_a_ros_section_keeps_the_environment(monkeypatch, tmp_path):
    from devices.lab import read_lab

    lab = tmp_path / "lab.toml"
    lab.write_text('[stage]\ndriver = "sim"\n')
    ros = read_lab(lab).ros
    assert not ros.given and ros == RosSection()
    monkeypatch.setenv("ROS_DOMAIN_ID", "5")
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("ROS_STATIC_PEERS", raising=False)
    assert apply_ros(ros) == {"ROS_DOMAIN_ID": "5", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    assert apply_ros(ros)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    lab.write_text("[ros]\n")
    assert read_lab(lab).ros.given
