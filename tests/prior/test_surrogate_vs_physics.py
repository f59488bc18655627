"""Agreement as numbers: surrogate Hessian vs the exact simulator Hessian, and transfer."""

import pytest
import torch

from pigp_torch.data.sampling import generate_dataset
from pigp_torch.prior import log_excess_hessian, prior_from_model
from pigp_torch.simulation import Spear3Coupling
from pigp_torch.surrogate import train_ensemble


def top_eigvec_cosines(A, B, k=3):
    _, Va = torch.linalg.eigh(A)
    _, Vb = torch.linalg.eigh(B)
    return [float((Va[:, -i] @ Vb[:, -i]).abs()) for i in range(1, k + 1)]


@pytest.mark.slow
def test_surrogate_hessian_matches_simulator():
    """Data -> 3-member surrogate: its Hessian of log(f - f_inf) at the true optimum is within 12 %
    (Frobenius) of the exact autograd Hessian, top-2 eigenvectors |cos| >= 0.98, third >= 0.95.

    Measured: 3.5 %, 5.4 % and 6.2 % in three runs on the machine the test was written on; on an
    AMD EPYC machine 6.2 % run alone (cosines 0.99996, 0.9996, 0.9795) and 9.8 % inside the slow
    suite. Float32 training differs in round-off with the CPU and, evidently, with what ran before
    in the process; the exact Hessian itself is reproducible to 1e-8. The members alone spread
    from 3 % to 11.5 %, which is why the prior uses the ensemble mean."""
    sim = Spear3Coupling(error_seed=1)
    data = generate_dataset(sim, 100_000, seed=0, progress=False)
    surrogate, _ = train_ensemble(data, n_members=3, progress=False)
    x_star, _ = sim.optimum()
    H_exact, _, _ = log_excess_hessian(sim.loss_rate, x_star, sim.loss_background)
    H_nn, _, _ = log_excess_hessian(surrogate, x_star, sim.loss_background)
    rel_h = float(torch.linalg.norm(H_nn - H_exact) / torch.linalg.norm(H_exact))
    assert rel_h <= 0.12, rel_h
    cosines = top_eigvec_cosines(-H_nn, -H_exact)
    assert min(cosines[:2]) >= 0.98 and cosines[2] >= 0.95, cosines


@pytest.mark.slow
def test_surrogate_precision_matches_the_authors_kernel():
    """The paper's chain (simulated data of the model ring -> 3-network surrogate -> autograd
    Hessian at the ring's optimum) passes the same fidelity check against the authors' SPEAR3
    kernel as the exact model: cosines >= 0.95, r >= 0.9, n/n+9 positive, condition 100-1000."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "simulation"))
    from test_fidelity import authors_precision, fidelity, passes

    names, P = authors_precision()
    sim = Spear3Coupling(error_seed=0)
    data = generate_dataset(sim, 100_000, seed=0, progress=False)
    surrogate, _ = train_ensemble(data, n_members=3, progress=False)
    x_star, _ = sim.optimum()
    H_nn, _, _ = log_excess_hessian(surrogate, x_star, sim.loss_background)
    m = fidelity((-H_nn / 2).detach().numpy(), P, names)
    assert passes(m), m


@pytest.mark.slow
def test_precision_transfers_between_machines():
    """The exact precision of another error seed has the same dominant eigen-directions."""
    priors = []
    for seed in (1, 3):
        sim = Spear3Coupling(error_seed=seed)
        priors.append(
            prior_from_model(
                sim.loss_rate,
                sim.bounds,
                f_inf=sim.loss_background,
                noise=0.04,
                x0=sim.optimum()[0],
            )
        )
    a, b = (p.normalized_precision() for p in priors)
    assert min(top_eigvec_cosines(a, b)) >= 0.99
    assert float(torch.linalg.norm(a - b) / torch.linalg.norm(a)) < 0.3
