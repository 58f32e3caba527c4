"""Shared test fixtures: every system and integrator, and seeded maneuvers."""

import jax
import jax.numpy as jnp
import numpy as np

import ldap_jax as lj


def systems():
    return {
        "car": lj.Car(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5),
        "snakeboard": lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02),
    }


def integrators():
    """(name, integrator, expected order)."""
    return [
        ("rdp_exp", lj.RDP(alpha=0.5, retraction="exp"), 2),
        ("rdp_cayley", lj.RDP(alpha=0.5, retraction="cayley"), 2),
        ("rdp_exact_dexp", lj.RDP(alpha=0.5, dtau_order=None), 2),
        ("rdp_alpha0", lj.RDP(alpha=0.0), 1),
        ("rdp_alpha1", lj.RDP(alpha=1.0), 1),
        ("rdp_alpha1_cayley", lj.RDP(alpha=1.0, retraction="cayley"), 1),
        ("rk2", lj.RK2(), 2),
        ("rk4", lj.RK4(), 4),
    ]


def maneuvers(system, n, seed=0):
    """A batch of ``n`` random maneuvers ``(q0, qdot0, controls)`` (leading batch axis)."""
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    return jax.vmap(system.sample_maneuver)(keys)


def index(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def fitted_order(hs, errs):
    """Least-squares slope of log(err) against log(h)."""
    return float(np.polyfit(np.log(np.asarray(hs)), np.log(np.asarray(errs)), 1)[0])


def pose_error(q, q_ref):
    """Max over the batch of the Euclidean error in (x, y, theta)."""
    return float(jnp.max(jnp.linalg.norm(q[..., :3] - q_ref[..., :3], axis=-1)))
