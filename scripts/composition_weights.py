"""Derive the weights of the 11-stage order-6 composition ``least_error11`` (``lj.RDP(order=6)``).

A symmetric second-order step is the flow of a modified vector field with odd powers of the step
only, ``Phi_h = exp(h X1 + h^3 X3 + h^5 X5 + h^7 X7 + ...)``. A palindromic composition
``Phi_{g_s h} o ... o Phi_{g_1 h}`` is ``exp(h X1 + h^3 L3 + h^5 L5 + h^7 L7 + ...)`` with
``L3 = (sum g^3) X3`` and ``L5 = (sum g^5) X5 + c(g) [X1, [X1, X3]]``: it has order 6 when
``sum g = 1``, ``sum g^3 = 0``, ``sum g^5 = 0`` and ``c(g) = 0``, and its leading error is ``L7``.

The script computes ``log(prod_i exp(g_i h X1 + (g_i h)^3 X3 + ...))`` as a power series in ``h``
whose coefficients are matrices (random ``X1 ... X7``, 5 x 5), reads the conditions off ``L3`` and
``L5``, and minimises ``|L7|`` (Frobenius norm, mean over three random sets) over the palindromic
weights of ``s`` stages that satisfy them (SLSQP from random starts, then the conditions solved to
round-off with all but the last three half weights held). With 11 stages the family has two free weights
(Sofroniou and Spaletta, Optim. Methods Softw. 20 (2005), built order-6 schemes of this size the
same way). It prints every order-6 scheme's ``|L7|`` and its effective error ``s |L7|^(1/6)``
(the relative cost of reaching a given accuracy, up to one constant):

    scheme              stages  |L7|      s |L7|^(1/6)
    kahan_li9           9       6.97e-02  5.77
    yoshida7            7       1.75e+00  7.68
    least_error11       11      3.57e-03  4.30

so ``least_error11`` reaches a given error with about 0.75x the substeps of Kahan and Li's 9-stage
scheme. Measured on the models (256 random maneuvers over 10 s, ``scripts/bench.py``'s): 1e-6 m
with 26 steps (286 substeps) instead of 40 (360) for the snakeboard.

    python scripts/composition_weights.py [--stages 11] [--starts 40] [--seed 1]

(about 5 s per start on one core: 3.5 minutes for 40). The search is local from random starts:
other starts may find other minima; the one printed last is the best found. With the defaults,
start 9 finds ``|L7| = 3.5696e-3`` at weights within 3e-8 of the library's, which an earlier run of
the same search (the series multiplied term by term, the SLSQP step polished from 5 digits) gave:
the minimum is flat, and both sets meet the conditions to round-off. No start finds a smaller
``|L7|``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

DEGREE = 7  # highest power of h kept
SIZE = 5  # random matrices X1, X3, X5, X7 of this size
SEEDS = (1, 2, 3)


def _random_fields(seed: int) -> dict[int, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {k: rng.standard_normal((SIZE, SIZE)) / np.sqrt(SIZE) for k in (1, 3, 5, 7)}


def _nilpotent_exp(m: np.ndarray) -> np.ndarray:
    """``exp`` of a strictly block upper triangular matrix (its series ends at the 7th power)."""
    out, term = np.eye(len(m)), np.eye(len(m))
    for k in range(1, DEGREE + 1):
        term = term @ m / k
        out = out + term
    return out


def _nilpotent_log(p: np.ndarray) -> np.ndarray:
    """``log`` of the identity plus a strictly block upper triangular matrix."""
    t = p - np.eye(len(p))
    out, power = np.zeros_like(p), np.eye(len(p))
    for k in range(1, DEGREE + 1):
        power = power @ t
        out = out + (-1) ** (k + 1) / k * power
    return out


def log_composition(weights, fields: dict[int, np.ndarray]) -> list[np.ndarray]:
    """The coefficients ``L_k`` of ``log`` of the composition, ``h^k`` for ``k <= 7``.

    A power series ``sum_k A_k h^k`` truncated after ``h^7`` is held as the block upper triangular
    Toeplitz matrix with blocks ``A_{j - i}`` (``j >= i``): the product of two series is the
    product of their matrices, and ``exp`` and ``log`` are finite sums (the matrices of series
    without constant term are nilpotent)."""
    blocks = DEGREE + 1

    def matrix(series: dict[int, np.ndarray]) -> np.ndarray:
        m = np.zeros((blocks * SIZE, blocks * SIZE))
        for k, a in series.items():
            for i in range(blocks - k):
                m[i * SIZE : (i + 1) * SIZE, (i + k) * SIZE : (i + k + 1) * SIZE] = a
        return m

    total = np.eye(blocks * SIZE)
    for g in weights:
        total = _nilpotent_exp(matrix({k: g**k * x for k, x in fields.items()})) @ total
    log = _nilpotent_log(total)
    return [log[:SIZE, k * SIZE : (k + 1) * SIZE] for k in range(blocks)]


def error_terms(weights, seeds=SEEDS) -> dict[int, float]:
    """``|L3|, |L5|, |L7|`` of a composition (Frobenius norms, mean over random fields)."""
    norms = [
        [np.linalg.norm(log_composition(weights, _random_fields(s))[k]) for k in (3, 5, 7)] for s in seeds
    ]
    return dict(zip((3, 5, 7), np.mean(norms, axis=0)))


def order_6_conditions(weights) -> np.ndarray:
    """``sum g^3``, and the two coefficients of ``L5`` on ``X5`` and ``[X1, [X1, X3]]``."""
    x = _random_fields(11)
    basis = np.stack([x[5].ravel(), _bracket(x[1], _bracket(x[1], x[3])).ravel()], 1)
    coefficients = np.linalg.lstsq(basis, log_composition(weights, x)[5].ravel(), rcond=None)[0]
    return np.concatenate([[np.sum(np.asarray(weights) ** 3)], coefficients])


def _bracket(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a @ b - b @ a


def palindrome(half) -> tuple[float, ...]:
    """The weights of an odd number of stages from the first half, the middle weight closing
    ``sum g = 1``."""
    half = [float(x) for x in half]
    return (*half, 1.0 - 2.0 * sum(half), *half[::-1])


def search(stages: int, starts: int, seed: int, log=print) -> np.ndarray:
    """The first half of the weights of least ``|L7|`` found (see the module docstring)."""
    from scipy.optimize import fsolve, minimize

    m = (stages - 1) // 2
    rng = np.random.default_rng(seed)
    best = None
    for i in range(starts):
        r = minimize(
            lambda x: error_terms(palindrome(x))[7],
            rng.uniform(-0.6, 0.6, m),
            method="SLSQP",
            constraints={"type": "eq", "fun": lambda x: order_6_conditions(palindrome(x))},
            options={"maxiter": 300, "ftol": 1e-14},
        )
        if not np.max(np.abs(order_6_conditions(palindrome(r.x)))) <= 1e-10:  # NaN too
            continue
        value = error_terms(palindrome(r.x))[7]
        if not np.isfinite(value):
            continue
        if best is None or value < best[0]:
            best = (value, r.x)
            log(f"  start {i}: |L7| = {value:.4e}, s |L7|^(1/6) = {stages * value ** (1 / 6):.4f}")
    if best is None:
        raise RuntimeError("no start satisfied the order conditions")
    x = best[1]

    def held(y):
        return order_6_conditions(palindrome(np.concatenate([x[:-3], y])))

    y = x[-3:]
    for _ in range(3):  # the three conditions to round-off, the other weights held
        y = fsolve(held, y, xtol=1e-15)
    return np.concatenate([x[:-3], y])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stages", type=int, default=11, help="odd number of stages, >= 9 (default 11)")
    parser.add_argument("--starts", type=int, default=40, help="random starts (default 40)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the starts (default 1)")
    args = parser.parse_args(argv)
    if args.stages < 9 or args.stages % 2 == 0:
        parser.error(f"--stages must be odd and >= 9, got {args.stages}")
    if args.starts < 1:
        parser.error(f"--starts must be positive, got {args.starts}")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from ldap_jax.integrators import SCHEMES

    print(f"{'scheme':<20}{'stages':<8}{'|L7|':<10}s |L7|^(1/6)")
    for name, (order, weights) in SCHEMES.items():
        if order == 6:
            e7 = error_terms(weights)[7]
            print(f"{name:<20}{len(weights):<8}{e7:<10.2e}{len(weights) * e7 ** (1 / 6):.2f}")
    t0 = time.perf_counter()
    half = search(args.stages, args.starts, args.seed)
    weights = palindrome(half)
    e7 = error_terms(weights)[7]
    print(f"searched {args.stages} stages, {args.starts} starts in {time.perf_counter() - t0:.0f} s:")
    print(f"  first half {[float(x) for x in half]}, middle {weights[len(half)]!r}")
    effective = args.stages * e7 ** (1 / 6)
    print(f"  conditions {order_6_conditions(weights)}, |L7| {e7:.4e}, s |L7|^(1/6) {effective:.4f}")


if __name__ == "__main__":
    main()
