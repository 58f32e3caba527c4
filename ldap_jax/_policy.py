"""Feedback policies: controls computed from the state, ``u = pi(t, q, qdot)``."""

from __future__ import annotations

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._controls import AbstractControls
from ._typing import ArrayLike

__all__ = ["AbstractPolicy", "Policy", "LinearPolicy"]


class AbstractPolicy(eqx.Module):
    """A feedback law ``u = pi(t, q, qdot)`` with ``n_channels`` outputs.

    :func:`~ldap_jax.simulate` samples it like a sampled-data controller: on the step
    ``[t_k, t_k + h]`` every control time ``t`` the integrator reads gets
    :meth:`sampled` ``(t, t_k, q_k, qdot_k)``, with the state of the step's start (the
    feedforward part may vary within the step, the feedback sees the last node). With zero
    feedback a policy reproduces its open-loop feedforward exactly. The first sample sees
    ``qdot0`` as given: where a system takes a shape velocity from the controls (the car's
    steering rate), an open-loop run sets it from the controls at ``t0``, but a policy reads the
    value passed, so give it the rate the policy's reference has there.
    """

    @property
    @abc.abstractmethod
    def n_channels(self) -> int: ...

    @abc.abstractmethod
    def __call__(self, t: Array, q: Array, qdot: Array) -> Float[Array, " n_channels"]: ...

    def sampled(self, t: Array, t_state: Array, q: Array, qdot: Array) -> Float[Array, " n_channels"]:
        """The control at time ``t`` when the latest measured state is ``(q, qdot)``, taken at
        ``t_state <= t`` (the start of the step that contains ``t``).

        Default: ``self(t, q, qdot)``. A policy that compares the state with a time-varying
        reference overrides it to compare at ``t_state``, where the state was measured: compared
        at ``t``, a state that is exactly on the reference would read as off it by
        ``x_ref(t) - x_ref(t_state)``, and the feedback would push the run off its reference.
        """
        return self(t, q, qdot)


class Policy(AbstractPolicy):
    """A policy from any function ``fn(t, q, qdot) -> (n_channels,)`` (pure and jit-able).

    Args:
        fn: the feedback law (an ``eqx.Module`` holding arrays is differentiable through them).
        n_channels: number of outputs.
    """

    fn: Callable
    channels: int = eqx.field(static=True)

    def __init__(self, fn: Callable, n_channels: int):
        if not callable(fn):
            raise TypeError(f"Policy: 'fn' must be callable, got {type(fn)}")
        if isinstance(n_channels, bool) or not isinstance(n_channels, int):
            raise TypeError(f"Policy: 'n_channels' must be a non-negative integer, got {n_channels!r}")
        if n_channels < 0:
            raise ValueError(f"Policy: 'n_channels' must be a non-negative integer, got {n_channels!r}")
        self.fn = fn
        self.channels = n_channels

    @property
    def n_channels(self) -> int:
        return self.channels

    def __call__(self, t, q, qdot):
        return jnp.asarray(self.fn(t, q, qdot))


class LinearPolicy(AbstractPolicy):
    """Time-varying affine feedback around a reference:
    ``u(t) = u_ff(t) + K(t) [x_ref(t) - x]`` with ``x = (q, qdot)``; sampled by
    :func:`~ldap_jax.simulate` as ``u(t) = u_ff(t) + K(t_k) [x_ref(t_k) - x_k]`` on the step
    ``[t_k, t_k + h]`` (:meth:`sampled`: the correction held over the step, as a discrete LQR's).

    Args:
        feedforward: open-loop controls ``u_ff``.
        gain: ``K``, shape (n_channels, 2 d) (constant) or ``(T, n_channels, 2 d)`` sampled with
            ``reference`` (held piecewise constant between samples).
        reference: ``x_ref`` samples ``(T, 2 d)`` at times ``times`` (linear interpolation), or
            ``None`` for feedback around zero.
        times: ``(T,)`` sample times of ``reference`` and a time-varying ``gain``, strictly
            increasing; before ``times[0]`` and after ``times[-1]`` both are held at their end
            samples.
    """

    feedforward: AbstractControls
    gain: Array
    reference: Array | None = None
    times: Array | None = None

    def __check_init__(self):
        if not isinstance(self.feedforward, AbstractControls):
            raise TypeError(
                "LinearPolicy: 'feedforward' must be ldap_jax controls (e.g. lj.Sampled), "
                f"got {type(self.feedforward)}"
            )
        n = self.feedforward.n_channels
        shape = tuple(jnp.shape(self.gain))
        # leading axes are allowed (a time-varying gain, or a batch for vmap): only the last two
        # are checked, (channels, 2 d)
        if len(shape) < 2 or shape[-2] != n or shape[-1] % 2:
            raise ValueError(
                f"LinearPolicy: 'gain' must have shape (..., {n}, 2 d) for {n} channels, got {shape}"
            )
        if self.reference is not None and jnp.shape(self.reference)[-1:] != shape[-1:]:
            raise ValueError(
                f"LinearPolicy: 'reference' must have {shape[-1]} columns (x = (q, qdot), like 'gain'), got "
                f"shape {tuple(jnp.shape(self.reference))}"
            )
        if self.times is not None and self.reference is None:
            raise ValueError("LinearPolicy: 'times' needs 'reference' (samples of x_ref at those times)")
        if self.times is not None and jnp.ndim(self.times) == 1:  # one policy (not a batch for vmap)
            n_t = jnp.shape(self.times)[0]
            ref_shape = tuple(jnp.shape(self.reference))
            if len(ref_shape) == 2 and ref_shape[0] != n_t:
                raise ValueError(
                    f"LinearPolicy: 'reference' has {ref_shape[0]} samples but 'times' has {n_t} "
                    "(one time per sample)"
                )
            if len(shape) == 3 and shape[0] != n_t:
                raise ValueError(
                    f"LinearPolicy: a time-varying 'gain' has one matrix per time: {shape[0]} for "
                    f"{n_t} 'times'"
                )
            if not isinstance(self.times, jax.core.Tracer):
                t = np.asarray(self.times)
                if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
                    raise ValueError(f"LinearPolicy: 'times' must be finite and strictly increasing, got {t}")

    @property
    def n_channels(self) -> int:
        return self.feedforward.n_channels

    def __call__(self, t, q, qdot):
        return self.sampled(t, t, q, qdot)

    def sampled(self, t, t_state, q, qdot):
        """``u_ff(t) + K(t_state) [x_ref(t_state) - x]``: the feedback compares the state with the
        reference at the time the state was taken (on the step ``[t_k, t_k + h]`` of
        :func:`~ldap_jax.simulate`, ``t_k``), so a run on its reference gets no feedback."""
        x = jnp.concatenate([q, qdot])
        if self.times is None:
            x_ref = jnp.zeros_like(x) if self.reference is None else self.reference
            gain = self.gain
        else:
            x_ref = jnp.stack([jnp.interp(t_state, self.times, col) for col in self.reference.T])
            i = jnp.searchsorted(self.times, t_state, side="right") - 1
            i = jnp.clip(i, 0, self.times.shape[0] - 1)
            gain = self.gain if self.gain.ndim == 2 else self.gain[i]
        return self.feedforward(t) + gain @ (x_ref - x)


def _as_array(x: ArrayLike) -> Array:
    return jnp.asarray(x)
