"""ament_python shim: builds the repository's Python packages as the ROS 2 package `metarig_ros`.

Optional; used only by colcon (see ../README.md). The pip route is the root `pyproject.toml`, which
stays the single source of truth: the version check and the console scripts are read from it, so
`ros2 run metarig_ros <script>` offers exactly the scripts that `pip install -e .` installs.
"""

import os
import tomllib
from pathlib import Path

PACKAGE = "metarig_ros"
HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]  # the repository root, where pyproject.toml and the packages live
PYPROJECT = ROOT / "pyproject.toml"


def pyproject() -> dict:
    with PYPROJECT.open("rb") as f:
        return tomllib.load(f)


def console_scripts() -> list[str]:
    """`name = module:func` for every entry of pyproject's [project.scripts], in its order."""
    return [f"{name} = {target}" for name, target in pyproject()["project"]["scripts"].items()]


def package_includes() -> list[str]:
    """The package patterns of pyproject's [tool.setuptools.packages.find]."""
    return pyproject()["tool"]["setuptools"]["packages"]["find"]["include"]


def main() -> None:
    from setuptools import find_packages, setup

    # setuptools wants `package_dir` relative to the current directory; colcon runs this from the
    # package folder, but make it hold however the script is started (and through symlinks).
    os.chdir(HERE)
    project = pyproject()["project"]
    setup(
        name=PACKAGE,
        version=project["version"],
        description=project["description"],
        license="MIT",
        maintainer="metarig",
        maintainer_email="metarig@example.invalid",
        package_dir={"": "../.."},
        packages=find_packages("../..", include=package_includes()),
        # build.py reads these next to itself (not needed at run time)
        package_data={"ros_nodes.interfaces": ["msg/*.msg", "srv/*.srv"]},
        data_files=[
            ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
            (f"share/{PACKAGE}", ["package.xml"]),
        ],
        # Python dependencies come from pip (root pyproject.toml), not from this shim
        install_requires=["setuptools"],
        zip_safe=False,
        entry_points={"console_scripts": console_scripts()},
    )


if __name__ == "__main__":
    main()
