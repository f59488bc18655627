"""Optimizer notices reach the run log, the report and the progress line, once each."""

from __future__ import annotations

import io

import torch

from pigp_torch import optimize
from pigp_torch.data.runlog import read_log
from pigp_torch.loop.progress import ProgressLine
from pigp_torch.optimizers.base import AskTellOptimizer
from pigp_torch.reporting.report import run_report


class _Noisy(AskTellOptimizer):
    """Moves along knob 0; says once, at its third ask, that it changed its mind."""

    def ask(self):
        if self.n_told == 3:
            self.notify("prior_rejected", "physics prior rejected (test)", statistic=9.5)
        x = self.X[-1].clone()
        x[0] = min(float(x[0]) + 0.1, 1.0)
        return x


def _objective(x):
    return float(-(torch.as_tensor(x) ** 2).sum())


def test_notice_in_log_row_and_progress(tmp_path):
    bounds = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    out = io.StringIO()
    line = ProgressLine(6, ["a", "b"], out=out)
    path = tmp_path / "run.jsonl"
    opt = _Noisy(bounds)
    table = optimize(_objective, opt, torch.zeros(2), 6, knob_names=["a", "b"], log=path,
                     callback=line, handle_signals=False)  # fmt: skip
    assert len(table) == 6
    records = read_log(path)
    assert len(records.notices) == 1
    notice = records.notices[0]
    assert notice["step"] == 3 and notice["kind"] == "prior_rejected"
    assert notice["at_told"] == 3 and notice["statistic"] == 9.5
    text = out.getvalue().splitlines()
    flagged = [k for k, t in enumerate(text) if "NOTICE" in t]
    assert len(flagged) == 1 and "physics prior rejected (test)" in text[flagged[0]]
    assert "evaluation    4/6" in text[flagged[0] - 1]
    listed = run_report(path, fit=False)["notices"]
    assert any("evaluation 4: physics prior rejected" in n for n in listed)
