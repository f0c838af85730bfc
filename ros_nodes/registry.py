"""The one list of the project's ROS nodes: name, console script, node class, config class.

Pure (no rclpy): classes are `"module:attr"` references resolved on demand, so the launcher, the
rig and the CLI can read the registry without importing ROS. `RIG` is what `metarig rig`
starts (in this order); `STOP_ORDER` is the order it stops them: the devices first, the
recorder last so that it still records them coming to rest.
"""

import importlib
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class NodeSpec:
    """One node: ROS node name, console script (`pyproject.toml`), node class, config class."""

    name: str
    script: str
    node_class: str  # "module:Class"
    config_class: str | None  # "module:Class" of its typed parameters (None: no parameters)
    entry_point: str = ""  # console-script target "module:func" ("": the node module's main)

    def __post_init__(self):
        if not self.entry_point:
            object.__setattr__(self, "entry_point", self.node_class.split(":")[0] + ":main")

    def node(self) -> type:
        """The rclpy node class (imports rclpy)."""
        return resolve(self.node_class)

    def config(self) -> type | None:
        """The frozen config dataclass of the node's parameters (pure)."""
        return None if self.config_class is None else resolve(self.config_class)


def resolve(ref: str):
    """`"package.module:attr"` -> the attribute."""
    module, _, attr = ref.partition(":")
    return getattr(importlib.import_module(module), attr)


_N = "ros_nodes.nodes."
_P = "ros_nodes.params:"
NODES: dict[str, NodeSpec] = {s.name: s for s in (
    NodeSpec("shaker", "metarig-shaker", _N + "shaker_node:ShakerNode", _P + "ShakerNodeConfig"),
    NodeSpec("stage", "metarig-stage", _N + "stage_node:StageNode", _P + "StageNodeConfig"),
    NodeSpec("camera", "metarig-camera", _N + "camera_node:CameraNode", _P + "CameraNodeConfig"),
    NodeSpec("recorder", "metarig-recorder", _N + "recorder_node:RecorderNode",
             _P + "RecorderNodeConfig"),
    # the sequencer alone runs the whole rig with one process per node
    NodeSpec("sequencer", "metarig-sequencer", _N + "sequencer_node:SequencerNode", None,
             "ros_nodes.cli_rig:sequencer_main"),
    NodeSpec("dic_tracker", "metarig-dic", _N + "dic_tracker_node:DICTrackerNode",
             "ros_nodes.dic_params:DICNodeConfig"),
    NodeSpec("comparison", "metarig-compare", _N + "compare_node:CompareNode",
             _P + "CompareNodeConfig"),
)}

# the device nodes `metarig rig` starts, in start order (the sequencer runs in its own process)
RIG: tuple[str, ...] = ("shaker", "stage", "camera", "recorder")
STOP_ORDER: tuple[str, ...] = ("shaker", "stage", "camera", "recorder")


def rig_nodes() -> list[NodeSpec]:
    """The specs of `RIG`, in start order."""
    return [NODES[n] for n in RIG]
