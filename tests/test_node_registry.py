"""One node registry and one topic table (pure): in step with pyproject, the launcher, the
recorder defaults; no import cycle between the rig CLI and the nodes."""

import ast
import tomllib
from pathlib import Path

from ros_nodes import launcher, topics
from ros_nodes.registry import NODES, RIG, STOP_ORDER

ROOT = Path(__file__).resolve().parents[1]


def test_every_node_is_a_console_script_of_pyproject():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    for spec in NODES.values():
        assert scripts[spec.script] == spec.entry_point, spec.name


def test_the_launcher_starts_and_stops_the_registry_nodes():
    assert set(STOP_ORDER) == set(RIG) and STOP_ORDER[-1] == "recorder"
    for name in RIG:
        argv = launcher.command_line(name, {"seed": 3, "topics": ("/a", "/b")})
        assert argv[0].endswith("/" + NODES[name].script)
        assert argv[1:] == ["--ros-args", "-p", "seed:=3", "-p", "topics:=[\"/a\",\"/b\"]"]


def test_topics_are_listed_once_with_a_type_and_qos():
    names = [t.name for t in topics.TOPICS]
    assert len(names) == len(set(names))
    for t in topics.TOPICS:
        pkg, kind, typ = t.type.split("/")
        assert kind == "msg" and pkg and typ and t.qos.depth >= 1
    assert all(s.type.split("/")[1] == "srv" for s in topics.SERVICES)
    assert set(topics.RECORDED) <= set(topics.BY_NAME)
    assert "| `/camera/image_raw` | `sensor_msgs/msg/Image` | stream |" in topics.markdown_table()


def _imports(path: Path) -> set[str]:
    """Modules imported anywhere in a file (module level and inside functions)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_no_import_cycle_between_the_rig_cli_and_the_nodes():
    for f in (ROOT / "ros_nodes" / "nodes").glob("*.py"):
        assert "ros_nodes.cli_rig" not in _imports(f), f.name
    assert "ros_nodes.nodes.sequencer_node" not in _imports(ROOT / "ros_nodes" / "cli_rig.py")
    # the procedure itself needs no ROS
    assert not any(m.startswith(("rclpy", "ros_nodes.nodes"))
                   for m in _imports(ROOT / "ros_nodes" / "logic" / "experiment.py"))
