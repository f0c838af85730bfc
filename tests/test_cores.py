"""Pools are sized by the cores a process may use, not by the machine's (`metarig.cores`)."""

import json
import os
import subprocess
import sys

import pytest

from metarig.cores import usable_cores

NARROWED = """
import json, os, sys
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # as `taskset -c K` starts it
from metarig.cores import usable_cores
from tracking.batch import threads_per_worker
from design_engine.design.evaluator import TaskEvaluator
from design_engine.design.task import load_task
evaluator = TaskEvaluator(load_task("focusing", size=(4, 4)))
print(json.dumps([usable_cores(), threads_per_worker(1), evaluator._scenes is None]))
"""


def test_the_cores_are_the_affinity_of_the_process():
    assert usable_cores() == len(os.sched_getaffinity(0)) >= 1


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity here")
def test_a_process_narrowed_to_one_core_sizes_its_pools_by_that_core():
    """The tracker's threads and a design run's solves at once: one each, where the machine
    has more cores (`os.cpu_count()`)."""
    out = subprocess.run([sys.executable, "-c", NARROWED], capture_output=True, text=True,
                         check=True, timeout=300)
    cores, threads, one_at_a_time = json.loads(out.stdout.splitlines()[-1])
    assert (cores, threads, one_at_a_time) == (1, 1, True)
