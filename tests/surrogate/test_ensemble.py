"""The surrogate ensemble: its log-excess and Hessian are the members' means; save/load is exact."""

import pytest
import torch

from pigp_torch.surrogate import (
    SurrogateEnsemble,
    SurrogateMLP,
    load_surrogate,
    save_surrogate,
    train_ensemble,
)


def members(k=3, d=3):
    b = torch.tensor([[-1.0] * d, [1.0] * d], dtype=torch.float64)
    out = []
    for s in range(k):
        torch.manual_seed(s)
        out.append(SurrogateMLP(b, 0.2, widths=(8, 8), target_mean=1.0, target_std=0.5).double())
    return out


def test_mean_of_members_and_hessian():
    """t(x) is the mean of the members' t_k(x); its Hessian the mean of their Hessians."""
    ms = members()
    ens = SurrogateEnsemble(ms)
    x = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.5, -0.5]], dtype=torch.float64)
    expected = torch.stack([m.log_excess(x) for m in ms]).mean(0)
    assert torch.allclose(ens.log_excess(x), expected, rtol=1e-14)
    assert torch.allclose(ens(x), 0.2 + torch.exp(expected), rtol=1e-14)
    x0 = x[0]
    H = torch.autograd.functional.hessian(ens.log_excess, x0)
    Hk = [torch.autograd.functional.hessian(m.log_excess, x0) for m in ms]
    assert torch.allclose(H, sum(Hk) / len(Hk), rtol=1e-12, atol=1e-14)


def test_members_must_agree():
    """Members with other bounds or f_inf are refused."""
    a = members(1)[0]
    b = SurrogateMLP(torch.tensor([[-2.0] * 3, [2.0] * 3], dtype=torch.float64), 0.2).double()
    with pytest.raises(ValueError, match="share"):
        SurrogateEnsemble([a, b])
    with pytest.raises(ValueError, match="at least one"):
        SurrogateEnsemble([])


def test_save_load_round_trip(tmp_path):
    """An ensemble saved and loaded gives bit-identical outputs and keeps its size."""
    ens = SurrogateEnsemble(members()).double().eval()
    path = save_surrogate(ens, tmp_path / "e.pt", {"note": "x"})
    back, meta = load_surrogate(path)
    assert isinstance(back, SurrogateEnsemble) and len(back.members) == 3
    x = torch.rand(5, 3, dtype=torch.float64)
    assert torch.equal(back(x), ens(x)) and meta == {"note": "x"}


def test_train_ensemble_uses_distinct_seeds():
    """train_ensemble trains members with different seeds (different weights), one report each."""
    g = torch.Generator().manual_seed(0)
    X = 2 * torch.rand(400, 2, generator=g, dtype=torch.float64) - 1
    y = 0.2 + 1.0 / torch.sqrt(1 + 3 * (X**2).sum(-1))
    b = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    ens, reports = train_ensemble(
        (X, y), f_inf=0.2, bounds=b, n_members=2, max_epochs=3, widths=(8,), progress=False
    )
    assert len(reports) == 2
    w0, w1 = (m.net[0].weight for m in ens.members)
    assert not torch.equal(w0, w1)
