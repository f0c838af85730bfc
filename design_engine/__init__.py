"""design_engine: differentiable simulation and design of rigid-unit metamaterials (JAX).

Public API re-exported here. The engine runs in float64 (enabled on import) and keeps a
persistent XLA compilation cache (directory `$METARIG_JAX_CACHE`, default
`~/.cache/metarig/jax`; set it to an empty string to disable; programs that took at least
`$METARIG_JAX_CACHE_MIN_S` seconds to compile are kept, default 0.5; the test suite keeps all). Errors inside compiled code are
turned into NaN (`EQX_ON_ERROR=nan`, required for the cache to hold diffrax programs) and every
run checks its results for NaN and solver failure itself.
"""

import os

os.environ.setdefault("EQX_ON_ERROR", "nan")


def _default_xla_flag(flag: str) -> None:
    """Append `flag` ("--name=value") to XLA_FLAGS unless they name its setting already (a
    flag of the user's own wins). XLA reads XLA_FLAGS when its CPU backend starts (the first
    computation), so this holds even when jax was imported before."""
    if flag.split("=")[0].lstrip("-") not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = " ".join(filter(None, (os.environ.get("XLA_FLAGS", ""), flag)))


# XLA's classic CPU code generators instead of its newer fusion emitters: on the engine's own
# programs they compile in 0.55-0.65x and run in 0.83-1.0x the time; float64 results agree to
# 1e-12, the float32 fixed step to 7e-6 (benchmarks/bench_xla_emitters.py ->
# benchmarks/results/bench_xla_emitters.json, 2 cores). METARIG_XLA_CLASSIC_EMITTERS=0 leaves
# XLA's default.
if os.environ.get("METARIG_XLA_CLASSIC_EMITTERS", "1") != "0":
    _default_xla_flag("--xla_cpu_use_fusion_emitters=false")
# XLA's copy insertion with region analysis (its GPU default), which leaves out copies of loop
# buffers that its CPU default keeps: the policy's forward passes 2-7 % faster, reverse passes
# 0-4 %, J and gradient the same to the bit (benchmarks/bench_programs.py ->
# bench_programs_copy_region_analysis.json, _2.json)
_default_xla_flag("--xla_cpu_copy_insertion_use_region_analysis=true")

import logging  # noqa: E402

# JAX probes for accelerators at start-up and logs a warning for each one it does not find
logging.getLogger("jax._src.xla_bridge").setLevel(logging.ERROR)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
_cache = os.environ.get("METARIG_JAX_CACHE", os.path.expanduser("~/.cache/metarig/jax"))
if _cache:
    jax.config.update("jax_compilation_cache_dir", _cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs",
                      float(os.environ.get("METARIG_JAX_CACHE_MIN_S", "0.5")))
    # JAX points XLA's GPU autotune cache into the cache folder, and that path then enters every
    # program's key: a cache copied or moved to another folder missed every program. The CPU
    # has no use for that cache
    jax.config.update("jax_persistent_cache_enable_xla_caches", "none")

from design_engine.design.constraints import ConstraintLimits as ConstraintLimits  # noqa: E402
from design_engine.design.constraints import make_constraints as make_constraints  # noqa: E402
from design_engine.physics.geometry import InvalidDesignError as InvalidDesignError  # noqa: E402
from design_engine.physics.lattice import Lattice as Lattice  # noqa: E402
from design_engine.physics.lattice import kagome as kagome  # noqa: E402
from design_engine.physics.lattice import periodic_design as periodic_design  # noqa: E402
from design_engine.physics.lattice import quads as quads  # noqa: E402
from design_engine.physics.material import Material as Material  # noqa: E402
from design_engine.physics.scenes import PRESETS as PRESETS  # noqa: E402
from design_engine.physics.scenes import Scene as Scene  # noqa: E402
from design_engine.physics.scenes import build_scene as build_scene  # noqa: E402
from design_engine.solve.run import SceneRun as SceneRun  # noqa: E402
from design_engine.solve.run import make_objective as make_objective  # noqa: E402
from design_engine.solve.run import simulate_rig as simulate_rig  # noqa: E402
from design_engine.solve.run import simulate_scene as simulate_scene  # noqa: E402
from design_engine.solve.simulate import SimulationError as SimulationError  # noqa: E402
from design_engine.solve.simulate import SolverConfig as SolverConfig  # noqa: E402
from metarig.trajectory import Trajectory as Trajectory  # noqa: E402
