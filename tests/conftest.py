"""Shared test set-up: float64 JAX (via design_engine), the --runslow flag."""

import pytest

import design_engine  # noqa: F401  (enables x64 and the compilation cache)


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run slow tests")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow (make test-slow)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
