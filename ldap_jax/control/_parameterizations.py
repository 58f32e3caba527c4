"""Control parameterizations: per-step sampled controls and periodic gaits (sinusoid sums).

A parameterization maps a pytree of free parameters (what the optimizer updates, O(1) by
construction thanks to a per-channel ``scale``) to an :class:`~ldap_jax.AbstractControls`.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .._compilation_cache import asarray
from .._controls import AbstractControls, Sampled, Sinusoids
from .._typing import ArrayLike
from .._validation import check_positive_int, is_concrete

__all__ = ["AbstractParameterization", "SampledControls", "SinusoidGait", "PeriodicControls"]


class AbstractParameterization(eqx.Module):
    """Parameters -> controls."""

    @abc.abstractmethod
    def controls(self, params) -> AbstractControls: ...

    @abc.abstractmethod
    def init(self, key: PRNGKeyArray | None = None, *, amplitude: float = 0.3): ...


class SampledControls(AbstractParameterization):
    """Discrete optimal control: one value per channel at each step time ``t_k``.

    ``params`` has shape ``(n_steps + 1, n_channels)``; the controls are
    ``Sampled(params * scale, t_final, t0)``, so an integrator sampling at the step times sees
    exactly ``c_k = params[k] * scale`` (stage times in between see linear interpolation).

    Args:
        t_final, t0: time interval.
        n_steps: number of steps N of the rollout.
        scale: per-channel scale (n_channels,).
    """

    t_final: Array
    t0: Array
    scale: Float[Array, " n"]
    n_steps: int = eqx.field(static=True)

    def __init__(self, t_final: ArrayLike, n_steps: int, scale: ArrayLike, *, t0: ArrayLike = 0.0):
        n_steps = check_positive_int("n_steps", n_steps)
        self.t_final = asarray(t_final, float)
        self.t0 = asarray(t0, float)
        self.scale = asarray(scale, float)
        if self.scale.ndim != 1:
            raise ValueError(f"SampledControls: 'scale' must be 1-d (n_channels,), got {self.scale.shape}")
        if is_concrete(self.scale):
            a = np.asarray(self.scale)
            if not np.all(np.isfinite(a) & (a > 0)):
                raise ValueError(f"SampledControls: 'scale' must be positive and finite, got {a}")
        self.n_steps = n_steps

    def controls(self, params: Float[Array, "K n"]) -> Sampled:
        return Sampled(self.values(params), self.t_final, self.t0)

    def values(self, params: Float[Array, "K n"]) -> Float[Array, "K n"]:
        """Control values at the step times (for effort and bounds)."""
        shape = (self.n_steps + 1, self.scale.shape[0])
        if jnp.shape(params) != shape:
            raise ValueError(
                f"'params' must have shape {shape} (N + 1 nodes, channels), got {jnp.shape(params)}"
            )
        return params * self.scale[None, :]

    def init(self, key=None, *, amplitude=0.3, n_modes: int = 3, periodic: bool = False):
        """A smooth initial guess: per channel a sum of ``n_modes`` sines ``sin(j pi t / T)`` with
        coefficients ``amplitude * N(0, 1)`` (``key``), or ``amplitude * sin(pi t / T)`` ... for
        ``key=None`` (a deterministic guess: channel ``c`` gets mode ``c + 1``). ``periodic``: the
        modes are ``sin(2 pi j t / T + phase)`` (phases uniform with ``key``, channel ``c``
        shifted by a quarter period without), periodic over ``[0, T]``."""
        n = self.scale.shape[0]
        s = jnp.linspace(0.0, 1.0, self.n_steps + 1)
        if periodic:
            return self._periodic_init(key, amplitude, n_modes, s)
        if key is None:
            return self.fixed_init(amplitude, n_modes=n_modes)
        modes = jnp.stack([jnp.sin((j + 1) * jnp.pi * s) for j in range(n_modes)], axis=1)  # (K, M)
        return modes @ (amplitude * jax.random.normal(key, (n_modes, n)))

    def fixed_init(self, amplitude=0.3, *, n_modes: int = 3, xp=jnp):
        """The deterministic guess (:meth:`init` with ``key=None``): channel ``c`` is
        ``amplitude * sin((c mod n_modes + 1) pi t / T)`` at the nodes. ``xp``: the array module
        (``numpy`` computes it on the host, with no compiled program)."""
        s = xp.linspace(0.0, 1.0, self.n_steps + 1)
        n = self.scale.shape[0]
        return xp.stack([amplitude * xp.sin((c % n_modes + 1) * xp.pi * s) for c in range(n)], axis=1)

    def _periodic_init(self, key, amplitude, n_modes, s):
        n = self.scale.shape[0]
        j = jnp.arange(1, n_modes + 1, dtype=s.dtype)
        if key is None:
            phase = 0.5 * jnp.pi * jnp.arange(n, dtype=s.dtype)[None, :] * jnp.ones((n_modes, 1))
            coef = jnp.zeros((n_modes, n)).at[0].set(amplitude)
        else:
            k1, k2 = jax.random.split(key)
            phase = jax.random.uniform(k1, (n_modes, n), s.dtype, 0.0, 2 * jnp.pi)
            coef = amplitude * jax.random.uniform(k2, (n_modes, n), s.dtype, 0.2, 1.0) / j[:, None]
        args = 2 * jnp.pi * j[None, :, None] * s[:, None, None] + phase[None]  # (K, M, n)
        return jnp.sum(coef[None] * jnp.sin(args), axis=1)


class PeriodicControls(AbstractControls):
    """Controls repeated with period ``period``: ``controls(t) = base(t mod period)``.

    A gait's controls over one period (:class:`~ldap_jax.Sampled` on ``[0, period]``), evaluated
    over as many periods as a rollout asks. ``cycles`` only sets how many periods of the base's
    breakpoints (its samples, where the slope jumps) :func:`ldap_jax.reference` steps onto.

    Args:
        base: the controls over ``[0, period]``.
        period: the period (s).
        cycles: periods whose breakpoints are reported (default 1; :meth:`over` sets it).
    """

    base: AbstractControls
    period: Array = eqx.field(converter=asarray)
    cycles: int = eqx.field(static=True, default=1)

    @property
    def n_channels(self) -> int:
        return self.base.n_channels

    def __call__(self, t):
        t = jnp.asarray(t, self.period.dtype)
        return self.base(t - self.period * jnp.floor(t / self.period))

    def over(self, cycles: int) -> PeriodicControls:
        """The same controls, with the breakpoints of ``cycles`` periods."""
        return PeriodicControls(self.base, self.period, int(cycles))

    def breakpoints(self):
        b = self.base.breakpoints()
        if b is None:
            return None
        k = jnp.arange(self.cycles, dtype=b.dtype)
        return (b[None, :] + self.period * k[:, None]).reshape(-1)


class SinusoidGait(AbstractParameterization):
    """Periodic gait: each channel a sum of sinusoids with free amplitudes, frequencies, phases.

    ``params = (A, W, P)``, each (n_channels, n_terms); the controls are
    ``Sinusoids(A * scale, W, P)``: channel ``c`` is ``sum_j scale_c A[c, j] sin(W[c, j] t + P[c, j])``.
    With ``shared_frequency`` the frequencies are one parameter per term, shared by all
    channels (a gait: rotor and steering at a common frequency, the relative phase free).

    Args:
        scale: per-channel amplitude scale (n_channels,).
        n_terms: sinusoids per channel.
        frequency: initial frequency of the first term (rad/s); term j starts at ``(j+1)`` times it.
        shared_frequency: one frequency per term for all channels.
    """

    scale: Float[Array, " n"]
    frequency: Array
    n_terms: int = eqx.field(static=True)
    shared_frequency: bool = eqx.field(static=True)

    def __init__(
        self, scale: ArrayLike, *, n_terms: int = 1, frequency: ArrayLike = 1.0, shared_frequency=True
    ):
        if isinstance(n_terms, bool) or not isinstance(n_terms, int) or n_terms < 1:
            raise ValueError(f"SinusoidGait: 'n_terms' must be a positive integer, got {n_terms!r}")
        self.scale = asarray(scale, float)
        if self.scale.ndim != 1:
            raise ValueError(f"SinusoidGait: 'scale' must be 1-d (n_channels,), got {self.scale.shape}")
        self.frequency = asarray(frequency, float)
        if is_concrete(self.frequency) and not np.all(np.isfinite(np.asarray(self.frequency))):
            raise ValueError(f"SinusoidGait: 'frequency' must be finite, got {np.asarray(self.frequency)}")
        self.n_terms = n_terms
        self.shared_frequency = shared_frequency

    def controls(self, params) -> Sinusoids:
        n, m = self.scale.shape[0], self.n_terms
        expected = ((n, m), (1, m) if self.shared_frequency else (n, m), (n, m))
        shapes = (
            tuple(jnp.shape(x) for x in params) if isinstance(params, (tuple, list)) else jnp.shape(params)
        )
        if shapes != expected:
            raise ValueError(
                f"'params' must be (amplitudes, frequencies, phases) of shapes {expected}, got {shapes}"
            )
        a, w, p = params
        w = jnp.broadcast_to(w, a.shape)
        return Sinusoids(a * self.scale[:, None], w, p)

    def init(self, key=None, *, amplitude=0.3, periodic: bool = False):
        """Amplitudes ``amplitude`` (or ``amplitude * U(0.5, 1.5)`` per entry with ``key``),
        frequencies ``(j + 1) * frequency``, phases ``pi/2`` apart between channels (or uniform
        with ``key``)."""
        n, m = self.scale.shape[0], self.n_terms
        w = self.frequency * jnp.arange(1, m + 1, dtype=self.scale.dtype)
        w = w[None, :] if self.shared_frequency else jnp.broadcast_to(w, (n, m))
        if key is None:
            a = jnp.full((n, m), amplitude)
            p = jnp.broadcast_to(0.5 * jnp.pi * jnp.arange(n, dtype=self.scale.dtype)[:, None], (n, m))
        else:
            ka, kp, kw = jax.random.split(key, 3)
            a = amplitude * jax.random.uniform(ka, (n, m), minval=0.5, maxval=1.5)
            p = jax.random.uniform(kp, (n, m), minval=0.0, maxval=2 * jnp.pi)
            w = w * jax.random.uniform(kw, w.shape, minval=0.8, maxval=1.25)
        return (a, w, jnp.asarray(p))
