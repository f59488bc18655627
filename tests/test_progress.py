"""The progress line per evaluation, and a benchmark method that prints it without changing its
proposals."""

from __future__ import annotations

import io

import torch

from pigp_torch.bench import METHODS, run_one
from pigp_torch.loop.progress import ProgressLine, reporting_spec
from pigp_torch.prior import PhysicsPrior


def test_line_has_step_reading_best_move_and_time():
    t = iter([0.0, 1.5, 2.0])
    out = io.StringIO()
    line = ProgressLine(
        3, ["a", "b"], unit="A", objective_unit="mA/min", out=out, clock=lambda: next(t)
    )
    line({"step": 0, "a": 0.0, "b": 0.0, "y": 1.0})
    line({"step": 1, "a": 0.5, "b": -2.0, "y": 0.5})
    first, second = out.getvalue().splitlines()
    assert first == "evaluation    1/3  y = 1 mA/min  best = 1 mA/min  move -  1.50 s/step"
    assert second == (
        "evaluation    2/3  y = 0.5 mA/min  best = 1 mA/min  move 2 A (b)  0.50 s/step"
    )


def test_minimizing_and_resumed_best():
    line = ProgressLine(10, ["a"], maximize=False, clock=lambda: 0.0)
    line.seed([[1.0], [3.0]], [2.0, 0.7])
    text = line.format(2, [2.0], 0.9)
    assert "evaluation    3/10" in text and "best = 0.7" in text and "move 1 (a)" in text


def test_reporting_spec_prints_every_tell_and_keeps_the_numbers(capsys):
    """Nelder-Mead on the simulated ring: the same table with and without the progress lines."""
    plain = run_one(METHODS["nelder-mead"], 1, _dummy_prior(), budget=6, optimum_starts=0)
    sim_names = [c for c in plain.columns if "QSS" in c]
    spec = reporting_spec(METHODS["nelder-mead"], 6, sim_names, unit="A", objective_unit="mA/min")
    capsys.readouterr()
    wrapped = run_one(spec, 1, _dummy_prior(), budget=6, optimum_starts=0)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "evaluation" in ln]
    assert len(lines) == 6 and lines[-1].split()[0] == "nelder-mead"
    assert "evaluation    6/6" in lines[-1] and " A (" in lines[-1]
    assert lines[-1].count(" mA/min") == 2
    cols = [*sim_names, "y"]
    assert torch.equal(torch.tensor(plain[cols].to_numpy()), torch.tensor(wrapped[cols].to_numpy()))


def _dummy_prior() -> PhysicsPrior:
    """A prior with the SPEAR3 knobs (Nelder-Mead does not read it)."""
    from pigp_torch.simulation import Spear3Coupling

    ring = Spear3Coupling(1)
    d = ring.dim
    return PhysicsPrior(
        x0=torch.zeros(d, dtype=torch.float64),
        f_x0=1.0,
        f_inf=0.2,
        precision=torch.eye(d, dtype=torch.float64),
        amplitude=0.1,
        noise=0.04,
        knob_names=list(ring.knob_names),
        bounds=ring.bounds,
    )


def test_a_rejected_prior_reads_as_the_method_working():
    """The prior check's notice says what it means and that it is expected; others pass as
    is."""
    from pigp_torch.loop.progress import notice_text

    out = io.StringIO()
    line = ProgressLine(3, ["a"], unit="A", objective_unit="mA/min", out=out, clock=lambda: 0.0)
    message = "physics prior rejected after 15 readings: misfit z = 4.1 > 3; stage 2 of 3"
    line({"step": 0, "a": 0.0, "y": 1.0, "notices": [message, "other"]})
    notes = [t for t in out.getvalue().splitlines() if "NOTICE" in t]
    assert notes[0] == (
        "NOTICE  prior check: the readings disagree with the physics prior after 15 readings: "
        "misfit z = 4.1 > 3; stage 2 of 3. Meaning: this machine differs from the model ring "
        "the prior was built from, so the method relaxes the prior as that stage says; expected "
        "when the machine is not the model (as in pigp demo), harmless, the run goes on"
    )
    assert notes[1] == "NOTICE  other" and notice_text("other") == "other"
