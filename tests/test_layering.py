"""Imports flow one way: design_engine <- hardware_sim <- ros_nodes; ROS only at the edge."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROS_ALLOWED = ("ros_nodes/nodes/", "ros_nodes/convert.py")


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "import_module":
            if node.args and isinstance(node.args[0], ast.Constant):
                out.add(str(node.args[0].value))
    return out


def _is_ros(mod: str) -> bool:
    top = mod.split(".")[0]
    return top in ("rclpy", "rosidl_runtime_py", "rosgraph_msgs", "builtin_interfaces",
                   "rcl_interfaces", "lifecycle_msgs") or top.endswith(("_msgs", "_srvs"))


def _files(pkg: str) -> list[Path]:
    return sorted((ROOT / pkg).rglob("*.py"))


@pytest.mark.parametrize("pkg", ["design_engine", "hardware_sim", "ros_nodes"])
def test_layering(pkg):
    bad = []
    for f in _files(pkg):
        rel = f.relative_to(ROOT).as_posix()
        for mod in _imports(f):
            top = mod.split(".")[0]
            if _is_ros(mod) and not rel.startswith(ROS_ALLOWED):
                bad.append(f"{rel}: imports {mod} (only {', '.join(ROS_ALLOWED)} may)")
            if pkg == "design_engine" and top in ("hardware_sim", "ros_nodes"):
                bad.append(f"{rel}: design_engine imports {mod}")
            if pkg == "hardware_sim" and top == "ros_nodes":
                bad.append(f"{rel}: hardware_sim imports {mod}")
    assert not bad, "\n".join(bad)


def test_the_walker_sees_ros_imports():
    assert _is_ros("rclpy.node") and _is_ros("sensor_msgs.msg") and _is_ros("metarig_msgs.msg")
    assert _is_ros("std_srvs.srv") and not _is_ros("numpy")
    assert "rclpy" in _imports(ROOT / "ros_nodes/nodes/_common.py")
