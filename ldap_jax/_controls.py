"""Control signals: sinusoid sums (gaits) and sampled sequences (discrete optimal control).

A control is a pytree mapping a time ``t`` (scalar) to the values of its channels, shape
``(n_channels,)``. Which physical input a channel drives is the system's business
(:meth:`ldap_jax.systems.AbstractSystem.inputs`).
"""

from __future__ import annotations

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._fields import converter_field
from ._numerics import plain_active, sincos
from ._typing import ArrayLike

__all__ = ["AbstractControls", "Sinusoids", "Sampled", "Constant"]


def _float_array(x: ArrayLike) -> Array:
    """Converter of the control fields: a floating array (integers converted), or a ``TypeError``
    naming the field (``Sinusoids: 'amplitude' must be ...``)."""
    value = x

    def bad() -> TypeError:
        cls, name = converter_field()
        return TypeError(
            f"{cls or 'controls'}: '{name or 'value'}' must be an array of real numbers, got {value!r}"
        )

    if isinstance(x, (str, bytes)) or x is None:
        raise bad()
    try:
        x = jnp.asarray(x)
    except (TypeError, ValueError) as err:
        raise bad() from err
    if jnp.issubdtype(x.dtype, jnp.integer) or x.dtype == jnp.bool_:
        x = x.astype(jnp.result_type(float))
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise bad()
    return x


class AbstractControls(eqx.Module):
    """A time-dependent control: ``controls(t) -> (n_channels,)``."""

    @property
    @abc.abstractmethod
    def n_channels(self) -> int: ...

    @abc.abstractmethod
    def __call__(self, t: ArrayLike) -> Float[Array, " n_channels"]: ...

    def value_checks(self) -> tuple[tuple[str, Array], ...]:
        """``(message, condition)`` pairs the control's values must satisfy (default: none
        besides finiteness, which every run checks). Checked at construction when the values
        are concrete (``ValueError``), and in every run when they are traced, where a violation
        fails that trajectory with ``RESULTS.invalid_input``."""
        return ()

    def breakpoints(self) -> Float[Array, " B"] | None:
        """The times at which the control or one of its derivatives jumps (``None``: smooth).

        :func:`ldap_jax.reference` steps onto them (diffrax's ``jump_ts``): an adaptive solver's
        error estimate does not see a kink between two stages, and stepping across one costs it
        the order of the method there."""
        return None

    def impulse_spread(self, t0: Array, t1: Array) -> Float[Array, " n_channels"] | None:
        """An estimate, per channel, of the range (largest minus smallest value) of the integral
        ``int_{t0}^{t} controls`` over ``t`` in ``[t0, t1]``, or ``None`` (unknown: a rollout then
        accumulates it along its nodes). The divergence test of :func:`ldap_jax.simulate` takes
        its energy scale from it, so it must not be computed from the run's own nodes when they can
        alias (a sinusoid sampled at a step near its period)."""
        return None

    def derivative(self, t: ArrayLike) -> Float[Array, " n_channels"]:
        """``d/dt controls(t)`` by forward-mode autodiff."""
        t = jnp.asarray(t)
        return jax.jvp(self.__call__, (t,), (jnp.ones_like(t),))[1]

    def sampler(self, h: Array, fractions: Array) -> Callable[[Array], Float[Array, "S n_channels"]]:
        """A function ``t -> (controls(t + f_j h))_j`` for the fractions ``f_j`` of a step.

        Rollouts call it once per step with the step's start time; a subclass may precompute
        what depends only on ``h`` (:class:`Sinusoids` does).
        """
        return lambda t: jax.vmap(self.__call__)(t + h * fractions)

    def node_sampler(self) -> Callable[[Array], Float[Array, " n_channels"]] | None:
        """A function ``t -> controls(t)`` for a rollout that carries the controls from step to
        step, or ``None`` (the default: the rollout calls :meth:`sampler` at every step).

        A symmetric (order-2) integrator that reads the controls at the two ends of its step only
        (fractions ``(0, 1)``) then evaluates them once per step, at its end
        ``t_{k+1} = t0 + (k + 1) h``, and the next step reads them from the carry (:class:`Sinusoids`
        does this: one sine per term and step instead of a sine and a cosine). The values must be
        the controls at ``t`` (to round-off: they replace :meth:`sampler`'s at the fractions 0
        and 1)."""
        return None


class Sinusoids(AbstractControls):
    """Sums of sinusoids: channel ``c`` is ``sum_j A[c, j] sin(W[c, j] t + P[c, j])``.

    Args:
        amplitude: ``A``, shape (n_channels, n_terms).
        frequency: ``W`` (rad/s), same shape.
        phase: ``P`` (rad), same shape.

    Example:
        >>> ctl = Sinusoids(amplitude=[[0.1], [0.05]], frequency=[[1.0], [2.0]], phase=[[0.0], [0.3]])
        >>> ctl(0.5).shape
        (2,)
    """

    amplitude: Float[Array, "n_channels n_terms"] = eqx.field(converter=_float_array)
    frequency: Float[Array, "n_channels n_terms"] = eqx.field(converter=_float_array)
    phase: Float[Array, "n_channels n_terms"] = eqx.field(converter=_float_array)

    def __check_init__(self):
        shapes = {n: getattr(self, n).shape for n in ("amplitude", "frequency", "phase")}
        for name, shape in shapes.items():
            if len(shape) < 2:
                raise ValueError(
                    f"Sinusoids: {name!r} must have shape (n_channels, n_terms) (leading batch axes "
                    f"allowed, for vmap), got {shape}"
                )
        if len(set(shapes.values())) != 1:
            raise ValueError(f"Sinusoids: amplitude, frequency and phase shapes differ: {shapes}")

    @property
    def n_channels(self) -> int:
        return self.amplitude.shape[-2]

    def __call__(self, t):
        t = jnp.asarray(t, self.amplitude.dtype)
        return jnp.sum(self.amplitude * jnp.sin(self.frequency * t + self.phase), axis=-1)

    def impulse_spread(self, t0, t1):
        """``sum_j min(2 |A_j| / |W_j|, |A_j| (t1 - t0))``: a term's integral is a sinusoid of
        amplitude ``|A_j| / |W_j|`` (or, over a short interval or at ``W_j = 0``, grows no faster
        than ``|A_j|``)."""
        a, w = jnp.abs(self.amplitude), jnp.abs(self.frequency)
        span = jnp.abs(t1 - t0)
        safe_w = jnp.where(w > 0, w, 1.0)
        term = jnp.where(w > 0, jnp.minimum(2 * a / safe_w, a * span), a * span)
        return jnp.sum(term, axis=-1)

    def sampler(self, h, fractions, *, reverse_only: bool = False):
        """Angle addition: ``sin(w (t + f h) + p) = sin(w t + p) cos(w f h) + cos(w t + p) sin(w f h)``,
        with the ``(cos, sin)(w f h)`` of a step computed once: one ``sincos`` per term and step,
        however many fractions the integrator reads. Written term by term on scalars, so that a
        vmapped batch keeps each term one contiguous vector: the same arithmetic on the
        ``(channels, terms)`` arrays compiles faster (a 2 x 2 gait: 13-37% fewer XLA kernels in a
        rollout, 0.72-0.86x the compile time) but runs slower under XLA's default code generation
        (a plain ``jax.jit``): 1.22-1.34x for ``RDP()``, 1.8-2.0x for ``RDP(order=4)`` and
        1.13-1.5x for RK4 (car and snakeboard, 200 maneuvers, 1000 steps, both forms alternating in
        one process). Compiled with :func:`ldap_jax.compiler_options` (as the library's own entry
        points are) the array form ran 0.90x for order 4 and RK4 and 1.02-1.04x for ``RDP()``; the
        term-by-term form under XLA's defaults is the fastest of the four (order 4: 5.1e6 steps/s
        against 3.2e6 at best on arrays).

        ``reverse_only`` (a program differentiated in reverse mode only: the rollout of
        :func:`~ldap_jax.simulate` outside forward mode): the same values, each term with a
        hand-written VJP (:func:`_sinusoid_term`) that sends the derivative through
        ``(sin, cos)(w f h)`` to ``w`` and ``h`` at once, so that a rollout's backward pass keeps
        three cotangents per term (``A``, ``W``, ``P``), not five (and the two of shape ``S``)."""
        n_ch = self.amplitude.shape[-2]
        ds, dc = sincos(self.frequency[None] * (h * fractions)[:, None, None])  # (S, channels, terms)
        # every coefficient a scalar of its own, taken apart here, before the rollout's loop: under
        # vmap each is one contiguous vector (sliced inside the loop from the (B, channels, terms)
        # arrays, they were strided loads: 4 of the 6 sincos of a snakeboard step cost 10x the
        # kernel's own), and sin and cos finished in one kernel each (``whole``)
        terms = [
            [(*term, ds[:, i, j], dc[:, i, j]) for j, term in enumerate(channel)]
            for i, channel in enumerate(self._scalar_terms())
        ]

        custom = reverse_only and not plain_active()

        def sample(t):
            if not n_ch:
                return jnp.zeros((fractions.shape[0], 0), t.dtype)
            columns = []
            for i in range(n_ch):
                col = 0.0
                for a, w, p, dsv, dcv in terms[i]:
                    if custom:
                        # (sin, cos)(w f h) keep their dependence on w and h (the VJP returns
                        # none for them): a second reverse pass differentiates the first through them
                        sc = (jax.lax.stop_gradient(fractions), dsv, dcv)
                        col = col + _sinusoid_term(a, w, p, t, h, sc)
                    else:
                        s, c = sincos(w * t + p, whole=True)
                        col = col + a * (s * dcv + c * dsv)
                columns.append(col)
            return jnp.stack(columns, axis=-1)

        return sample

    def _scalar_terms(self) -> list[list[tuple[Array, Array, Array]]]:
        """``(A[c, j], W[c, j], P[c, j])`` per channel ``c`` and term ``j``, each a scalar of its own
        (one contiguous vector under ``vmap``), taken apart before a rollout's loop."""
        n_ch, n_terms = self.amplitude.shape[-2:]
        return [
            [(self.amplitude[i, j], self.frequency[i, j], self.phase[i, j]) for j in range(n_terms)]
            for i in range(n_ch)
        ]

    def node_sampler(self):
        """``t -> sum_j A[c, j] sin(W[c, j] t + P[c, j])``, term by term on scalars (contiguous
        vectors under ``vmap``, as :meth:`sampler`), one sine per term (``sincos``'s, finished in
        one kernel). A rollout whose integrator reads the controls at the ends of its steps only
        (order-2 RDP, DLA, GNI) calls it once per step, at the step's end, and carries the
        values into the next step: the angle addition of :meth:`sampler` needs a sine and a
        cosine per term at every step's start (8 of the 39 XLA kernels of a snakeboard step).
        JAX differentiates it (its derivative keeps the three cotangents of a term; a
        hand-written VJP sharing one argument reduction between the sine and the cosine ran no
        faster)."""
        terms = self._scalar_terms()

        def sample(t):
            if not terms:
                return jnp.zeros((0,), t.dtype)
            columns = []
            for channel in terms:
                col = 0.0
                for a, w, p in channel:
                    col = col + a * sincos(w * t + p, whole=True)[0]
                columns.append(col)
            return jnp.stack(columns)

        return sample


@jax.custom_vjp
def _sinusoid_term(a, w, p, t, h, sc):
    """One term of :meth:`Sinusoids.sampler` at the fractions ``f`` of a step:
    ``a (sin x DC + cos x DS)``, ``x = w t + p``, with ``(f, DS, DC) = sc``, ``(DS, DC)`` the values of
    ``(sin, cos)(w f h)`` (computed once, before the loop). Its VJP, for the cotangent ``g`` (S,)::

        a_bar = sum_s g_s (sin x DC_s + cos x DS_s),   x_bar = a sum_s g_s (cos x DC_s - sin x DS_s),
        y_bar_s = a g_s (cos x DC_s - sin x DS_s)          (y_s = w f_s h, the argument of DS, DC)
        w_bar = t x_bar + sum_s f_s h y_bar_s,   p_bar = x_bar,   t_bar = w x_bar,
        h_bar = sum_s f_s w y_bar_s.
    """
    _, ds, dc = sc
    s, c = sincos(w * t + p, whole=True)
    return a * (s * dc + c * ds)


def _sinusoid_term_fwd(a, w, p, t, h, sc):
    return _sinusoid_term(a, w, p, t, h, sc), (a, w, p, t, h, sc)


def _sinusoid_term_bwd(res, g):
    a, w, p, t, h, (f, ds, dc) = res
    s, c = sincos(w * t + p, whole=True)
    # the few fractions written out (a reduce over a short axis is a kernel of its own)
    gs = [g[i] for i in range(g.shape[0])]
    a_b = sum(gi * (s * dc[i] + c * ds[i]) for i, gi in enumerate(gs))
    y_b = [a * gi * (c * dc[i] - s * ds[i]) for i, gi in enumerate(gs)]
    x_b = sum(y_b)
    fy = sum(f[i] * yi for i, yi in enumerate(y_b))
    return a_b, t * x_b + h * fy, x_b, w * x_b, w * fy, None


_sinusoid_term.defvjp(_sinusoid_term_fwd, _sinusoid_term_bwd)


class Sampled(AbstractControls):
    """Control values at uniformly spaced times, linearly interpolated in between.

    ``values[k]`` is the control at ``t_k = t0 + k dt`` with ``dt = (t_final - t0) / (K - 1)``;
    outside ``[t0, t_final]`` the end values are held (:func:`ldap_jax.simulate` warns when known
    samples miss part of its run). Sampled with the same number of steps as
    :func:`ldap_jax.simulate`, the values are exactly the discrete controls at the step times
    (discrete optimal control).

    Args:
        values: shape (K, n_channels), K >= 2.
        t_final: time of the last sample.
        t0: time of the first sample.
    """

    values: Float[Array, "K n_channels"] = eqx.field(converter=_float_array)
    t_final: Array = eqx.field(converter=_float_array)
    t0: Array = eqx.field(converter=_float_array, default=0.0)

    def __check_init__(self):
        if self.values.ndim < 2 or self.values.shape[-2] < 2:
            raise ValueError(
                f"Sampled: 'values' must have shape (K >= 2, n_channels), got {self.values.shape}"
            )
        with jax.ensure_compile_time_eval():
            for message, ok in self.value_checks():
                if _concrete(ok) and not bool(jnp.all(ok)):
                    raise ValueError(f"Sampled: {message}, got t_final={self.t_final}, t0={self.t0}")

    def value_checks(self):
        ok = jnp.isfinite(self.t_final) & jnp.isfinite(self.t0) & (self.t_final > self.t0)
        return (("'t_final' must be finite and exceed 't0'", ok),)

    @property
    def n_channels(self) -> int:
        return self.values.shape[-1]

    def breakpoints(self):
        """The sample times: the interpolant's slope jumps there."""
        n = self.values.shape[0]
        return self.t0 + (self.t_final - self.t0) * jnp.arange(n, dtype=self.values.dtype) / (n - 1)

    def __call__(self, t):
        n = self.values.shape[0]
        t = jnp.asarray(t, self.values.dtype)
        s = (t - self.t0) / (self.t_final - self.t0) * (n - 1)
        s = jnp.clip(s, 0.0, n - 1)
        i = jnp.clip(jnp.floor(s).astype(int), 0, n - 2)
        w = s - i.astype(s.dtype)
        return (1 - w) * self.values[i] + w * self.values[i + 1]

    def impulse_spread(self, t0, t1):
        """The range of the exact integral of the interpolant at its samples (held constant
        outside ``[t0, t_final]``, where it grows by at most ``|end value|`` per second)."""
        dt = (self.t_final - self.t0) / (self.values.shape[0] - 1)
        p = jnp.cumsum(0.5 * dt * (self.values[1:] + self.values[:-1]), axis=0)
        p = jnp.concatenate([jnp.zeros_like(self.values[:1]), p])
        outside = jnp.maximum(jnp.abs(self.values[0]), jnp.abs(self.values[-1])) * (
            jnp.maximum(self.t0 - t0, 0) + jnp.maximum(t1 - self.t_final, 0)
        )
        return jnp.max(p, axis=0) - jnp.min(p, axis=0) + outside


class Constant(AbstractControls):
    """Constant channel values: ``controls(t) = values`` (e.g. zeros for an uncontrolled run).

    Args:
        values: shape (n_channels,).
    """

    values: Float[Array, " n_channels"] = eqx.field(converter=_float_array)

    def __check_init__(self):
        if self.values.ndim < 1:
            raise ValueError(f"Constant: 'values' must have shape (n_channels,), got {self.values.shape}")

    @property
    def n_channels(self) -> int:
        return self.values.shape[-1]

    def __call__(self, t):
        return self.values

    def impulse_spread(self, t0, t1):
        return jnp.abs(self.values) * jnp.abs(t1 - t0)


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)
