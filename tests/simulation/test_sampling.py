"""Simulated-data generation: the sampling design, determinism, metadata and the file round trip."""

import torch

from pigp_torch.cli import main
from pigp_torch.data.dataset import Dataset
from pigp_torch.data.sampling import sampling_design
from pigp_torch.simulation import Spear3Coupling


def test_design_fractions_and_bounds():
    """40 % Sobol over the box, the rest in Gaussian draws around the centre, all in the bounds."""
    b = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 4.0]], dtype=torch.float64)
    c = torch.tensor([0.5, 0.0, 1.0], dtype=torch.float64)
    X = sampling_design(1000, b, c, seed=1)
    assert X.shape == (1000, 3)
    assert ((X >= b[0]) & (X <= b[1])).all()
    local = X[400:]
    half = (b[1] - b[0]) / 2
    # the local draws are centred on c; their widths are log-uniform in 0.01..0.3
    assert torch.allclose(local.median(0).values, c, atol=0.02 * half.max())
    dist = ((local - c) / half).abs()
    assert (dist.median(0).values < 0.1).all()  # most draws are close
    assert (dist.max(0).values > 0.3).all()  # the widest reach well beyond 0.3 sigma
    # the global part spreads over the box: its mean is near the box centre
    assert torch.allclose(X[:400].mean(0), (b[0] + b[1]) / 2, atol=0.05 * half.max())


def test_design_is_deterministic():
    """The same seed gives the same design; another seed another one."""
    b = torch.tensor([[-1.0] * 4, [1.0] * 4], dtype=torch.float64)
    c = torch.zeros(4, dtype=torch.float64)
    assert torch.equal(sampling_design(50, b, c, seed=3), sampling_design(50, b, c, seed=3))
    assert not torch.equal(sampling_design(50, b, c, seed=3), sampling_design(50, b, c, seed=4))


def test_generate_data_command(tmp_path):
    """`pigp generate-data` writes a dataset whose values equal the simulator's, with metadata."""
    out = tmp_path / "d.npz"
    assert main(["generate-data", "--seed", "1", "--n", "300", "-o", str(out)]) == 0
    ds = Dataset.load(out)
    sim = Spear3Coupling(1)
    assert len(ds) == 300
    assert torch.allclose(ds.loss_rate, sim.loss_rate(ds.x), rtol=1e-12)
    assert ds.knob_names == sim.knob_names
    assert ds.metadata["error_seed"] == 1
    assert ds.f_inf == sim.loss_background
    assert torch.equal(ds.bounds, sim.bounds)
    assert ds.metadata["design"]["n_unstable_dropped"] == 0
    again = tmp_path / "e.npz"
    main(["generate-data", "--seed", "1", "--n", "300", "-o", str(again)])
    assert torch.equal(Dataset.load(again).x, ds.x)


def test_generate_data_rejects_bad_n(tmp_path, capsys):
    """A non-positive sample count is a clear error (exit code 2), not a crash."""
    assert main(["generate-data", "--n", "0", "-o", str(tmp_path / "x.npz")]) == 2
    assert "n must be positive" in capsys.readouterr().err
