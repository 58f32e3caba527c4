"""The study's vocabulary: method and model names, and its settings."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from functools import reduce

from ..integrators import DLA, GNI, RDP, RK2, RK4, AbstractIntegrator
from ..systems import AbstractSystem, Car, Snakeboard

__all__ = ["METHODS", "MODELS", "CSV_COLUMNS", "StudyConfig", "make_integrator"]

#: Integrators of the study, by the name used in the CSV's ``method`` column.
METHODS: dict[str, Callable[[], AbstractIntegrator]] = {
    "rdp": lambda: RDP(alpha=0.5, retraction="exp"),
    "rdp4": lambda: RDP(order=4),
    "rdp6": lambda: RDP(order=6),
    "rdp8": lambda: RDP(order=8),
    "rdp_a0": lambda: RDP(alpha=0.0, retraction="exp"),
    "rdp_a1": lambda: RDP(alpha=1.0, retraction="exp"),
    "rdp_cayley": lambda: RDP(alpha=0.5, retraction="cayley"),
    "rdp_a0_cayley": lambda: RDP(alpha=0.0, retraction="cayley"),
    "rdp_a1_cayley": lambda: RDP(alpha=1.0, retraction="cayley"),
    "gni": lambda: GNI(),
    "gni_folded": lambda: GNI(variant="folded"),
    "dla": lambda: DLA(),
    "rk2": lambda: RK2(),
    "rk4": lambda: RK4(),
}

#: The paper's models with the library's default parameters.
MODELS: dict[str, Callable[[], AbstractSystem]] = {"snakeboard": Snakeboard, "car": Car}

#: Columns of the study's CSV, one row per model x duration x method x N.
CSV_COLUMNS = (
    "model",
    "duration",
    "method",
    "n_steps",
    "h",
    "runs",
    "failures",
    "failure_rate",
    "nonfinite",
    "singular",
    "not_converged",
    "blowup",
    "final_error_mean",
    "final_error_median",
    "final_error_max",
    "max_error_mean",
    "max_error_median",
    "max_error_max",
    "runtime_us",
    "reference_error",
)


def make_integrator(name: str) -> AbstractIntegrator:
    """The integrator named ``name`` (a key of :data:`METHODS`)."""
    if name not in METHODS:
        raise ValueError(f"'method' must be one of {sorted(METHODS)}, got {name!r}")
    return METHODS[name]()


def _positive_int(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"'{name}' must be a positive integer, got {value!r}")
    if value < 1:
        raise ValueError(f"'{name}' must be a positive integer, got {value!r}")


def _positive_float(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"'{name}' must be a positive number, got {value!r}")
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"'{name}' must be positive and finite, got {value!r}")


def _names(name: str, value) -> None:
    if isinstance(value, (str, bytes)) or not isinstance(value, (tuple, list)):
        raise TypeError(f"'{name}' must be a tuple of names, got {value!r}")


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """Settings of a study (defaults: the paper's full study).

    Attributes:
        models: keys of :data:`MODELS`.
        durations: trajectory lengths in seconds (paper: 10 s, Fig. 4; 600 s, Fig. 5).
        methods: keys of :data:`METHODS`.
        resolutions: total numbers of steps N; each must be a multiple of ``n_out``.
        runs: maneuvers per model.
        seed: seed of the maneuvers.
        n_out: evenly spaced nodes (besides t = 0) at which errors are measured (the max error is
            the largest over these ``n_out + 1`` times); default the greatest common divisor of
            the resolutions, capped at 500 (a warning when that leaves fewer than 10).
        reference_step: largest step of the RK4 reference (a converged fine-step run, also at
            least 4 times finer than the finest resolution; its own error is estimated by
            halving the step on ``reference_check`` maneuvers).
        reference_check: maneuvers on which the reference error is estimated (at most
            ``runs``: a larger value uses all of them).
        repeats: timed repeats (after compilation) per method and N; the median is reported.
        timing_runs: batch size of the timed calls (the first ``timing_runs`` maneuvers, all
            ``runs`` when it is larger; errors and failures always use all ``runs``).
        blowup_factor: a finite run whose max position error exceeds ``blowup_factor`` x
            (1 + the reference path's extent from its start) counts as a failure (blow-up).
        zero_steer_rate: snakeboard maneuvers start with ``phidot(0) = 0`` (see
            :func:`~ldap_jax.study.sample_maneuvers`).
    """

    models: tuple[str, ...] = ("snakeboard", "car")
    durations: tuple[float, ...] = (10.0, 600.0)
    methods: tuple[str, ...] = tuple(METHODS)
    resolutions: tuple[int, ...] = (250, 500, 1000, 2000, 4000)
    runs: int = 1000
    seed: int = 0
    n_out: int | None = None
    reference_step: float = 5e-3
    reference_check: int = 16
    repeats: int = 3
    timing_runs: int = 200
    blowup_factor: float = 10.0
    zero_steer_rate: bool = True

    def __post_init__(self):
        for field in ("models", "methods", "durations", "resolutions"):
            _names(field, getattr(self, field))
        if not self.models or not self.methods:
            raise ValueError(f"'models' and 'methods' must not be empty, got {self.models}, {self.methods}")
        for name in self.models:
            if name not in MODELS:
                raise ValueError(f"'models' must be among {sorted(MODELS)}, got {name!r}")
        for name in self.methods:
            if name not in METHODS:
                raise ValueError(f"'methods' must be among {sorted(METHODS)}, got {name!r}")
        if not self.resolutions:
            raise ValueError("'resolutions' must not be empty")
        for n in self.resolutions:
            _positive_int("resolutions", n)
        if len(set(self.resolutions)) != len(self.resolutions):
            raise ValueError(f"'resolutions' must be distinct, got {self.resolutions}")
        if not self.durations:
            raise ValueError("'durations' must not be empty")
        for t in self.durations:
            _positive_float("durations", t)
        for name in ("runs", "timing_runs", "repeats", "reference_check"):
            _positive_int(name, getattr(self, name))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise TypeError(f"'seed' must be an integer, got {self.seed!r}")
        _positive_float("reference_step", self.reference_step)
        _positive_float("blowup_factor", self.blowup_factor)
        if self.n_out is not None:
            _positive_int("n_out", self.n_out)
        bad = [n for n in self.resolutions if n % self.output_nodes]
        if bad:
            raise ValueError(f"'resolutions' {bad} are not multiples of n_out={self.output_nodes}")
        if self.n_out is None and self.output_nodes < 10:
            warnings.warn(
                f"StudyConfig: the resolutions {tuple(self.resolutions)} have no common factor above "
                f"{self.output_nodes}, so the max errors are taken at only {self.output_nodes + 1} times "
                "(n_out = the greatest common divisor); choose resolutions with a common factor, or n_out",
                stacklevel=3,
            )

    @property
    def output_nodes(self) -> int:
        if self.n_out is not None:
            return int(self.n_out)
        g = reduce(math.gcd, (int(n) for n in self.resolutions))
        return max(d for d in range(1, min(g, 500) + 1) if g % d == 0)  # largest divisor <= 500
