"""Sweeps over many runs: Pareto fronts and the Pareto sweep, robustness maps, Dask."""
