"""The direct L-BFGS-B driver: bit for bit scipy.optimize.minimize, and its fallback."""

import numpy as np
import pytest
import scipy.optimize

import pigp_torch._utils.lbfgsb as lbfgsb
from pigp_torch._utils.lbfgsb import minimize_lbfgsb


def rosenbrock(x):
    return float(scipy.optimize.rosen(x)), scipy.optimize.rosen_der(x)


def scipy_reference(fg, x0, bounds, **options):
    return scipy.optimize.minimize(
        fg, x0, jac=True, method="L-BFGS-B", bounds=bounds, options=options
    )


CASES = [
    # (x0, bounds, options): unbounded to convergence; boxed with active bounds; one-sided
    # bounds stopped by maxiter; stopped by maxfun; the tight tolerances of the multistart.
    (np.zeros(29), None, {"maxiter": 200}),
    (np.full(29, 0.2), [(-0.5, 0.7)] * 29, {"maxiter": 200}),
    (np.full(8, 2.0), [(None, 1.5)] * 4 + [(0.5, None)] * 4, {"maxiter": 7}),
    (np.full(8, -1.0), None, {"maxfun": 12}),
    (np.full(6, 0.9), [(0.0, 1.0)] * 6, {"maxiter": 200, "maxfun": 400, "ftol": 1e-15,
                                         "gtol": 1e-11}),
]  # fmt: skip


@pytest.mark.parametrize("x0, bounds, options", CASES)
def test_direct_driver_reproduces_scipy_bit_for_bit(x0, bounds, options):
    assert lbfgsb._self_check()  # this scipy passes, so the direct loop is what runs
    ref = scipy_reference(rosenbrock, x0, bounds, **options)
    got = minimize_lbfgsb(rosenbrock, x0, bounds=bounds, **options)
    assert np.array_equal(ref.x, got.x)
    assert float(ref.fun) == float(got.fun)
    assert np.array_equal(ref.jac, got.jac)
    assert (ref.nit, ref.nfev, ref.status, ref.success) == (
        got.nit, got.nfev, got.status, got.success
    )  # fmt: skip
    assert ref.nit > 3  # a real search, not a start-point return


def test_fallback_is_scipy_and_bad_bounds_are_refused(monkeypatch):
    calls = []

    def counted(x):
        calls.append(x.copy())
        return rosenbrock(x)

    x0 = np.full(5, 0.3)
    monkeypatch.setattr(lbfgsb, "_DIRECT_OK", False)  # as after a failed self-check
    got = minimize_lbfgsb(counted, x0, maxiter=50)
    ref = scipy_reference(rosenbrock, x0, None, maxiter=50)
    assert np.array_equal(ref.x, got.x) and got.nfev == ref.nfev == len(calls)
    assert hasattr(got, "hess_inv")  # scipy's own result object
    monkeypatch.setattr(lbfgsb, "_DIRECT_OK", True)
    with pytest.raises(ValueError, match="lower bound is greater"):
        minimize_lbfgsb(rosenbrock, x0, bounds=[(1.0, 0.0)] * 5)
    with pytest.raises(ValueError, match="length of x0"):
        minimize_lbfgsb(rosenbrock, x0, bounds=[(0.0, 1.0)] * 4)


def test_start_outside_the_box_is_clipped_like_scipy():
    x0 = np.array([3.0, -3.0, 0.5])
    bounds = [(-1.0, 1.0)] * 3
    ref = scipy_reference(rosenbrock, x0, bounds, maxiter=100)
    got = minimize_lbfgsb(rosenbrock, x0, bounds=bounds, maxiter=100)
    assert np.array_equal(ref.x, got.x) and np.all(np.abs(got.x) <= 1.0)
