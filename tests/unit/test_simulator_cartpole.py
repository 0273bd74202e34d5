"""The stateful "true" cartpole: seeded disturbance, impulse and mass-change interventions."""

from __future__ import annotations

import numpy as np
import pytest

from arcade_core.dynamics.params import CARTPOLE_TRUE
from simulator.cartpole import CartpoleSim


def test_disturbance_statistics_and_seeding():
    sim = CartpoleSim(seed=4)
    d = []
    for _ in range(2000):
        sim.step(0.0)
        d.append(sim.last_disturbance)
    d = np.array(d)
    # N(-0.5, 0.5): mean within 4 standard errors, variance within 10 %.
    assert d.mean() == pytest.approx(-0.5, abs=4 * np.sqrt(0.5 / d.size))
    assert d.var() == pytest.approx(0.5, rel=0.1)
    a, b, c = CartpoleSim(seed=1), CartpoleSim(seed=1), CartpoleSim(seed=2)
    xa = [a.step(0.3) for _ in range(20)]
    xb = [b.step(0.3) for _ in range(20)]
    xc = [c.step(0.3) for _ in range(20)]
    np.testing.assert_array_equal(xa, xb)
    assert not np.allclose(xa, xc)


def test_disturbance_and_friction_act_on_the_cart():
    quiet = CARTPOLE_TRUE._replace(dist_mean=0.0, dist_std=0.0)
    sim = CartpoleSim(quiet)
    x = sim.reset((0.0, 1.0, 0.0, 0.0))
    x = sim.step(0.0)
    # Upright, at rest pole: only cart friction, xddot = -mu_c xdot / M.
    assert x[1] == pytest.approx(1.0 - sim.dt * 0.25 * 1.0 / 1.0)
    biased = CARTPOLE_TRUE._replace(dist_std=0.0)
    x = CartpoleSim(biased).step(0.0)
    assert x[1] == pytest.approx(sim.dt * -0.5 / 1.0)


def test_push_and_mass_change_interventions():
    quiet = CARTPOLE_TRUE._replace(dist_mean=0.0, dist_std=0.0)
    sim = CartpoleSim(quiet)
    sim.push(2.0)
    x = sim.step(0.0)
    assert x[1] == pytest.approx(2.0 * sim.dt / 1.0)  # impulse on the cart only, once
    assert sim.step(0.0)[1] < x[1]
    sim.reset()
    sim.scale_masses(0.9)
    assert (sim.params.M, sim.params.m) == pytest.approx((0.9, 0.09))
    x = sim.step(1.0)
    assert x[1] == pytest.approx(sim.dt * 1.0 / 0.9)  # lighter cart accelerates more
    sim.reset()
    assert sim.params == quiet and sim.time == 0.0
    with pytest.raises(ValueError):
        sim.scale_masses(0.0)
