"""Every topic and service of the rig, once: name, message type, QoS, publisher, meaning.

Pure data (no rclpy): nodes, the recorder's default topic list, tests and docs all read it.
`ros_nodes.nodes._common.qos_profile` turns a `Qos` into an rclpy `QoSProfile`.
Types are ROS 2 type names (`pkg/msg/Type`, `pkg/srv/Type`).
"""

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Qos:
    """A QoS profile as plain data (history is always keep-last)."""

    name: str
    depth: int
    reliable: bool = True
    latched: bool = False  # transient-local durability: late joiners get the last `depth`


# commands and set-points: reliable, a short queue
COMMAND = Qos("command", 10)
# latched: the sample layout, rig configuration, current targets (late joiners get the last one)
LATCHED = Qos("latched", 1, latched=True)
# measured streams (joint states, frames, poses): reliable publishers with a deep queue; live
# viewers may subscribe best-effort (`rclpy.qos.qos_profile_sensor_data`)
STREAM = Qos("stream", 100)
# a stream (a tick per simulated step, as fast as the devices follow): keep-last 10 let the
# reliable writer overwrite ticks not yet acknowledged on a busy machine (one tick lost in a
# recording under load); 1000 is a second of simulated time at the default 1 ms step
CLOCK_QOS = Qos("clock", 1000)
# the devices' joint states: the camera and the comparison rebuild the device motion from every
# sample, so the queues hold 5 s at 1 kHz; keep-last 100 lost 10 of 200 shaker samples in the
# simulated camera on a busy machine, which moved the specimen's true poses by up to 0.9 mm
# between two runs of the same command
JOINTS_QOS = Qos("joints", 5000)


@dataclass(frozen=True, slots=True)
class Topic:
    """One topic: full name, message type, QoS of its publisher, publishing node, meaning."""

    name: str
    type: str
    qos: Qos
    publisher: str
    description: str


@dataclass(frozen=True, slots=True)
class Service:
    """One service: full name, service type, serving node."""

    name: str
    type: str
    server: str


CLOCK = Topic("/clock", "rosgraph_msgs/msg/Clock", CLOCK_QOS, "sequencer",
              "simulated time (sim), frame stamps (replay with publish_clock)")
RIG_STOP = Topic("/rig/stop", "std_msgs/msg/Empty", COMMAND, "sequencer",
                 "anyone: shaker and stage stop")
RIG_PHASE = Topic("/rig/phase", "std_msgs/msg/String", LATCHED, "sequencer",
                  "current experiment phase")
RIG_DESIGN = Topic("/rig/design", "std_msgs/msg/String", LATCHED, "camera",
                   "design JSON with polygons_m")
RIG_CONFIG = Topic("/rig/config", "std_msgs/msg/String", LATCHED, "sequencer",
                   "plan + resolved parameters (JSON)")
SHAKER_COMMAND = Topic("/shaker/command", "trajectory_msgs/msg/JointTrajectory", LATCHED,
                       "shaker", "commanded waveform (joint shaker, m, absolute start stamp)")
SHAKER_JOINTS = Topic("/shaker/joint_states", "sensor_msgs/msg/JointState", JOINTS_QOS, "shaker",
                      "shaker position m, velocity m/s")
STAGE_JOINTS = Topic("/stage/joint_states", "sensor_msgs/msg/JointState", JOINTS_QOS, "stage",
                     "stage_bottom, stage_top: travel toward the centre, m")
STAGE_TARGET = Topic("/stage/target_strain", "std_msgs/msg/Float64", LATCHED, "stage",
                     "current target strain, 1")
STAGE_STATE = Topic("/stage/state", "std_msgs/msg/String", LATCHED, "stage",
                    "idle/moving/holding/fault: why")
IMAGE = Topic("/camera/image_raw", "sensor_msgs/msg/Image", STREAM, "camera",
              "frames mono8/mono16 (publisher depth: camera queue_depth)")
REFERENCE_IMAGE = Topic("/camera/reference_image", "sensor_msgs/msg/Image", LATCHED, "camera",
                        "the sample unloaded, taken before the stages close (`/camera/snapshot`): "
                        "the tracker's reference, so that poses are from the unloaded design")
CAMERA_INFO = Topic("/camera/camera_info", "sensor_msgs/msg/CameraInfo", STREAM, "camera",
                    "K[0] = 1/m_per_px, same stamps as the frames")
GROUND_TRUTH = Topic("/camera/ground_truth", "metarig_msgs/msg/UnitPose2DArray", STREAM,
                     "camera", "sim: true unit poses in the sample frame (m, rad)")
CAMERA_STATUS = Topic("/camera/status", "std_msgs/msg/String", LATCHED, "camera",
                      "camera status JSON")
RECORDER_STATUS = Topic("/recorder/status", "std_msgs/msg/String", COMMAND, "recorder",
                        "recorder status JSON (counts, matched)")
RECORDER_REPORT = Topic("/recorder/report", "std_msgs/msg/String", LATCHED, "recorder",
                        "final recording report JSON")
DIAGNOSTICS = Topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", COMMAND,
                    "shaker, stage", "device diagnostics")
POSES = Topic("/dic/poses", "metarig_msgs/msg/UnitPose2DArray", STREAM, "dic_tracker",
              "tracked unit poses (live: decimated preview; in a run's MCAP: every frame, "
              "tracked after the capture)")
IMAGE_PREVIEW = Topic("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage", STREAM,
                      "recorder", "lossless PNG copies of the frames, written into the MCAP "
                      "only, so that Rerun shows them as images (it shows mono8 as depth)")
COMPARE_RESULT = Topic("/compare/result", "metarig_msgs/msg/ComparisonResult", LATCHED,
                       "comparison", "experiment against simulation: errors and energy series")
COMPARE_SUMMARY = Topic("/compare/summary", "std_msgs/msg/String", LATCHED, "comparison",
                        "the comparison's summary.json")
COMPARE_SIMULATED = Topic("/compare/simulated_poses", "metarig_msgs/msg/UnitPose2DArray",
                          STREAM, "comparison", "simulated unit poses at the frame times")

TOPICS: tuple[Topic, ...] = (
    CLOCK, RIG_STOP, RIG_PHASE, RIG_DESIGN, RIG_CONFIG, SHAKER_COMMAND, SHAKER_JOINTS,
    STAGE_JOINTS, STAGE_TARGET, STAGE_STATE, IMAGE, REFERENCE_IMAGE, CAMERA_INFO, GROUND_TRUTH,
    CAMERA_STATUS, RECORDER_STATUS, RECORDER_REPORT, DIAGNOSTICS, POSES, IMAGE_PREVIEW,
    COMPARE_RESULT, COMPARE_SUMMARY, COMPARE_SIMULATED)
BY_NAME: dict[str, Topic] = {t.name: t for t in TOPICS}

# what the recorder writes by default (status/report topics are bookkeeping, not data)
RECORDED: tuple[str, ...] = (
    CLOCK.name, RIG_STOP.name, RIG_PHASE.name, RIG_DESIGN.name, RIG_CONFIG.name,
    SHAKER_COMMAND.name, SHAKER_JOINTS.name, STAGE_JOINTS.name, STAGE_TARGET.name,
    STAGE_STATE.name, IMAGE.name, REFERENCE_IMAGE.name, CAMERA_INFO.name, GROUND_TRUTH.name,
    DIAGNOSTICS.name,
    POSES.name, COMPARE_RESULT.name, COMPARE_SUMMARY.name, COMPARE_SIMULATED.name)

# services
SHAKER_FIRE = Service("/shaker/fire", "metarig_msgs/srv/FirePulse", "shaker")
SHAKER_STOP = Service("/shaker/stop", "std_srvs/srv/Trigger", "shaker")
SHAKER_COMPENSATE = Service("/shaker/compensate", "metarig_msgs/srv/FirePulse",
                            "shaker")
STAGE_SET_STRAIN = Service("/stage/set_strain", "metarig_msgs/srv/SetStrain", "stage")
STAGE_STOP = Service("/stage/stop", "std_srvs/srv/Trigger", "stage")
STAGE_RESET = Service("/stage/reset", "std_srvs/srv/Trigger", "stage")
CAMERA_START = Service("/camera/start", "std_srvs/srv/Trigger", "camera")
CAMERA_STOP = Service("/camera/stop", "std_srvs/srv/Trigger", "camera")
CAMERA_SNAPSHOT = Service("/camera/snapshot", "std_srvs/srv/Trigger", "camera")
RECORDER_START = Service("/recorder/start", "std_srvs/srv/Trigger", "recorder")
RECORDER_STOP = Service("/recorder/stop", "std_srvs/srv/Trigger", "recorder")
DIC_RESET = Service("/dic_tracker/reset_reference", "std_srvs/srv/Trigger", "dic_tracker")
COMPARE_RUN = Service("/compare/run", "std_srvs/srv/Trigger", "comparison")

SERVICES: tuple[Service, ...] = (
    SHAKER_FIRE, SHAKER_STOP, SHAKER_COMPENSATE, STAGE_SET_STRAIN, STAGE_STOP, STAGE_RESET,
    CAMERA_START, CAMERA_STOP, CAMERA_SNAPSHOT, RECORDER_START, RECORDER_STOP, DIC_RESET,
    COMPARE_RUN)


def markdown_table() -> str:
    """The topic table of the docs (name, type, QoS, publisher, meaning)."""
    rows = ["| topic | type | QoS | from | meaning |", "|---|---|---|---|---|"]
    for t in TOPICS:
        rows.append(f"| `{t.name}` | `{t.type}` | {t.qos.name} | {t.publisher} | "
                    f"{t.description} |")
    return "\n".join(rows)
