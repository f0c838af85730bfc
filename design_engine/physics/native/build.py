"""Build and register the native bond force (`bond_force.cc`) and the native Verlet stages
(`verlet_stages.cc`, both on `bond_kernels.h`) as XLA CPU custom calls.

The sources are compiled once per machine by the C++ compiler (`$CXX`, default `g++`) against
the XLA FFI headers that jaxlib ships, into `$METARIG_NATIVE_CACHE` (default
`~/.cache/metarig/native`), keyed by the source, the flags, the compiler, jax's version and the
CPU (the code is built for the CPU it runs on, `-march=native`). Where there is no compiler, or
`METARIG_NATIVE=0`, `library()` says why in one line and the engine keeps the JAX force.
"""

import ctypes
import fcntl
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

log = logging.getLogger(__name__)

HERE = Path(__file__).parent
SOURCES = (HERE / "bond_force.cc", HERE / "verlet_stages.cc")
HEADERS = (HERE / "bond_kernels.h",)
FLAGS = ("-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-fno-math-errno",
         "-fno-trapping-math")
# custom-call target name -> symbol of its handler in the library
TARGETS = {
    "metarig_bond_force_f64": "MetarigBondForceF64",
    "metarig_bond_force_f32": "MetarigBondForceF32",
    "metarig_bond_force_vjp_f64": "MetarigBondForceVjpF64",
    "metarig_bond_force_vjp_f32": "MetarigBondForceVjpF32",
    "metarig_contact_force_f64": "MetarigContactForceF64",
    "metarig_contact_force_f32": "MetarigContactForceF32",
    "metarig_contact_force_vjp_f64": "MetarigContactForceVjpF64",
    "metarig_contact_force_vjp_f32": "MetarigContactForceVjpF32",
    "metarig_verlet_stages_f64": "MetarigVerletStagesF64",
    "metarig_verlet_stages_f32": "MetarigVerletStagesF32",
    "metarig_verlet_stages_vjp_f64": "MetarigVerletStagesVjpF64",
    "metarig_verlet_stages_vjp_f32": "MetarigVerletStagesVjpF32",
}

_lock = threading.Lock()
_state: dict = {}  # "library" (CDLL) or "reason" (why there is none), set once per process


class NativeUnavailable(RuntimeError):
    """The native force cannot be used here; the message says why (one line)."""


def cache_dir() -> Path:
    return Path(os.environ.get("METARIG_NATIVE_CACHE",
                               os.path.expanduser("~/.cache/metarig/native")))


def _cpu() -> str:
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor()
    lines = [ln for ln in info.splitlines() if ln.startswith(("model name", "flags"))]
    return "\n".join(sorted(set(lines)))


def _compiler() -> str:
    return os.environ.get("CXX", "g++")


def _key(compiler_version: str) -> str:
    import jax

    h = hashlib.sha256()
    for part in (*(p.read_bytes() for p in SOURCES + HEADERS), " ".join(FLAGS).encode(), compiler_version.encode(),
                 jax.__version__.encode(), _cpu().encode()):
        h.update(part)
        h.update(b"\0")
    return h.hexdigest()[:20]


def _build() -> Path:
    cxx = _compiler()
    if shutil.which(cxx) is None:
        raise NativeUnavailable(f"no C++ compiler ({cxx}) on this machine")
    try:
        version = subprocess.run([cxx, "--version"], capture_output=True, text=True,
                                 timeout=60).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        raise NativeUnavailable(f"the C++ compiler {cxx} does not run: {exc}") from None
    out = cache_dir() / f"bond_force-{_key(version)}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    # one process builds while the others (test workers) wait for its library
    with open(out.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if out.exists():
            return out
        return _compile(cxx, out)


def _compile(cxx: str, out: Path) -> Path:
    import jax

    # built beside its final name and moved there in one step, so that processes building at
    # once (test workers) never load a half-written library
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [cxx, *FLAGS, f"-I{jax.ffi.include_dir()}", *map(str, SOURCES), "-o", tmp]
    log.info("building the native bond force: %s", " ".join(cmd))
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.SubprocessError) as exc:
        os.unlink(tmp)
        raise NativeUnavailable(f"building the native bond force failed: {exc}") from None
    if done.returncode != 0:
        os.unlink(tmp)
        first = next((ln for ln in done.stderr.splitlines() if "error" in ln), done.stderr[:200])
        raise NativeUnavailable(f"building the native bond force failed: {first.strip()}")
    os.replace(tmp, out)
    return out


def library() -> ctypes.CDLL:
    """The built library with its targets registered with XLA (once per process); raises
    `NativeUnavailable` (one line) where it cannot be had."""
    with _lock:
        if "library" in _state:
            return _state["library"]
        if "reason" in _state:
            raise NativeUnavailable(_state["reason"])
        try:
            if os.environ.get("METARIG_NATIVE", "1") == "0":
                raise NativeUnavailable("switched off (METARIG_NATIVE=0)")
            lib = ctypes.CDLL(str(_build()))
            _register(lib)
        except NativeUnavailable as exc:
            _state["reason"] = str(exc)
            log.info("native bond force unavailable (%s): the JAX force is used", exc)
            raise
        _state["library"] = lib
        return lib


def available() -> bool:
    """Whether the native force can be used here (builds it the first time)."""
    try:
        library()
    except NativeUnavailable:
        return False
    return True


def _register(lib: ctypes.CDLL) -> None:
    import jax

    for target, symbol in TARGETS.items():
        jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, symbol)),
                                    platform="cpu")


def main() -> int:
    """Build now (`make install` calls this) and say where, or why not; never fails, since the
    engine then keeps the JAX force."""
    try:
        lib = library()
    except NativeUnavailable as exc:
        print(f"native bond force not used ({exc}): the engine uses the JAX force")
        return 0
    print(f"native bond force: {lib._name}")
    return 0
