"""`metarig rig` body: start the nodes (in process or as processes), run the sequence, clean up.

Whatever happens (success, refusal, timeout, Ctrl-C, SIGTERM), the devices are stopped and the
recorder finishes its file before the nodes go down, and `run.json` says how the run ended.
"""

import json
import logging
import threading
import time
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor

from metarig.signals import deferred_stop, stop_on_signals
from ros_nodes.launcher import ProcessGroup, command_line
from ros_nodes.logic.experiment import Experiment, RigError
from ros_nodes.logic.sequence import DESIGN_NAME, summary, write_summary
from ros_nodes.nodes._common import local_discovery_by_default
from ros_nodes.nodes._launch import InProcessRig
from ros_nodes.nodes.sequencer_node import SequencerNode

log = logging.getLogger("metarig.rig")


def run_rig(plan, node_params: dict[str, dict], out: Path, processes: bool = False,
            lab: dict | None = None) -> int:
    """Run `plan` on the nodes of `node_params` (name -> parameters); writes `out`/run.json.

    lab: None for the simulated rig (simulated clock); for lab devices on the system clock,
        `{"lab_file": path, "design_json": the sample's nominal design, "ros": the ROS
        environment applied}` (the sequencer publishes the design; run.json keeps `lab_file`
        and `ros`).
    Returns the exit code: 0 completed, 130 interrupted (Ctrl-C/SIGTERM), 1 failed.
    """
    wall0 = time.monotonic()
    stop_on_signals()
    config = {"plan": plan.as_dict(), "node_parameters": node_params}
    clock = "simulated" if lab is None else "system"
    seq_kw = {} if lab is None else {"simulated_clock": False,
                                     "design_json": lab["design_json"]}
    if lab is not None:
        config["lab_file"] = str(lab["lab_file"])
    group, rig, ctx, ex, seq, exp = None, None, None, None, None, None
    status, report, timings, code = "failed", None, {}, 1
    try:
        local_discovery_by_default()  # the node processes inherit it too
        if processes:
            group = ProcessGroup(out / "logs")
            for name, params in node_params.items():
                group.start(name, command_line(name, params))
            with deferred_stop():  # a Ctrl-C now is acted on once everything exists
                ctx = Context()
                rclpy.init(context=ctx)
                seq = SequencerNode(plan, config, context=ctx, parameter_overrides=[
                    rclpy.parameter.Parameter("use_sim_time", value=False)], **seq_kw)
                exp = Experiment(plan, seq)
                ex = MultiThreadedExecutor(num_threads=2, context=ctx)
                ex.add_node(seq)
                threading.Thread(target=ex.spin, daemon=True).start()
            group.wait_started(2.0)
        else:
            with deferred_stop():
                rig = InProcessRig(node_params)
                seq = SequencerNode(plan, config, context=rig.context, **seq_kw)
                exp = Experiment(plan, seq)
                rig.add(seq)
                rig.start()
        timings = exp.run()
        status, code = "completed", 0
    except KeyboardInterrupt:
        log.warning("interrupted: stopping the rig and finishing the recording")
        status, code = "interrupted", 130
    except (RigError, RuntimeError) as e:
        log.error("%s", e)
        status = f"failed: {e}"
    finally:
        try:
            if exp is not None:
                report = exp.finish(completed=code == 0)
                design = seq.design()
                if design is not None:
                    (out / DESIGN_NAME).write_text(json.dumps(design))
        except KeyboardInterrupt:
            log.warning("second interrupt: skipping the orderly stop")
        finally:
            if group is not None:
                group.stop()
            if seq is not None:
                seq.close()
            if rig is not None:
                rig.shutdown()
            if ex is not None:
                ex.shutdown(timeout_sec=2.0)
                seq.destroy_node()
            if ctx is not None:
                rclpy.try_shutdown(context=ctx)
    timings["total_wall"] = time.monotonic() - wall0
    data = summary(plan, node_params, report, timings, exp.events if exp else [], status, clock)
    if lab is not None:
        data["lab_file"], data["ros"] = str(lab["lab_file"]), lab.get("ros", {})
    if exp is not None and exp.compensation:
        data["compensation"] = exp.compensation
    path = write_summary(out, data)
    if report is not None:
        lost = report.get("dropped", 0)
        log.info("%s in %.1f s: %d messages recorded, %d dropped -> %s", status,
                 timings["total_wall"], report.get("messages", 0), lost, report.get("path"))
        frames = data.get("frames")
        if frames and frames["lost"]:
            log.warning("%d of %d camera frames are missing from the recording",
                        frames["lost"], frames["published"])
        if frames and frames.get("lost_at_camera"):
            log.warning("the camera lost %d frames before publishing (its frame counter jumped)",
                        frames["lost_at_camera"])
        if frames and frames.get("expected", frames["published"]) != frames["published"]:
            log.warning("the camera published %d frames where the plan's capture window holds %d "
                        "(a clock that lagged at its start or stop; run.json keeps both)",
                        frames["published"], frames["expected"])
    else:
        log.warning("%s: no recording report (see %s)", status, path)
        if code == 0:
            code = 1
    return code
