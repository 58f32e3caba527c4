"""lj.shard_vmap: jax.vmap with the batch split over devices (one device in this process; four in
test_study's child process, where the batch is padded and each device runs its own loops)."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import code, maneuvers, systems

import ldap_jax as lj

SYSTEMS = systems()


def _rollout(system, q0, qdot0, ctl):
    return lj.simulate(system, q0, qdot0, ctl, t_final=1.0, n_steps=8)


def test_shard_vmap_equals_vmap_with_static_arguments_and_outputs():
    """A model given once (in_axes None) and a trajectory out (arrays and a result code):
    the same nodes and codes as jax.vmap, and one compilation for two calls."""
    car = SYSTEMS["car"]
    q0, qdot0, ctl = maneuvers(car, 3, seed=2)
    run = lj.shard_vmap(_rollout, in_axes=(None, 0, 0, 0))
    out = run(car, q0, qdot0, ctl)
    ref = jax.vmap(_rollout, in_axes=(None, 0, 0, 0))(car, q0, qdot0, ctl)
    assert isinstance(out, lj.Trajectory) and out.q.shape == (3, 9, 5)
    np.testing.assert_allclose(out.q, ref.q, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(code(out.result), code(ref.result))
    from ldap_jax import _sharding

    before = _sharding._program._cached._cache_size()
    again = run(car, q0 + 0.01, qdot0, ctl)  # new values: the same program
    assert _sharding._program._cached._cache_size() == before
    assert not np.allclose(again.q, out.q)


def test_shard_vmap_bad_arguments_are_named():
    car = SYSTEMS["car"]
    q0, qdot0, ctl = maneuvers(car, 3, seed=2)
    with pytest.raises(ValueError, match="'in_axes'"):
        lj.shard_vmap(_rollout, in_axes=(None, 0))(car, q0, qdot0, ctl)
    with pytest.raises(ValueError, match="'in_axes'"):
        lj.shard_vmap(_rollout, in_axes=1)(car, q0, qdot0, ctl)
    with pytest.raises(ValueError, match="at least one batched"):
        lj.shard_vmap(_rollout, in_axes=None)(car, q0, qdot0, ctl)
    with pytest.raises(ValueError, match="argument 0 is batched"):  # a model has no batch axis
        lj.shard_vmap(_rollout)(car, q0, qdot0, ctl)
    with pytest.raises(ValueError, match=r"batch size: \[2, 3\]"):
        lj.shard_vmap(_rollout, in_axes=(None, 0, 0, 0))(car, q0[:2], qdot0, ctl)
    with pytest.raises(ValueError, match="empty batch"):
        lj.shard_vmap(jnp.sin)(jnp.zeros((0,)))
    with pytest.raises(ValueError, match="'mesh'"):
        mesh = jax.sharding.Mesh(np.asarray(jax.devices()).reshape(1, 1), ("a", "b"))
        lj.shard_vmap(jnp.sin, mesh=mesh)


def test_use_cpu_cores_keeps_a_started_backend_and_names_bad_counts(monkeypatch):
    """Once JAX's backend runs (as in this worker), the device count is fixed: the flags are left
    alone and the devices JAX has are returned; a bad count is named."""
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    jax.devices()
    assert lj.use_cpu_cores(3) == len(jax.devices("cpu"))
    assert "device_count" not in os.environ["XLA_FLAGS"]
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(ValueError, match="'n'"):
            lj.use_cpu_cores(bad)
