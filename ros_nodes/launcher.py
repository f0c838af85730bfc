"""The project's small launcher (there is no `ros2 launch` here): node processes (pure part).

`metarig rig` runs every node in its own process with `--processes`: each node is its console
script with `--ros-args -p name:=value ...`. This module builds those command lines and manages
the processes (start, stop with SIGINT, then SIGTERM, then SIGKILL after deadlines). The
in-process variant (one MultiThreadedExecutor) is `ros_nodes.nodes._launch`.
"""

import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from metarig.signals import deferred_stop
from ros_nodes.registry import NODES, STOP_ORDER

log = logging.getLogger("metarig.launcher")
def ros_value(v) -> str:
    """A parameter value in `-p name:=value` syntax (YAML)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(ros_value(x) for x in v) + "]"
    if isinstance(v, str):
        return json.dumps(v)
    return repr(v)


def command_line(node: str, params: dict, params_file: Path | None = None) -> list[str]:
    """argv of one node's console script with its parameters."""
    exe = Path(sys.prefix) / "bin" / NODES[node].script
    argv = [str(exe), "--ros-args"]
    if params_file is not None:
        argv += ["--params-file", str(params_file)]
    for k, v in params.items():
        argv += ["-p", f"{k}:={ros_value(v)}"]
    return argv


@dataclass
class ProcessGroup:
    """Node processes started together and stopped together."""

    logs_dir: Path
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, node: str, argv: list[str]) -> None:
        self.logs_dir.mkdir(parents=True, exist_ok=True)
        with open(self.logs_dir / f"{node}.log", "w") as out, deferred_stop():
            # own process group: a terminal Ctrl-C reaches us first, and we stop nodes in order
            self.procs[node] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT,
                                                env=dict(os.environ), start_new_session=True)
        log.info("started %s (pid %d)", node, self.procs[node].pid)

    def check(self) -> None:
        for name, p in self.procs.items():
            if p.poll() is not None:
                tail = (self.logs_dir / f"{name}.log").read_text()[-2000:]
                raise RuntimeError(f"node {name} exited with {p.returncode}:\n{tail}")

    def stop(self, order=STOP_ORDER, timeout_s: float = 10.0) -> dict[str, int]:
        """SIGINT each node (`order` first, then any other), escalate after `timeout_s`;
        returns exit codes."""
        codes = {}
        for name in [*order, *(n for n in self.procs if n not in order)]:
            p = self.procs.get(name)
            if p is None:
                continue
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
                if p.poll() is not None:
                    break
                p.send_signal(sig)
                try:
                    p.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop on %s", name, signal.Signals(sig).name)
            codes[name] = p.returncode
        return codes

    def wait_started(self, timeout_s: float = 5.0) -> None:
        """Fail early if a node dies during start-up (bad parameters)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.check()
            time.sleep(0.1)
