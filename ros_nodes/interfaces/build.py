"""Build the `metarig_msgs` interface package into the current Python environment, without colcon.

Run by the project's install step (`make install`) as `python -m ros_nodes.interfaces.build`.
It is idempotent: a hash of the interface files and of this script is stored next to the
installed package, and a second run with nothing changed only checks that the package imports.

Steps (the facts behind them are in the project's `ros-interfaces.md`):
1. generate C, Python and the three C type supports from the `.msg`/`.srv` files with the rosidl
   generators of the PyPI ROS wheels (entry points loaded non-strictly: the wheels register them
   twice);
2. compile five shared libraries and three Python extension modules with gcc/g++;
3. install the libraries into `<prefix>/lib` (already on the ROS wheels' `LD_LIBRARY_PATH`), the
   Python package into site-packages and the interface files into `<prefix>/share/metarig_msgs`
   (the MCAP writer reads message definitions from there).
"""

import argparse
import hashlib
import logging
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

PACKAGE = "metarig_msgs"
HERE = Path(__file__).resolve().parent
PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
              "int32", "uint32", "int64", "uint64", "string", "wstring"}
# Every service also carries a generated `_Event` message that uses these packages.
SERVICE_DEPS = ("builtin_interfaces", "service_msgs")

log = logging.getLogger("metarig_msgs.build")


class BuildError(RuntimeError):
    """The interface package could not be generated or compiled."""


def interface_files() -> list[Path]:
    """The `.msg` and `.srv` files of the package, sorted."""
    return sorted(HERE.glob("msg/*.msg")) + sorted(HERE.glob("srv/*.srv"))


def dependencies(files: list[Path]) -> list[str]:
    """Message packages the interfaces refer to (`pkg/Type` fields), plus the service deps."""
    deps: set[str] = set()
    for f in files:
        for line in f.read_text().splitlines():
            line = line.split("#", 1)[0].strip()
            if not line or line == "---":
                continue
            ftype = re.sub(r"\[.*\]$", "", line.split()[0])
            if "/" in ftype:
                deps.add(ftype.split("/")[0])
            elif ftype not in PRIMITIVES and ftype not in ("Header", "time", "duration"):
                raise BuildError(f"{f.name}: type {ftype!r} must be written pkg/Type")
        if f.suffix == ".srv":
            deps.update(SERVICE_DEPS)
    deps.discard(PACKAGE)
    return sorted(deps)


def source_hash(files: list[Path]) -> str:
    h = hashlib.sha256(Path(__file__).read_bytes())
    for f in files:
        h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()[:16]


def _site_packages() -> Path:
    return Path(sysconfig.get_paths()["purelib"])


def _generate(files: list[Path], gen: Path, prefix: Path) -> None:
    os.environ.setdefault("AMENT_PREFIX_PATH", str(prefix))
    from rosidl_cli.command.generate.extensions import (load_type_extensions,
                                                        load_typesupport_extensions)

    logging.getLogger("rosidl_cli").setLevel(logging.ERROR)  # the duplicate entry point warnings
    rel = [f"{HERE}:{f.relative_to(HERE)}" for f in files]
    include = [str(prefix / "share")]
    wanted = [("type", load_type_extensions, ["c", "py"]),
              ("ts", load_typesupport_extensions, ["c", "introspection_c", "fastrtps_c"])]
    for tag, loader, specs in wanted:
        exts = loader(specs=specs, strict=False)
        if sorted(e.name for e in exts) != sorted(specs):
            raise BuildError(f"rosidl {tag} generators missing: want {specs}, "
                             f"found {[e.name for e in exts]}")
        for ext in exts:
            # `<kind>/metarig_msgs/msg/...` so that `#include "metarig_msgs/msg/..."` resolves
            ext.generate(PACKAGE, rel, include, output_path=gen / f"{tag}_{ext.name}" / PACKAGE)


def _run(cmd: list[str]) -> None:
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise BuildError(f"compiler failed:\n{' '.join(cmd)}\n{r.stderr[-4000:]}")


def _compile(gen: Path, out: Path, prefix: Path, deps: list[str]) -> None:
    """Compile the five libraries (in dependency order) and the three extension modules."""
    site = _site_packages()
    lib_dirs = [prefix / "lib", out] + sorted(site.glob("ros_*.libs"))
    inc = [gen / k for k in ("type_c", "type_py", "ts_c", "ts_introspection_c", "ts_fastrtps_c")]
    inc += [prefix / "include"] + sorted(p for p in (prefix / "include").iterdir() if p.is_dir())
    inc += [Path(sysconfig.get_paths()["include"])]
    import numpy

    inc.append(Path(numpy.get_include()))
    common = ["-fPIC", "-shared", "-O2", "-w"] + [f"-I{p}" for p in inc] + [f"-L{p}" for p in lib_dirs]
    rpath = ["-Wl,-rpath,$ORIGIN"]

    def dep_libs(suffix: str) -> list[str]:
        return [f"-l{d}__{suffix}" for d in deps]

    def lib(name: str) -> Path:
        return out / f"lib{PACKAGE}__{name}.so"

    pkg = gen / "type_c" / PACKAGE
    base = ["-lrosidl_runtime_c", "-lrcutils"]
    steps = [
        ("rosidl_generator_c", ["gcc"], sorted(pkg.glob("*/detail/*__functions.c"))
         + sorted(pkg.glob("*/detail/*__description.c"))
         # services: the event-message helpers of the C type support live here too
         + sorted(pkg.glob("*/detail/*__type_support.c")),
         dep_libs("rosidl_generator_c") + ["-lrosidl_typesupport_c"] + base),
        ("rosidl_typesupport_introspection_c", ["gcc"],
         sorted((gen / "ts_introspection_c" / PACKAGE).glob("*/detail/*__type_support.c")),
         [f"-l{PACKAGE}__rosidl_generator_c", "-lrosidl_typesupport_introspection_c"]
         + dep_libs("rosidl_typesupport_introspection_c") + dep_libs("rosidl_generator_c") + base),
        ("rosidl_typesupport_fastrtps_c", ["g++", "-std=c++17"],
         sorted((gen / "ts_fastrtps_c" / PACKAGE).glob("*/detail/*__type_support_c.cpp")),
         [f"-l{PACKAGE}__rosidl_generator_c", "-lrosidl_typesupport_fastrtps_c",
          "-lrosidl_typesupport_fastrtps_cpp", "-lfastcdr", "-lrmw"]
         + dep_libs("rosidl_typesupport_fastrtps_c") + dep_libs("rosidl_generator_c") + base),
        ("rosidl_typesupport_c", ["g++", "-std=c++17"],
         sorted((gen / "ts_c" / PACKAGE).glob("*/*__type_support.cpp")),
         [f"-l{PACKAGE}__rosidl_generator_c", "-lrosidl_typesupport_c"]
         + dep_libs("rosidl_typesupport_c") + dep_libs("rosidl_generator_c") + base),
        ("rosidl_generator_py", ["gcc"], sorted((gen / "type_py" / PACKAGE).glob("*/_*_s.c")),
         [f"-l{PACKAGE}__rosidl_generator_c", f"-l{PACKAGE}__rosidl_typesupport_c"]
         + dep_libs("rosidl_generator_py") + dep_libs("rosidl_generator_c")
         + dep_libs("rosidl_typesupport_c") + base),
    ]
    for name, cc, srcs, libs in steps:
        if not srcs:
            raise BuildError(f"no generated sources for {name}")
        _run(cc + common + rpath + [str(s) for s in srcs] + ["-o", str(lib(name))] + libs)

    ext = sysconfig.get_config_var("EXT_SUFFIX")
    pydir = out / PACKAGE
    shutil.copytree(gen / "type_py" / PACKAGE, pydir,
                    ignore=shutil.ignore_patterns("*.c", "tmp", "*.idl"))
    (pydir / "__init__.py").write_text("")

    def ext_module(ts: str) -> None:
        src = gen / "type_py" / PACKAGE / f"_{PACKAGE}_s.ep.rosidl_typesupport_{ts}.c"
        _run(["gcc"] + common + ["-Wl,-rpath,$ORIGIN/.."] + [str(src)]
             + ["-o", str(pydir / f"{PACKAGE}_s__rosidl_typesupport_{ts}{ext}")]
             + [f"-l{PACKAGE}__rosidl_generator_py", f"-l{PACKAGE}__rosidl_typesupport_{ts}",
                f"-l{PACKAGE}__rosidl_generator_c", "-lrosidl_runtime_c", "-lrcutils"])

    with ThreadPoolExecutor(3) as pool:
        list(pool.map(ext_module, ["c", "fastrtps_c", "introspection_c"]))


def _package_xml(deps: list[str]) -> str:
    dep_lines = "\n".join(f"  <depend>{d}</depend>" for d in deps)
    return f"""<?xml version="1.0"?>
<package format="3">
  <name>{PACKAGE}</name>
  <version>0.1.0</version>
  <description>Interfaces of the metarig lab rig (built by ros_nodes.interfaces.build)</description>
  <maintainer email="metarig@example.invalid">metarig</maintainer>
  <license>MIT</license>
{dep_lines}
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export><build_type>ament_cmake</build_type></export>
</package>
"""


def _install(out: Path, prefix: Path, files: list[Path], deps: list[str], digest: str) -> None:
    site = _site_packages()
    for so in out.glob(f"lib{PACKAGE}__*.so"):
        shutil.copy2(so, prefix / "lib" / so.name)
    dest = site / PACKAGE
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(out / PACKAGE, dest)
    share = prefix / "share" / PACKAGE
    if share.exists():
        shutil.rmtree(share)
    for f in files:
        (share / f.parent.name).mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, share / f.parent.name / f.name)
    (share / "package.xml").write_text(_package_xml(deps))
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text("")
    (share / ".build-hash").write_text(digest)


def _check_import(prefix: Path) -> str | None:
    """Import the installed package in a fresh interpreter; None on success, else the error."""
    code = (f"from {PACKAGE}.msg import UnitPose2DArray; from rclpy.serialization import "
            "serialize_message as s; s(UnitPose2DArray())")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    return None if r.returncode == 0 else (r.stderr.strip().splitlines() or ["?"])[-1]


def build(force: bool = False, keep: Path | None = None) -> Path:
    """Generate, compile and install the package; returns the installed Python package dir."""
    prefix = Path(sys.prefix)
    files = interface_files()
    deps = dependencies(files)
    digest = source_hash(files)
    stamp = prefix / "share" / PACKAGE / ".build-hash"
    dest = _site_packages() / PACKAGE
    if not force and stamp.exists() and stamp.read_text() == digest and _check_import(prefix) is None:
        log.info("%s is up to date (%s)", PACKAGE, digest)
        return dest
    work = Path(tempfile.mkdtemp(prefix=f"{PACKAGE}-")) if keep is None else keep
    try:
        gen, out = work / "gen", work / "out"
        out.mkdir(parents=True, exist_ok=True)
        log.info("generating %s from %d interface files (deps: %s)", PACKAGE, len(files),
                 ", ".join(deps))
        _generate(files, gen, prefix)
        log.info("compiling")
        _compile(gen, out, prefix, deps)
        _install(out, prefix, files, deps, digest)
    finally:
        if keep is None:
            shutil.rmtree(work, ignore_errors=True)
    err = _check_import(prefix)
    if err is not None:
        raise BuildError(f"{PACKAGE} was built but does not import: {err}")
    log.info("installed %s into %s", PACKAGE, dest)
    return dest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--force", action="store_true", help="rebuild even if up to date")
    parser.add_argument("--keep", type=Path, default=None,
                        help="build in this folder and keep the generated sources")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    try:
        build(force=args.force, keep=args.keep)
    except BuildError as e:
        log.error("%s", e)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
