"""Autodiff gradient of a scene objective against a central finite difference along one direction."""

import jax.numpy as jnp
import numpy as np
import pytest

from design_engine.solve.run import checked, make_objective


def central_difference(value, x, h, seed=0):
    """(d, (J(x + h d) - J(x - h d)) / 2h) for a random unit direction d; `value(x)` returns
    (J, aux)."""
    d = np.random.default_rng(seed).normal(size=np.size(x))
    d /= np.linalg.norm(d)
    return d, (float(value(x + h * d)[0]) - float(value(x - h * d)[0])) / (2 * h)


def directional_check(scene, config, h, seed=0, rel=1e-4, one_program=False):
    """Assert dJ/dx . d == (J(x + h d) - J(x - h d)) / 2h (rel) for a random unit d; returns both.

    `one_program`: J(x +- h d) from the value-and-gradient program too, so that only one
    program is compiled (for scenes whose compile costs more than their solves)."""
    vg, value = make_objective(scene, config)
    x = jnp.asarray(scene.design)
    (j, _), grad = checked(vg(x), config)
    if one_program:
        def value(y):
            return vg(y)[0]
    d, fd = central_difference(lambda y: checked(value(y), config), x, h, seed)
    ad = float(jnp.dot(grad, d))
    assert float(j) > 0 or scene.spin_point is not None
    assert ad == pytest.approx(fd, rel=rel), (ad, fd)
    return ad, fd
