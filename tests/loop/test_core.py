"""Tests of the optimization loop: the evaluation table, the budget, and restoring the knobs."""

from __future__ import annotations

import pytest
import torch
from botorch.models import SingleTaskGP
from gpytorch.kernels import RBFKernel, ScaleKernel

from pigp_torch.loop import optimize
from pigp_torch.machine import GuardedMachine
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.optimizers.bayesopt import BayesOpt
from tests.loop.problems import BOUNDS, D, bowl


class Walk(AskTellOptimizer):
    """Deterministic test optimizer: each ask moves the last point by +0.1 on every knob."""

    name = "walk"

    def __init__(self, bounds, fail_at=None, **kwargs):
        super().__init__(bounds, **kwargs)
        self.fail_at = fail_at

    def ask(self):
        if self.fail_at is not None and self.n_told == self.fail_at:
            raise RuntimeError("optimizer failure")
        return torch.clamp(self.X[-1] + 0.1, self.bounds[0], self.bounds[1])


class BowlMachine(GuardedMachine):
    """A noise-free machine reading bowl(x); optionally raises on a given read."""

    def __init__(self, fail_on_read=None, **kwargs):
        super().__init__(BOUNDS, ["qs1", "qs2"], **kwargs)
        self.fail_on_read = fail_on_read
        self.n_reads = 0
        self.n_sets = 0

    def _apply(self, x):
        self.n_sets += 1

    def read(self):
        self.n_reads += 1
        if self.n_reads == self.fail_on_read:
            raise KeyboardInterrupt
        return bowl(self._x)


def test_table_columns_dtypes_and_values():
    """The table has one row per evaluation, x0 in row 0, float64 knobs and the objective's y."""
    calls = []

    def f(x):
        calls.append(x.clone())
        return bowl(x)

    x0 = [-0.5, -0.6]
    table = optimize(f, Walk(BOUNDS), x0, budget=5)
    assert list(table.columns) == ["step", "x0", "x1", "y", "method", "ask_time_s", "eval_time_s"]
    assert table.shape == (5, 7) and len(calls) == 5
    assert table["step"].tolist() == [0, 1, 2, 3, 4]
    assert table["step"].dtype == "int64"
    assert all(table[c].dtype == "float64" for c in ("x0", "x1", "y", "ask_time_s"))
    assert table.loc[0, ["x0", "x1"]].tolist() == x0
    assert table["x0"].tolist() == pytest.approx([-0.5, -0.4, -0.3, -0.2, -0.1])
    assert table["y"].tolist() == [bowl(c) for c in calls]
    assert set(table["method"]) == {"walk"}
    assert (table[["ask_time_s", "eval_time_s"]] >= 0).all().all()


def test_budget_counts_every_evaluation_and_callback_sees_rows():
    """budget = evaluations including x0; the callback receives each row as the table has it."""
    rows = []
    opt = Walk(BOUNDS)
    table = optimize(
        bowl, opt, torch.zeros(2), 7, callback=rows.append, method="mine", knob_names=["a", "b"]
    )
    assert len(table) == 7 and opt.n_told == 7
    assert rows == table.to_dict("records")
    assert rows[3]["method"] == "mine" and rows[3]["a"] == pytest.approx(0.3)
    one = optimize(bowl, Walk(BOUNDS), torch.zeros(2), 1)
    assert len(one) == 1 and one.loc[0, "y"] == bowl(torch.zeros(2))


def test_machine_knob_names_and_default_restore_initial():
    """On a machine the columns use its knob names and the initial knobs are set back at the end."""
    m = BowlMachine(x_init=[0.05, 0.05])
    table = optimize(m, Walk(BOUNDS), [-0.5, -0.5], 4)
    assert list(table.columns[1:3]) == ["qs1", "qs2"]
    assert m.n_reads == 4
    assert torch.equal(m.get(), torch.tensor([0.05, 0.05], dtype=D))
    assert table["qs1"].tolist() == pytest.approx([-0.5, -0.4, -0.3, -0.2])


def test_restore_best_and_none():
    """restore='best' sets the best observed point, restore='none' leaves the last one."""
    m = BowlMachine()
    table = optimize(m, Walk(BOUNDS), [-0.2, -0.9], 8, restore="best")
    best = table.loc[table["y"].idxmax(), ["qs1", "qs2"]].tolist()
    assert best == pytest.approx([0.4, -0.3])  # |x - x*|^2 = 0.02, the walk's closest point
    assert m.get().tolist() == pytest.approx(best)
    m2 = BowlMachine()
    table = optimize(m2, Walk(BOUNDS, maximize=False), [-0.2, -0.9], 8, restore="best")
    assert m2.get().tolist() == pytest.approx(table.loc[table["y"].idxmin(), ["qs1", "qs2"]])
    m3 = BowlMachine()
    table = optimize(m3, Walk(BOUNDS), [-0.2, -0.9], 3, restore="none")
    assert m3.get().tolist() == pytest.approx([0.0, -0.7])


def test_restore_initial_when_the_optimizer_or_the_machine_fails():
    """An exception from ask() or a KeyboardInterrupt in read() sets the initial knobs back."""
    m = BowlMachine(x_init=[0.1, 0.2])
    with pytest.raises(RuntimeError, match="optimizer failure"):
        optimize(m, Walk(BOUNDS, fail_at=3), [-0.5, -0.5], 10, restore="best")
    assert m.n_reads == 3 and torch.equal(m.get(), torch.tensor([0.1, 0.2], dtype=D))
    m = BowlMachine(x_init=[0.1, 0.2], fail_on_read=2)
    with pytest.raises(KeyboardInterrupt):
        optimize(m, Walk(BOUNDS), [-0.5, -0.5], 10)
    assert torch.equal(m.get(), torch.tensor([0.1, 0.2], dtype=D))
    m = BowlMachine(x_init=[0.1, 0.2], fail_on_read=2)
    with pytest.raises(KeyboardInterrupt):
        optimize(m, Walk(BOUNDS), [-0.5, -0.5], 10, restore="none")
    assert m.get().tolist() == pytest.approx([-0.4, -0.4])


def test_refused_step_restores_through_ramp_within_max_step():
    """A far start point and every proposal farther than the step limit are ramped to; a
    refused setting (outside the bounds) ends in a ramp back to the initial knobs."""

    class Jump(Walk):
        def ask(self):
            return self.X[-1] + 0.2  # 0.7, 0.9, then 1.1: outside the bounds

    m = BowlMachine(max_step=0.15)  # 0.15 of the half-range 1 = 0.15 per knob per set
    with pytest.raises(ValueError, match="outside bounds"):
        optimize(m, Jump(BOUNDS), [0.5, 0.0], 5)
    assert m.n_reads == 3
    # ramp 0 -> 0.5 in 4 sets (steps <= 0.99 * 0.15), each +0.2 in 2, the refused 1.1 in none,
    # the restore 0.9 -> 0 in ceil(0.9 / 0.1485) = 7
    assert m.n_sets == 4 + 2 + 2 + 7
    assert torch.equal(m.get(), torch.zeros(2, dtype=D))


def test_failed_restore_warns_and_keeps_the_original_error():
    """If restoring after a failure fails too, a warning says so and the original error escapes."""

    class Broken(BowlMachine):
        def _apply(self, x):
            super()._apply(x)
            if self.n_reads >= 2:
                raise OSError("hardware down")

    m = Broken(fail_on_read=2)
    with pytest.warns(UserWarning, match="could not restore.*hardware down"):
        with pytest.raises(KeyboardInterrupt):
            optimize(m, Walk(BOUNDS), [-0.5, -0.5], 10)
    assert m.get().tolist() == pytest.approx([-0.4, -0.4])


def test_progress_bar_counts_steps(capsys):
    """progress=True shows a tqdm bar labelled by the method that reaches budget/budget."""
    optimize(bowl, Walk(BOUNDS), torch.zeros(2), 6, progress=True)
    err = capsys.readouterr().err
    assert "walk" in err and "6/6" in err


def test_bad_arguments_raise():
    """Bad budget, restore mode, knob names or a missing x0 raise ValueError."""
    with pytest.raises(ValueError, match="budget"):
        optimize(bowl, Walk(BOUNDS), torch.zeros(2), 0)
    with pytest.raises(ValueError, match="restore"):
        optimize(bowl, Walk(BOUNDS), torch.zeros(2), 2, restore="last")
    with pytest.raises(ValueError, match="clash"):
        optimize(bowl, Walk(BOUNDS), torch.zeros(2), 2, knob_names=["y", "a"])
    with pytest.raises(ValueError, match="knob names"):
        optimize(bowl, Walk(BOUNDS), torch.zeros(2), 2, knob_names=["a"])
    with pytest.raises(ValueError, match="x0 is required"):
        optimize(bowl, Walk(BOUNDS), None, 2)
    with pytest.raises(ValueError, match="x0"):
        optimize(bowl, Walk(BOUNDS), torch.zeros(3), 2)


def test_bayesopt_through_the_loop_improves_a_machine():
    """BayesOpt driven by the loop from the machine's current knobs climbs the bowl to >= 0.98."""

    def factory(X, Y):
        k = ScaleKernel(RBFKernel(ard_num_dims=2)).to(D)
        k.base_kernel.lengthscale = torch.tensor([0.5, 0.5], dtype=D)
        k.outputscale = 0.5
        gp = SingleTaskGP(X, Y, torch.full_like(Y, 1e-4), covar_module=k, outcome_transform=None)
        return gp.eval()

    m = BowlMachine(x_init=[-0.6, 0.6])
    bo = BayesOpt(BOUNDS, factory, step_limit=0.3, num_restarts=2, raw_samples=32)
    table = optimize(m, bo, None, 12, restore="best")
    assert table.loc[0, "y"] == pytest.approx(bowl([-0.6, 0.6]))  # 0.17
    assert table["y"].max() >= 0.98
    assert set(table["method"]) == {"bo"}
    assert bowl(m.get()) == pytest.approx(table["y"].max())
