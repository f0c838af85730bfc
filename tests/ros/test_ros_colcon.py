"""The optional ament_python package builds with colcon and its node starts the `ros2 run` way.

colcon (colcon-core + colcon-ros, a dev dependency) builds `ament/metarig_ros` into a scratch
workspace; the executable is then found as `ros2 run` finds it (the ament index under
AMENT_PREFIX_PATH, then `<prefix>/lib/<package>/<name>`), started with the workspace's
site-packages first on the path (what `source install/setup.bash` does), and must come up as
a real shaker node that answers its fire service from the installed copy of the code.
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from rostools import call, stop_process

ROOT = Path(__file__).resolve().parents[2]
COLCON = Path(sys.prefix) / "bin" / "colcon"
PY = f"python{sys.version_info.major}.{sys.version_info.minor}"


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    if not COLCON.exists():
        pytest.skip("colcon is not installed (pip install -e '.[dev]')")
    ws = tmp_path_factory.mktemp("colcon_ws")
    (ws / "src").mkdir()
    (ws / "src" / "metarig_ros").symlink_to(ROOT / "ament" / "metarig_ros")
    r = subprocess.run([str(COLCON), "build"], cwd=ws,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return ws


def test_colcon_installs_the_package_into_the_ament_index(workspace):
    from ament_index_python.packages import get_package_prefix, get_package_share_directory

    os.environ["AMENT_PREFIX_PATH"] = str(workspace / "install" / "metarig_ros")
    try:
        prefix = Path(get_package_prefix("metarig_ros"))
        share = Path(get_package_share_directory("metarig_ros"))
    finally:
        del os.environ["AMENT_PREFIX_PATH"]
    assert (share / "package.xml").read_text() == (ROOT / "ament/metarig_ros/package.xml").read_text()
    scripts = sorted(p.name for p in (prefix / "lib" / "metarig_ros").iterdir())
    import tomllib

    with (ROOT / "pyproject.toml").open("rb") as f:
        assert scripts == sorted(tomllib.load(f)["project"]["scripts"])
    site = prefix / "lib" / PY / "site-packages"
    for pkg in ("design_engine", "hardware_sim", "ros_nodes", "metarig"):
        assert (site / pkg / "__init__.py").is_file(), pkg


def test_installed_shaker_node_runs_like_ros2_run(workspace, ros_node, start_node, ros_env):
    from metarig_msgs.srv import FirePulse

    prefix = workspace / "install" / "metarig_ros"
    exe = prefix / "lib" / "metarig_ros" / "metarig-shaker"
    assert os.access(exe, os.X_OK)
    env = dict(ros_env, AMENT_PREFIX_PATH=str(prefix),
               PYTHONPATH=os.pathsep.join([str(prefix / "lib" / PY / "site-packages"),
                                           ros_env.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    # the console script's interpreter line names the Python that ran colcon (here the venv's)
    probe = subprocess.run([str(exe.with_name("metarig")), "--help"], env=env, capture_output=True,
                           text=True, timeout=120)
    assert probe.returncode == 0 and "simulate" in probe.stdout, probe.stderr
    proc = start_node([exe], "-p", "device.max_amplitude_m:=0.008", "-p",
                      "allowed_callers:=[/test_client]", env=env)
    node, ex = ros_node
    try:
        fire = node.create_client(FirePulse, "/shaker/fire")
        r = call(fire, FirePulse.Request(waveform="pulse", amplitude_m=0.010, frequency_hz=30.0), ex)
        assert not r.accepted and "0.008" in r.message  # the parameter given on the command line
        out = stop_process(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    # the node ran the workspace's copy of the code, not the repository's
    check = subprocess.run([sys.executable, "-c", "import ros_nodes; print(ros_nodes.__file__)"],
                           env=env, cwd=workspace, capture_output=True, text=True, timeout=60)
    assert Path(check.stdout.strip()).is_relative_to(prefix), check.stdout
    shutil.rmtree(workspace / "build", ignore_errors=True)
