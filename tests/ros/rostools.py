"""Helpers for real-node tests: start node processes, spin until a condition holds or a
deadline passes, stop processes."""

import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.prefix) / "bin"


def node_command(cmd: str | list[str], *ros_args: str) -> list[str]:
    """argv of a console script (`metarig-shaker`: from this venv) or of an explicit argv, with
    `--ros-args ros_args...` appended when there are any."""
    argv = [str(BIN / cmd)] if isinstance(cmd, str) else [str(a) for a in cmd]
    return [*argv, "--ros-args", *ros_args] if ros_args else argv


def popen(argv: list[str], env: dict[str, str]) -> subprocess.Popen:
    """Start a process with stdout and stderr combined into one text pipe."""
    return subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def spin_until(executor, predicate, timeout_s: float, what: str, error=AssertionError) -> None:
    """Spin `executor` until `predicate()` is true; raise `error` naming `what` after
    `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise error(f"timed out after {timeout_s} s waiting for {what}")
        executor.spin_once(timeout_sec=0.05)


def wait_for_service(client, executor, timeout_s: float = 45.0) -> None:
    spin_until(executor, lambda: client.service_is_ready(), timeout_s,
               f"service {client.srv_name}")


def call(client, request, executor, timeout_s: float = 45.0, resend_s: float = 5.0):
    """Call a service, spinning `executor` until the response arrives; a request unanswered
    after `resend_s` is sent again, as the rig's sequencer does (`sequencer_node.ask`: right
    after start-up Fast DDS may drop a response; tests call only services whose repeat is
    harmless at that point)."""
    from ros_nodes.logic.experiment import RigError
    from ros_nodes.nodes.sequencer_node import ask

    def wait(predicate, what, t):
        spin_until(executor, predicate, t, what, error=RigError)

    try:
        return ask(client, request, timeout_s, resend_s, wait=wait)
    except RigError as exc:
        raise AssertionError(str(exc)) from None


def wait_matched(pub_or_sub, executor, timeout_s: float = 20.0, count: int = 1) -> None:
    """Wait until a publisher has `count` matched subscriptions (or a subscription publishers)."""
    get = getattr(pub_or_sub, "get_subscription_count", None) or pub_or_sub.get_publisher_count
    spin_until(executor, lambda: get() >= count, timeout_s, f"{count} match(es) on {pub_or_sub.topic_name}")


def stop_process(proc: subprocess.Popen, timeout_s: float = 15.0) -> str:
    """SIGINT a node process, wait for it (kill if it hangs), return its combined output."""
    if proc.poll() is None:
        proc.send_signal(subprocess.signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired as exc:
        # SIGABRT first: a node started with PYTHONFAULTHANDLER (`ros_env`) writes where each
        # of its threads stood into its output, so a hang says where it hung
        proc.send_signal(subprocess.signal.SIGABRT)
        try:
            out, _ = proc.communicate(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        raise AssertionError(
            f"process did not stop on SIGINT within {timeout_s} s:\n{out}") from exc
    return out
