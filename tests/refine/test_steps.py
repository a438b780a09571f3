"""The Gauss-Newton step of the trajectory fit and its damping (hamid/refine/steps.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hamid.refine.steps import Damping, Normal


def _linear_problem(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, Normal]:
    """Residuals r(h) = r0 - J h of one segment, linear in 2 parameters and 3 state values,
    and their normal equations (H = J'J, g = J'r0)."""
    rng = np.random.default_rng(seed)
    r0, J = rng.standard_normal(40), rng.standard_normal((40, 5))
    H, g = J.T @ J, J.T @ r0
    t, x = slice(0, 2), slice(2, 5)
    normal = Normal(cost=(r0**2)[None, :], H_tt=H[None, t, t], g_t=g[None, t],
                    H_xx=H[None, x, x], H_xt=H[None, x, t], g_x=g[None, x])
    return r0, J, H, normal


@pytest.mark.parametrize("damping", [0.0, 0.5, 20.0])
def test_a_step_foretells_the_drop_of_a_linear_misfit_exactly(damping):
    """For residuals linear in the step, the quadratic model is the misfit: the drop
    foretold is the drop, damped or not; undamped, the step is least squares' (lstsq)."""
    r0, J, H, normal = _linear_problem(0)
    d_theta, d_x, _, predicted = normal.step(damping)
    h = np.concatenate([d_theta, d_x[0]])
    assert predicted == pytest.approx(r0 @ r0 - np.sum((r0 - J @ h) ** 2), rel=1e-10)
    if damping == 0.0:
        np.testing.assert_allclose(h, np.linalg.lstsq(J, r0, rcond=None)[0], rtol=1e-10)
    else:   # Marquardt's: (H + damping diag H) h = g
        np.testing.assert_allclose((H + damping * np.diag(np.diag(H))) @ h, J.T @ r0,
                                   rtol=1e-9, atol=1e-12)


def test_the_damping_grows_on_failures_and_falls_by_how_well_steps_were_foretold():
    failed = Damping().failed()
    assert (failed.factor, failed.growth) == (1e-3, 4.0)
    assert failed.failed().factor == pytest.approx(4e-3)
    assert failed.failed().failed().factor == pytest.approx(3.2e-2)
    at = Damping(0.03)
    assert at.succeeded(1.0, 1.0).factor == pytest.approx(0.01)   # as foretold: a third
    assert at.succeeded(0.5, 1.0).factor == pytest.approx(0.03)   # half: kept
    assert at.succeeded(1e-3, 1.0).factor == pytest.approx(0.03 * (1 + 0.998**3))
    assert at.succeeded(3.0, 1.0).factor == pytest.approx(0.01)   # more than foretold
    assert failed.succeeded(1.0, 1.0).growth == 2.0   # growth starts again
    assert Damping(2e-6).succeeded(1.0, 1.0).factor == 0.0   # below 1e-6: undamped
