"""trim_compilation_cache: compiled programs hold memory mappings until JAX's caches drop them."""

import sys

import jax
import jax.numpy as jnp
import pytest
from helpers import maneuvers, systems

import ldap_jax as lj


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/maps")
def test_trim_releases_the_mappings_of_compiled_programs():
    sb = systems()["snakeboard"]
    q0, qdot0, ctl = jax.tree_util.tree_map(lambda x: x[0], maneuvers(sb, 1, seed=0))
    lj.trim_compilation_cache(1e-9)  # start from empty caches
    before = lj.memory_mappings()[0]
    for n in (11, 12):  # two programs (n_steps is static)
        lj.simulate(sb, q0, qdot0, ctl, t_final=1.0, n_steps=n, integrator=lj.DLA()).q.block_until_ready()
    grown = lj.memory_mappings()[0]
    assert grown > before + 100  # hundreds of mappings per compiled DLA rollout
    assert not lj.trim_compilation_cache(1.0)  # far below the limit: nothing to do
    assert lj.trim_compilation_cache(1e-9)
    assert lj.memory_mappings()[0] < grown - 100
    # the library still works after the caches are gone
    traj = lj.simulate(sb, q0, qdot0, ctl, t_final=1.0, n_steps=11, integrator=lj.DLA())
    assert bool(jnp.all(jnp.isfinite(traj.q)))


def test_trim_threshold_is_checked():
    with pytest.raises(ValueError, match="'threshold'"):
        lj.trim_compilation_cache(0.0)
    with pytest.raises(ValueError, match="'threshold'"):
        lj.trim_compilation_cache(1.5)
