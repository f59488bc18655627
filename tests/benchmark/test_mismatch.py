"""The mismatch suite's prior transforms: what each does to the precision, shape and centre."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pigp_torch.bench import mismatch as mm
from pigp_torch.prior import PhysicsPrior

DT = torch.float64
D = 13


@pytest.fixture
def prior():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(D, D, generator=g, dtype=DT)
    P = A @ A.T + D * torch.eye(D, dtype=DT)
    C = torch.randn(D, D, generator=g, dtype=DT)
    return PhysicsPrior(
        x0=torch.linspace(-3, 3, D, dtype=DT), f_x0=1.5, f_inf=0.1, precision=P / 100,
        amplitude=1.0, noise=0.04, knob_names=[f"k{i}" for i in range(D)],
        bounds=torch.tensor([[-30.0] * D, [30.0] * D], dtype=DT),
        center_cov=C @ C.T + torch.eye(D, dtype=DT), peak_shape=2 * P / 100,
    )  # fmt: skip


def test_scaled_multiplies_precision_and_shape(prior):
    out = mm.scaled(prior, 3.0)
    torch.testing.assert_close(out.precision, 3 * prior.precision)
    torch.testing.assert_close(out.peak_shape, 3 * prior.peak_shape)
    torch.testing.assert_close(out.center_cov, prior.center_cov)


@pytest.mark.parametrize("angle", [20.0, 45.0])
def test_rotation_has_the_stated_largest_angle_and_keeps_the_spectrum(prior, angle):
    R = mm.random_rotation(D, angle, seed=0)
    torch.testing.assert_close(R @ R.T, torch.eye(D, dtype=DT), rtol=0, atol=1e-12)
    assert float(torch.linalg.det(R)) == pytest.approx(1.0, abs=1e-10)
    # the largest principal angle: arccos of the smallest real part of R's eigenvalues
    theta = math.degrees(math.acos(float(torch.linalg.eigvals(R).real.min())))
    assert theta == pytest.approx(angle, abs=1e-6)
    out = mm.rotated(prior, angle)
    torch.testing.assert_close(torch.linalg.eigvalsh(out.precision),
                               torch.linalg.eigvalsh(prior.precision))  # fmt: skip
    assert not torch.allclose(out.precision, prior.precision)


def test_miscalibration_is_the_prior_of_the_model_with_that_calibration(prior):
    """With knob k read as I_k = I_true / 1.2 by the model, a quadratic log-peak
    -(I - x0)^T P (I - x0) in model amps has precision S P S and optimum x0 / S."""
    out = mm.miscalibrated(prior, knobs=(1, 4), factor=1.2)
    s = torch.ones(D, dtype=DT)
    s[[1, 4]] = 1.2

    def model_log_peak(current):  # the true physics seen through the model's calibration
        return -((s * current - s * out.x0) @ prior.precision @ (s * current - s * out.x0))

    H = torch.autograd.functional.hessian(model_log_peak, out.x0)
    torch.testing.assert_close(-H / 2, out.precision)
    torch.testing.assert_close(out.x0 * s, prior.x0)
    torch.testing.assert_close(torch.diag(s) @ out.center_cov @ torch.diag(s), prior.center_cov)


def test_centre_shift_is_k_sigma_along_the_top_mode(prior):
    half = torch.full((D,), 30.0, dtype=DT)
    v1 = mm.centre_shift(prior, 1.0, half)
    v2 = mm.centre_shift(prior, 2.0, half)
    torch.testing.assert_close(v2, 2 * v1)
    C = 3.0 * prior.center_cov + torch.diag((0.22 * half) ** 2)
    lam = torch.linalg.eigvalsh(C)
    assert float(v1 @ v1) == pytest.approx(float(lam[-1]), rel=1e-10)
    assert float(v1 @ C @ v1) == pytest.approx(float(lam[-1]) ** 2, rel=1e-10)


def test_the_suite_lists_every_case_once():
    names = [c.name for c in mm.cases(lambda **kw: None, torch.ones(D, dtype=DT))]
    assert len(names) == len(set(names)) == 18
    assert {"control", "tune+0.02", "design-deck", "rot45", "centre+2σ", "calib+20%",
            "bg×0", "touschek×2"} <= set(names)  # fmt: skip
    mild = {c.name for c in mm.cases(lambda **kw: None, torch.ones(D, dtype=DT)) if c.mild}
    assert mild == {"tune+0.02", "tune-0.02", "scale×3", "scale÷3", "centre+1σ", "calib+20%"}


@pytest.mark.slow
def test_retuned_model_ring_has_the_new_tunes():
    ring = mm.retuned_model(0.02)
    nu = np.array(ring.ideal_lattice.get_tune(get_integer=True)[:2])
    np.testing.assert_allclose(nu, [14.1299 + 0.02, 6.2200 + 0.02], atol=2e-4)
