"""trim_compilation_cache: compiled programs hold memory mappings until JAX's caches drop them."""

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import eager_operations, maneuvers, systems

import ldap_jax as lj


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/maps")
def test_trim_releases_the_mappings_of_compiled_programs():
    # It empties JAX's caches in its test worker, as the worker's own trims after a test do
    # (conftest.py: one or two per worker in a full run), and then starts a worker's count of
    # mappings afresh.
    sb = systems()["snakeboard"]
    q0, qdot0, ctl = jax.tree_util.tree_map(lambda x: x[0], maneuvers(sb, 1, seed=0))
    lj.trim_compilation_cache(1e-9)  # start from empty caches
    before = lj.memory_mappings()[0]
    for n in (11, 12):  # two programs (n_steps is static)
        lj.simulate(sb, q0, qdot0, ctl, t_final=1.0, n_steps=n).q.block_until_ready()
    grown = lj.memory_mappings()[0]
    # hundreds of mappings per compiled rollout (measured: 814 for these two RDP rollouts, 752 for
    # the same with DLA, whose programs take 3x longer to compile)
    assert grown > before + 100
    assert not lj.trim_compilation_cache(1.0)  # far below the limit: nothing to do
    assert lj.trim_compilation_cache(1e-9)
    assert lj.memory_mappings()[0] < grown - 100
    # the library still works after the caches are gone
    traj = lj.simulate(sb, q0, qdot0, ctl, t_final=1.0, n_steps=11)
    assert bool(jnp.all(jnp.isfinite(traj.q)))


def test_trim_threshold_is_checked():
    with pytest.raises(ValueError, match="'threshold'"):
        lj.trim_compilation_cache(0.0)
    with pytest.raises(ValueError, match="'threshold'"):
        lj.trim_compilation_cache(1.5)


def test_compiler_options_top_level_and_nested(monkeypatch):
    """The library's entry points compile with lj.compiler_options() when called at the top level
    and stay usable inside a user's jit, vmap and grad (JAX rejects compile options on a nested
    jit); LDAP_JAX_FAST_COMPILE=0 turns the options off."""
    from ldap_jax import _compilation_cache as cc

    assert lj.compiler_options() == cc.FAST_COMPILE_OPTIONS  # this XLA knows them
    car = lj.Car()
    ctl = lj.Constant(jnp.array([0.1, 0.2]))

    def final_x(q0):
        return lj.simulate(car, q0, jnp.zeros(5), ctl, t_final=1.0, n_steps=10).q[-1, 0]

    q0 = jnp.zeros(5)
    top = final_x(q0)
    assert cc.in_trace() is False
    assert float(jnp.abs(jax.jit(final_x)(q0) - top)) < 1e-15
    assert float(jnp.max(jnp.abs(jax.vmap(final_x)(jnp.zeros((2, 5))) - top))) < 1e-15
    assert float(jax.grad(final_x)(q0)[0]) == pytest.approx(1.0, abs=1e-12)  # x_N = x_0 + ...
    # where the options apply: at the top level, under a top-level vmap (the batched program
    # runs as a top-level one) and on concrete arguments under a top-level grad (JAX calls the
    # program as it is), not inside a user's jit or on arguments a grad traces
    seen = []

    def where(x, args=None):
        seen.append(cc._runs_at_top_level(x if args is None else args))
        return x

    jax.vmap(jax.vmap(where))(jnp.zeros((2, 2)))
    jax.jit(jax.vmap(where))(jnp.zeros(2))
    jax.vmap(jax.jit(where))(jnp.zeros(2))
    jax.grad(where)(1.0)
    jax.vmap(jax.grad(where))(jnp.zeros(2))
    jax.grad(lambda x: where(x, np.ones(2)))(1.0)
    jax.grad(lambda x: where(x, jax.lax.stop_gradient(x)))(1.0)
    jax.jit(jax.grad(lambda x: where(x, np.ones(2))))(1.0)
    jax.jit(lambda x: where(x, np.ones(2)))(1.0)
    assert seen == [True, False, False, False, False, True, True, False, False]
    monkeypatch.setattr(cc, "_options", cc._UNSET)
    monkeypatch.setenv("LDAP_JAX_FAST_COMPILE", "0")
    assert lj.compiler_options() is None


@pytest.mark.parametrize(
    "x",
    [1.0, 3, True, 1 + 2j, np.float32(0.3), np.array([1.0, 2.0]), [1.0, 2.0], [1, 2], (0.5, 2), np.array(2)],
    ids=repr,
)
@pytest.mark.parametrize("dtype", [None, float, jnp.float32])
def test_asarray_is_jnp_asarray_without_a_program(x, dtype):
    """The library's ``asarray`` gives what ``jnp.asarray`` gives (dtype, weak type, values) and
    runs no eager JAX operation on a host value (``jnp.asarray`` compiles one in this JAX)."""
    from ldap_jax._compilation_cache import asarray

    try:
        expected = jnp.asarray(x, dtype)
    except TypeError:  # a complex number as a real dtype: the same error
        with pytest.raises(TypeError):
            asarray(x, dtype)
        return
    with eager_operations() as ops:
        got = asarray(x, dtype)
    assert ops == []
    assert isinstance(got, jax.Array) and got.dtype == expected.dtype and got.shape == expected.shape
    assert got.aval.weak_type == expected.aval.weak_type
    np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))


def test_asarray_errors_and_tracers_are_jnp_asarrays():
    from ldap_jax._compilation_cache import asarray

    for bad in (None, "a", [1, [2]]):
        with pytest.raises((TypeError, ValueError)):
            jnp.asarray(bad, float)
        with pytest.raises((TypeError, ValueError)):
            asarray(bad, float)
    assert jax.jit(lambda t: asarray(t, jnp.float32).dtype == jnp.float32)(1.0)


def test_compiler_options_probe_is_kept_next_to_the_compilation_cache(monkeypatch, tmp_path):
    """With a compilation cache directory the probe's answer is written there once; a new
    process (here: the module's state reset) reads it and compiles no probe."""
    from helpers import compiled_programs

    from ldap_jax import _compilation_cache as cc

    monkeypatch.setattr(cc, "_options", cc._UNSET)
    old = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    try:
        with compiled_programs("trace") as first:
            assert lj.compiler_options() == cc.FAST_COMPILE_OPTIONS
        assert first == ["<lambda>"] * 2  # the two probes
        assert (tmp_path / cc.PROBE_FILE).is_file()
        monkeypatch.setattr(cc, "_options", cc._UNSET)
        with compiled_programs("trace") as again:
            assert lj.compiler_options() == cc.FAST_COMPILE_OPTIONS
        assert again == []
        (tmp_path / cc.PROBE_FILE).write_text("{not json")  # a damaged file: probed again
        monkeypatch.setattr(cc, "_options", cc._UNSET)
        assert lj.compiler_options() == cc.FAST_COMPILE_OPTIONS
    finally:
        jax.config.update("jax_compilation_cache_dir", old)
