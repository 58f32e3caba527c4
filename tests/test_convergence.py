"""Every integrator converges to the diffrax reference with its order, on random maneuvers.

Positions and node velocities: for RDP the velocities are read from the carried momenta (the
inverse of the reduced Legendre transform), second-order accurate at alpha = 1/2 and at least
first order otherwise; for RK they are the state's.

The runs are made without diagnostics (``simulate(..., diagnostics=False)``: positions, velocities
and the result only), which nothing here reads: a smaller program to compile per integrator.
"""

import numpy as np
import pytest
from helpers import (
    CONV_GRID,
    CONV_NS,
    CONV_T,
    convergence_case,
    convergence_runs,
    fitted_order,
    integrators,
    systems,
)

SYSTEMS = systems()


def errors(sys_name, int_name, order):
    """Max position (x, y, theta) and velocity errors over the batch and the grid, per N."""
    _, ref = convergence_case(sys_name)
    runs = convergence_runs(sys_name, int_name, diagnostics=False)
    ns = CONV_NS[min(order, 4)]
    grid = ns[0]  # compare on the nodes of the coarsest run
    sub = CONV_GRID // grid
    q_ref, qdot_ref = ref.q[:, ::sub], ref.qdot[:, ::sub]
    pos, vel = [], []
    for n in ns:
        run = runs[n]
        assert not bool(np.any(run.failed)), run.result
        q, qdot = run.q[:, :: n // grid], run.qdot[:, :: n // grid]
        pos.append(float(np.max(np.linalg.norm(q[..., :3] - q_ref[..., :3], axis=-1))))
        vel.append(float(np.max(np.linalg.norm(qdot - qdot_ref, axis=-1))))
    return ns, pos, vel


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
@pytest.mark.parametrize("int_name, integrator, order", integrators(), ids=[i[0] for i in integrators()])
def test_observed_order(sys_name, int_name, integrator, order):
    ns, pos, vel = errors(sys_name, int_name, order)
    hs = [CONV_T / n for n in ns]
    p_pos, p_vel = fitted_order(hs, pos), fitted_order(hs, vel)
    print(f"{sys_name} {int_name}: position errors {pos} order {p_pos:.3f}; velocity {vel} order {p_vel:.3f}")
    assert p_pos > order - 0.15, (pos, p_pos)
    assert p_vel > min(order, 2) - 0.2, (vel, p_vel)
    assert pos[-1] < 0.05
