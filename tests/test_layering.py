"""Imports flow one way, ROS only at the edge, and no module imports itself round a circle.

Layers (a package may import only those before it):
    metarig base (trajectory, polygon, fields, argtypes: numpy only)
    <- design_engine (JAX)            <- hardware_sim <- ros_nodes
    <- tracking (DIC, no JAX, no simulator, no ROS)    <- ros_nodes
    design_engine, tracking <- comparison (experiment against simulation, no ROS) <- ros_nodes
    metarig base <- devices (lab device ports, vendor drivers: no ROS, simulator, JAX)
        <- hardware_sim (the simulated devices implement the ports) <- ros_nodes
`metarig.cli` / `metarig.__main__` dispatch to every package and are imported by none.
"""

import ast
import sys
from pathlib import Path

import pytest

from metarig.cli import SUBCOMMANDS

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("metarig", "design_engine", "tracking", "comparison", "hardware_sim", "devices",
            "ros_nodes")
ROS_ALLOWED = ("ros_nodes/nodes/", "ros_nodes/convert.py")
DISPATCH = ("metarig.cli", "metarig.__main__")
MAY_IMPORT = {  # package -> project packages it may import (besides itself)
    "metarig": set(),
    "design_engine": {"metarig"},
    "tracking": {"metarig"},
    "comparison": {"metarig", "design_engine", "tracking"},
    "hardware_sim": {"metarig", "design_engine", "devices"},
    "devices": {"metarig"},
    "ros_nodes": {"metarig", "design_engine", "tracking", "comparison", "hardware_sim",
                  "devices"},
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, names: bool = False) -> set[str]:
    """Every module named by an import anywhere in the file (functions included); with `names`,
    also `pkg.name` for each `from pkg import name` (which may be a submodule)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = _module_name(path).split(".")
    if path.name != "__init__.py":
        here = here[:-1]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = here[: len(here) - node.level + 1]
                base = ".".join(pkg + ([base] if base else []))
            if base:
                out.add(base)
                if names:
                    out.update(f"{base}.{a.name}" for a in node.names)
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


def _project_graph() -> dict[str, set[str]]:
    """Module -> project modules it imports (names resolved to existing modules)."""
    mods = {_module_name(f): f for pkg in PACKAGES for f in _files(pkg)}
    graph = {}
    for name, f in mods.items():
        graph[name] = {m for m in _imports(f, names=True) if m in mods and m != name}
    return graph


@pytest.mark.parametrize("pkg", PACKAGES)
def test_layering(pkg):
    bad = []
    for f in _files(pkg):
        rel = f.relative_to(ROOT).as_posix()
        mod = _module_name(f)
        for imp in _imports(f):
            top = imp.split(".")[0]
            if _is_ros(imp) and not rel.startswith(ROS_ALLOWED):
                bad.append(f"{rel}: imports {imp} (only {', '.join(ROS_ALLOWED)} may)")
            if mod in DISPATCH:
                continue
            if top in PACKAGES and top != pkg and top not in MAY_IMPORT[pkg]:
                bad.append(f"{rel}: {pkg} imports {imp}")
            if imp.startswith(DISPATCH):
                bad.append(f"{rel}: imports the command dispatcher {imp}")
            if pkg == "metarig" and top not in ("metarig", "numpy") and \
                    top not in sys.stdlib_module_names:
                bad.append(f"{rel}: the numpy-only base imports {imp}")
    assert not bad, "\n".join(bad)


# command modules: parse arguments, call the libraries, print; imported by the dispatcher only,
# which is the one place that knows every command
COMMANDS = tuple(sorted({module for module, _, _ in SUBCOMMANDS.values()}))
# modules that build or read ROS messages through `ros_nodes.convert` (which imports the message
# packages): the nodes, and the offline writer of a comparison's messages into a recording
CONVERT_USERS = ROS_ALLOWED + ("ros_nodes/recorded_compare.py",)


def _scanned() -> list[Path]:
    """Every module of the packages, and the benchmark scripts."""
    return [f for pkg in PACKAGES for f in _files(pkg)] + sorted((ROOT / "benchmarks").glob("*.py"))


# the design engine's rooms, in import order: a room imports only the rooms before it (and the
# package's own set-up); `commands/` is imported by the dispatcher only (above)
ROOMS = ("physics", "solve", "design", "sweeps", "calibration", "studies", "commands")


def test_the_engine_rooms_import_only_the_rooms_before_them():
    assert {p.name for p in (ROOT / "design_engine").iterdir()
            if p.is_dir() and (p / "__init__.py").exists()} == set(ROOMS)
    bad = []
    for f in _files("design_engine"):
        parts = f.relative_to(ROOT / "design_engine").parts
        if len(parts) < 2:
            continue
        room = parts[0]
        for imp in _imports(f):
            other = imp.split(".")[1] if imp.startswith("design_engine.") else None
            if other in ROOMS and ROOMS.index(other) > ROOMS.index(room):
                bad.append(f"design_engine/{'/'.join(parts)} ({room}) imports {imp}")
    assert not bad, "\n".join(bad)


def test_commands_are_leaves_and_logic_is_pure():
    """No module (benchmarks included) imports a command module but the dispatcher; a module
    that imports `ros_nodes.convert` imports ROS: only the nodes (and the offline comparison
    writer) may, so `ros_nodes/logic/` stays free of ROS even at one remove."""
    assert all((ROOT / (c.replace(".", "/") + ".py")).exists() for c in COMMANDS)
    rooms = {_module_name(f) for f in ROOT.glob("*/commands/*.py") if f.name != "__init__.py"}
    assert rooms <= set(COMMANDS), f"not commands, in a commands folder: {rooms - set(COMMANDS)}"
    bad = []
    for f in _scanned():
        rel, mod = f.relative_to(ROOT).as_posix(), _module_name(f)
        imports = _imports(f, names=True)
        if mod not in DISPATCH:
            bad += [f"{rel}: imports the command module {c}" for c in COMMANDS
                    if c in imports and c != mod]
        if "ros_nodes.convert" in imports and not rel.startswith(CONVERT_USERS):
            bad.append(f"{rel}: imports ros_nodes.convert (ROS messages)")
        if rel.startswith("benchmarks/"):
            bad += [f"{rel}: imports {i}" for i in imports if _is_ros(i)]
    assert not bad, "\n".join(bad)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_no_import_circles():
    # Importing a package itself (`import design_engine` for its set-up, or a re-export from
    # its `__init__`) is not counted: a circle is between modules.
    graph = {m: {d for d in deps if d not in PACKAGES} for m, deps in _project_graph().items()}
    circles = _cycles(graph)
    assert not circles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in circles)


def test_the_walker_sees_ros_imports_and_circles():
    assert _is_ros("rclpy.node") and _is_ros("sensor_msgs.msg") and _is_ros("metarig_msgs.msg")
    assert _is_ros("std_srvs.srv") and not _is_ros("numpy")
    assert "rclpy" in _imports(ROOT / "ros_nodes/nodes/_common.py")
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
