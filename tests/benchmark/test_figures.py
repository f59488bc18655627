"""Tests of the benchmark figures: files are written and hold one line per run plus one mean."""

import numpy as np
import pytest

from pigp_torch.bench import plot_prior_mean, plot_runs

N_RUNS, N_METHODS = 10, 5


def test_plot_runs_writes_a_line_per_run_and_a_mean_per_method(tiny_table, tmp_path):
    """Fig. 2b: thin lines = runs, thick lines = per-method means of the best-so-far gain."""
    path = tmp_path / "runs.png"
    fig = plot_runs(tiny_table, path, y="gain_fraction")
    assert path.stat().st_size > 1000
    lines = fig.axes[0].get_lines()
    assert len(lines) == N_RUNS + N_METHODS
    thick = [ln for ln in lines if ln.get_linewidth() > 2]
    assert len(thick) == N_METHODS
    pigp = tiny_table[tiny_table["method"] == "pigp"]
    expected = pigp.groupby("step")["gain_fraction"].mean().to_numpy()
    np.testing.assert_allclose(thick[0].get_ydata(), expected)
    np.testing.assert_array_equal(thick[0].get_xdata(), np.arange(1, 7))
    for ln in lines:  # best-so-far curves never decrease
        assert (np.diff(ln.get_ydata()) >= -1e-12).all()


def test_plot_runs_loss_rate_adds_optimum_lines(tiny_table, tmp_path):
    """With y = best noise-free loss rate, one dotted f* line per machine is added."""
    fig = plot_runs(tiny_table, tmp_path / "runs.pdf")
    assert (tmp_path / "runs.pdf").stat().st_size > 1000
    assert len(fig.axes[0].get_lines()) == N_RUNS + N_METHODS + 2
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels[-1] == "true optimum of each machine"  # the dotted lines say what they are
    one = tiny_table[tiny_table["machine_seed"] == tiny_table["machine_seed"].iloc[0]]
    fig = plot_runs(one, tmp_path / "one.pdf")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels[-1] == f"true optimum {one['f_star'].iloc[0]:.4g} mA/min"


def test_plot_prior_mean_compares_two_methods(tiny_table, tmp_path):
    """Fig. 2c: only pigp and pigp-zero-mean runs (2 + 2) and their two means are drawn."""
    path = tmp_path / "prior_mean.png"
    fig = plot_prior_mean(tiny_table, path, y="gain_fraction")
    assert path.stat().st_size > 1000
    assert len(fig.axes[0].get_lines()) == 4 + 2
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == [r"prior mean $f_\infty$", "prior mean 0"]
    with pytest.raises(ValueError, match="no runs of"):
        plot_prior_mean(tiny_table[tiny_table["method"] == "pigp"], path)
