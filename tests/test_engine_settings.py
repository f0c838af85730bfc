"""What importing `design_engine` sets for XLA (README, "Compiling"): its classic CPU emitters
and copy insertion with region analysis, each unless the user's XLA_FLAGS name it, and a
compilation cache whose keys hold no folder path."""

import os
import shutil
import subprocess
import sys

SHOW = "import os, design_engine; print(os.environ['XLA_FLAGS'])"


def flags_after_import(**env) -> list[str]:
    """XLA_FLAGS in a fresh interpreter after `import design_engine`, with `env` set (a value
    None: unset)."""
    run_env = {k: v for k, v in os.environ.items() if k not in env and k != "XLA_FLAGS"}
    run_env.update({k: v for k, v in env.items() if v is not None})
    out = subprocess.run([sys.executable, "-c", SHOW], env=run_env, capture_output=True,
                         text=True, check=True)
    return out.stdout.split()


def test_the_engine_sets_its_xla_flags_unless_the_user_named_them():
    assert sorted(flags_after_import()) == [
        "--xla_cpu_copy_insertion_use_region_analysis=true",
        "--xla_cpu_use_fusion_emitters=false"]
    mine = "--xla_cpu_copy_insertion_use_region_analysis=false"
    assert sorted(flags_after_import(XLA_FLAGS=mine)) == [
        mine, "--xla_cpu_use_fusion_emitters=false"]
    assert flags_after_import(METARIG_XLA_CLASSIC_EMITTERS="0") == [
        "--xla_cpu_copy_insertion_use_region_analysis=true"]


COMPILE = ("import design_engine, jax, jax.numpy as jnp; "
           "jax.jit(lambda x: jnp.sin(x) * 2.0)(jnp.ones(3)).block_until_ready()")


def cached_after_compiling(cache) -> list[str]:
    """The files of compilation cache `cache` after a fresh interpreter compiled one small
    program into it (every program kept: METARIG_JAX_CACHE_MIN_S=0)."""
    env = dict(os.environ, METARIG_JAX_CACHE=str(cache), METARIG_JAX_CACHE_MIN_S="0")
    subprocess.run([sys.executable, "-c", COMPILE], env=env, check=True, capture_output=True)
    return sorted(p.name for p in cache.iterdir())


def test_a_compilation_cache_copied_to_another_folder_is_used_there(tmp_path):
    """The cache's keys hold no folder path: two folders get the same keys, and a copy of one
    serves the same program without compiling it again (no new file)."""
    first = cached_after_compiling(tmp_path / "a")
    assert first and cached_after_compiling(tmp_path / "b") == first
    shutil.copytree(tmp_path / "a", tmp_path / "copy")
    assert cached_after_compiling(tmp_path / "copy") == first
