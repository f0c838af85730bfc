"""Who may command motion, over DDS on the test's isolated domain: the shaker and stage nodes
(this process, their own participant) accept `/shaker/fire` and `/stage/set_strain` from the
sequencer (a second participant) and refuse them, with the reason, while a third participant's
node that is not on `allowed_callers` has a client there; stopping takes anyone; a node named
on the list may command."""

import os
import threading

import pytest
from rostools import call, spin_until


@pytest.fixture
def devices(ros_context):
    """Shaker and stage nodes (simulated devices, default allow-list) spinning in a thread."""
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from ros_nodes.nodes.shaker_node import ShakerNode
    from ros_nodes.nodes.stage_node import StageNode

    shaker = ShakerNode(context=ros_context, parameter_overrides=[Parameter("rate_hz", value=50.0)])
    stage = StageNode(context=ros_context, parameter_overrides=[Parameter("rate_hz", value=20.0)])
    ex = MultiThreadedExecutor(num_threads=2, context=ros_context)
    for node in (shaker, stage):
        ex.add_node(node)
    thread = threading.Thread(target=ex.spin, daemon=True)
    thread.start()
    yield shaker, stage
    ex.shutdown(timeout_sec=2.0)
    for node in (shaker, stage):
        node.destroy_node()


class Participant:
    """A node in a context of its own (its own DDS participant), with its own executor."""

    def __init__(self, name: str, namespace: str = "/"):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, namespace=namespace, context=self.context)
        self.ex = SingleThreadedExecutor(context=self.context)
        self.ex.add_node(self.node)
        self._clients: dict = {}

    def fire(self, amplitude_m: float = 0.002):
        from metarig_msgs.srv import FirePulse

        return call(self.client(FirePulse, "/shaker/fire"),
                    FirePulse.Request(waveform="pulse", amplitude_m=amplitude_m,
                                      frequency_hz=30.0), self.ex, timeout_s=20.0)

    def set_strain(self, strain: float):
        from metarig_msgs.srv import SetStrain

        return call(self.client(SetStrain, "/stage/set_strain"), SetStrain.Request(strain=strain),
                    self.ex, timeout_s=20.0)

    def client(self, srv_type, name: str):
        if name not in self._clients:
            self._clients[name] = self.node.create_client(srv_type, name)
        return self._clients[name]

    def close(self) -> None:
        import rclpy

        if not self.context.ok():
            return
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _clients_seen(node, service: str) -> set[str]:
    from ros_nodes.logic.command_guard import full_name, request_topic

    return {full_name(i.node_namespace, i.node_name)
            for i in node.get_publishers_info_by_topic(request_topic(service), no_mangle=True)}


def test_only_the_sequencer_or_the_allow_list_may_command_motion(devices):
    from metarig_msgs.srv import FirePulse
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    shaker, stage = devices
    seq, intruder = Participant("sequencer"), Participant("script", "/elsewhere")
    try:
        r = seq.fire()
        assert r.accepted, r.message
        assert seq.set_strain(0.01).accepted
        # another program on the domain opens a client on the shaker's fire service
        intruder.client(FirePulse, "/shaker/fire")
        spin_until(intruder.ex, lambda: "/elsewhere/script" in _clients_seen(shaker, "/shaker/fire"),
                   20.0, "the shaker to see the script's client")
        r = intruder.fire()
        assert not r.accepted and r.message.startswith(
            "refused: /elsewhere/script may not command motion (allowed_callers: /sequencer)")
        r = seq.fire()  # a request does not say who sent it: refused while the script is there
        assert not r.accepted and "/elsewhere/script may not command motion" in r.message
        assert seq.set_strain(0.02).accepted  # no stranger on the stage's service
        # stopping takes anyone
        assert call(intruder.client(Trigger, "/shaker/stop"), Trigger.Request(), intruder.ex,
                    timeout_s=20.0).success
        # the allow-list names the script: both may command
        shaker.set_parameters([Parameter("allowed_callers",
                                         value=["/sequencer", "/elsewhere/script"])])
        spin_until(intruder.ex, lambda: shaker._playing_until is None, 30.0, "the pulse to end")
        r = intruder.fire()
        assert r.accepted, r.message
        # the script gone and the list back to the sequencer: the sequencer commands again
        shaker.set_parameters([Parameter("allowed_callers", value=["/sequencer"])])
        intruder.close()
        spin_until(seq.ex, lambda: "/elsewhere/script" not in _clients_seen(shaker, "/shaker/fire")
                   and shaker._playing_until is None, 20.0, "the script's client to go")
        r = seq.fire()
        assert r.accepted, r.message
    finally:
        seq.close()
        intruder.close()


def test_a_node_started_on_a_lab_file_joins_the_domain_of_its_ros_section(
        tmp_path, ros_node, start_node):
    import time

    import rclpy
    from rclpy.context import Context

    from rostools import stop_process

    domain = int(os.environ["ROS_DOMAIN_ID"]) + 101  # tests use 1-100: no other test is there
    lab = tmp_path / "lab.toml"
    lab.write_text(f'[stage]\ndriver = "sim"\n[ros]\ndomain_id = {domain}\n')
    proc = start_node("metarig-stage", "-r", "__ns:=/lab_rig", "-p", "hardware:=lab", "-p",
                      f"lab_file:={lab}")
    name = ("stage", "/lab_rig")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    there = rclpy.create_node("probe", context=ctx)
    here, ex = ros_node  # the test's own domain, which the node's environment named
    try:
        deadline = time.monotonic() + 30
        while name not in there.get_node_names_and_namespaces():
            assert time.monotonic() < deadline and proc.poll() is None, "no stage node in the " \
                f"lab file's domain {domain}"
            time.sleep(0.1)
        time.sleep(1.0)  # discovery on this machine takes milliseconds: long enough to see it
        ex.spin_once(timeout_sec=0.1)
        assert name not in here.get_node_names_and_namespaces()
    finally:
        there.destroy_node()
        rclpy.try_shutdown(context=ctx)
        stop_process(proc)
