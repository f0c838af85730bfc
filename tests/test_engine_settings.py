"""What importing `design_engine` sets for XLA (README, "Compiling"): its classic CPU emitters
and copy insertion with region analysis, each unless the user's XLA_FLAGS name it."""

import os
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
