"""Symmetric compositions: higher order from a symmetric second-order step.

If ``Phi_h`` is a symmetric one-step map of order 2 (``Phi_h o Phi_{-h} = id``), the composition
``Phi_{g_s h} o ... o Phi_{g_1 h}`` with palindromic weights ``g`` (``g_i = g_{s+1-i}``,
``sum g = 1``) reaches the order the weights are built for (Yoshida 1990; Suzuki 1990;
McLachlan 1995; Kahan and Li 1997; Hairer, Lubich and Wanner, *Geometric Numerical Integration*,
Sec. V.3). Each substep is a step of the base method with its own (possibly negative) size
``g_i h``, reading the controls at its own two ends, so every structural property of the base
step holds at every substep (for RDP: the constraints, the discrete momentum equation (21) and
the horizontal equation (23)).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SCHEMES", "DEFAULT_SCHEMES", "scheme_weights", "scheme_nodes"]


def _palindrome(half: list[float]) -> tuple[float, ...]:
    return tuple(half) + tuple(half[-2::-1])


_SUZUKI_P = 1.0 / (4.0 - 4.0 ** (1.0 / 3.0))
_YOSHIDA_W = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
#: The first five weights of ``least_error11``; the middle one closes ``sum g = 1``.
_LEAST_ERROR11 = (
    0.2106183931448784,
    0.18525732199797929,
    0.18020017218187612,
    -0.4434353876646512,
    0.11522793883581066,
)

#: Composition schemes by name: ``(order, weights)``.
SCHEMES: dict[str, tuple[int, tuple[float, ...]]] = {
    # Suzuki's fractal 5-stage scheme: every substep node stays inside the step (default, order 4)
    "suzuki5": (4, (_SUZUKI_P, _SUZUKI_P, 1.0 - 4.0 * _SUZUKI_P, _SUZUKI_P, _SUZUKI_P)),
    # Yoshida's triple jump: 3 stages, but its substeps leave [t_k, t_{k+1}] (weights > 1)
    "triple_jump": (4, (_YOSHIDA_W, 1.0 - 2.0 * _YOSHIDA_W, _YOSHIDA_W)),
    # McLachlan's 5-stage order-4 scheme with a small error constant (Hairer, Lubich, Wanner V.3)
    "mclachlan5": (
        4,
        _palindrome([0.28, 0.62546642846767004501, 1.0 - 2.0 * (0.28 + 0.62546642846767004501)]),
    ),
    # Kahan and Li's 9-stage order-6 scheme (s9odr6a): every node inside the step
    "kahan_li9": (
        6,
        _palindrome(
            [
                0.39216144400731413928,
                0.33259913678935943860,
                -0.70624617255763935981,
                0.08221359629355080023,
                0.79854399093482996340,
            ]
        ),
    ),
    # 11 stages of order 6 with the least leading error found (scripts/composition_weights.py): at
    # equal error 0.75x the substeps of Kahan and Li's 9; every node inside the step (default, order 6)
    "least_error11": (6, _palindrome([*_LEAST_ERROR11, 1.0 - 2.0 * sum(_LEAST_ERROR11)])),
    # Yoshida's 7-stage order-6 scheme (solution A): fewer stages, substeps leave the step
    "yoshida7": (
        6,
        _palindrome(
            [0.784513610477560, 0.235573213359357, -1.17767998417887]
            + [1.0 - 2.0 * (0.784513610477560 + 0.235573213359357 - 1.17767998417887)]
        ),
    ),
    # Kahan and Li's 17-stage order-8 scheme (1997): the smaller error of the two order-8 schemes
    # here (default, order 8)
    "kahan_li17": (
        8,
        _palindrome(
            [
                0.13020248308889008087881763,
                0.56116298177510838456196441,
                -0.38947496264484728640807860,
                0.15884190655515560089621075,
                -0.39590389413323757733623154,
                0.18453964097831570709183254,
                0.25837438768632204729397911,
                0.29501172360931029887096624,
                -0.60550853383003451169892108,
            ]
        ),
    ),
    # McLachlan's 15-stage order-8 scheme (1995): two substeps fewer, errors 8-18x larger; its
    # substeps leave the step (nodes in [-0.05, 1.05])
    "mclachlan15": (
        8,
        _palindrome(
            [
                0.74167036435061295344822780,
                -0.40910082580003159399730010,
                0.19075471029623837995387626,
                -0.57386247111608226665638773,
                0.29906418130365592384446354,
                0.33462491824529818378495798,
                0.31529309239676659663205666,
                -0.79688793935291635401978884,
            ]
        ),
    ),
}

#: The scheme used for each order when none is named.
DEFAULT_SCHEMES = {4: "suzuki5", 6: "least_error11", 8: "kahan_li17"}


def scheme_weights(name: str) -> tuple[float, ...]:
    return SCHEMES[name][1]


def scheme_nodes(weights: tuple[float, ...]) -> tuple[float, ...]:
    """The substep boundaries as fractions of the step, ``(0, g_1, g_1 + g_2, ..., 1)``."""
    nodes = np.concatenate([[0.0], np.cumsum(weights)])
    nodes[-1] = 1.0
    return tuple(float(x) for x in nodes)


def _check_tables() -> None:  # at import: palindromic, consistent
    for name, (order, w) in SCHEMES.items():
        assert np.isclose(sum(w), 1.0), name
        assert np.allclose(w, w[::-1]), name
        # the conditions sum g^(2k+1) = 0 for 2k + 2 <= order (necessary, not sufficient: the
        # measured orders are in tests/test_order.py)
        for k in range(1, order // 2):
            assert abs(sum(x ** (2 * k + 1) for x in w)) < 1e-12, (name, 2 * k + 1)


_check_tables()
