"""The optional colcon/ament_python packaging in ament/metarig_ros stays in step with the pip route.

No ROS or colcon needed: package.xml is parsed with xml.etree (and catkin_pkg, a project
dependency, when importable), the shim's console scripts are compared with pyproject.toml's
[project.scripts], and setuptools runs the shim's egg_info step into a temporary folder.
"""

import importlib.util
import re
import subprocess
import sys
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "ament" / "metarig_ros"
SHIM = PKG / "setup.py"
SOURCE_DIRS = ("ros_nodes", "hardware_sim", "devices", "metarig", "design_engine", "tracking",
               "comparison")
# ROS interface packages by naming convention: foo_msgs, foo_srvs, foo_interfaces
ROS_IMPORT = re.compile(r"^\s*(?:from|import)\s+([a-z][a-z0-9_]*_(?:msgs|srvs|interfaces))\b",
                        re.MULTILINE)


def _pyproject() -> dict:
    with (ROOT / "pyproject.toml").open("rb") as f:
        return tomllib.load(f)


def _package_xml() -> ET.Element:
    return ET.parse(PKG / "package.xml").getroot()


def _imported_interface_packages() -> set[str]:
    found: set[str] = set()
    for d in SOURCE_DIRS:
        for py in (ROOT / d).rglob("*.py"):
            found.update(ROS_IMPORT.findall(py.read_text()))
    return found


def _load_shim():
    spec = importlib.util.spec_from_file_location("metarig_ros_setup_shim", SHIM)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # setup() only runs under __main__
    return module


def test_package_xml_format3_ament_python():
    root = _package_xml()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "metarig_ros"
    assert root.findtext("version") == _pyproject()["project"]["version"]
    assert root.findtext("description", "").strip()
    assert root.find("maintainer") is not None and root.find("maintainer").get("email")
    assert root.findtext("license", "").strip()
    assert root.findtext("export/build_type") == "ament_python"


def test_package_xml_valid_for_catkin_pkg():
    package = pytest.importorskip("catkin_pkg.package")
    parsed = package.parse_package_string((PKG / "package.xml").read_text())
    parsed.validate()
    assert parsed.name == "metarig_ros" and parsed.package_format == 3
    assert parsed.get_build_type() == "ament_python"


def test_exec_depends_cover_imported_ros_packages():
    deps = {e.text.strip() for e in _package_xml().findall("exec_depend")}
    deps |= {e.text.strip() for e in _package_xml().findall("depend")}
    imported = _imported_interface_packages()
    # sanity: the regex does see the node modules' imports
    assert {"std_msgs", "std_srvs", "sensor_msgs", "metarig_msgs"} <= imported
    assert {"rclpy", "metarig_msgs"} <= deps
    missing = imported - deps
    assert not missing, f"package.xml lacks exec_depend for {sorted(missing)}"
    uses_lifecycle = any("rclpy.lifecycle" in p.read_text()
                         for p in (ROOT / "ros_nodes").rglob("*.py"))
    if uses_lifecycle:
        assert "lifecycle_msgs" in deps


def test_resource_marker_and_setup_cfg():
    marker = PKG / "resource" / "metarig_ros"
    assert marker.is_file()
    cfg = (PKG / "setup.cfg").read_text()
    for section, key in (("develop", "script_dir"), ("install", "install_scripts")):
        pattern = rf"^\[{section}\]\s*\n{key}\s*=\s*\$base/lib/metarig_ros\s*$"
        assert re.search(pattern, cfg, re.MULTILINE), (section, key)


def test_no_root_setup_files():
    # pip/setuptools must keep seeing only pyproject.toml at the root
    for name in ("setup.py", "setup.cfg", "package.xml"):
        assert not (ROOT / name).exists(), name


def test_shim_console_scripts_match_pyproject():
    expected = [f"{k} = {v}" for k, v in _pyproject()["project"]["scripts"].items()]
    assert expected, "pyproject.toml has no [project.scripts]"
    assert _load_shim().console_scripts() == expected


def test_shim_egg_info(tmp_path):
    """What colcon would install: name, entry points and packages, via setuptools itself."""
    r = subprocess.run([sys.executable, str(SHIM), "--name"], check=False, capture_output=True,
                       text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "metarig_ros"
    r = subprocess.run([sys.executable, str(SHIM), "-q", "egg_info", "--egg-base", str(tmp_path)],
                       check=False, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 0, r.stderr
    info = tmp_path / "metarig_ros.egg-info"
    lines = (info / "entry_points.txt").read_text().splitlines()
    start = lines.index("[console_scripts]") + 1
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("[")), len(lines))
    scripts = dict(tuple(s.strip() for s in ln.split("=", 1)) for ln in lines[start:end] if ln)
    assert scripts == _pyproject()["project"]["scripts"]
    top = set((info / "top_level.txt").read_text().split())
    assert top == set(SOURCE_DIRS)
