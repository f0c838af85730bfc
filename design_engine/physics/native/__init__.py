"""The bond map's energy and force as native XLA CPU custom calls (C++, built on first use).

`force.make_energy_and_gradient` is the JAX function; `build.available()` says whether it can
be used here.
"""
