"""Wrong-model cases of the ARES-EA benchmark: the machine departs from the model as stated."""

from __future__ import annotations

import json

import pandas as pd
import pytest
import torch

pytest.importorskip("cheetah")

from pigp_torch.cli import main
from pigp_torch.machines.ares_ea.cases import (
    CASE_TEXT,
    MODEL_ERROR_CASES,
    beam_outside,
    case_machine_parts,
    case_trial,
    check_case,
)
from pigp_torch.machines.ares_ea.command import MODEL_ERROR_HELP
from pigp_torch.machines.ares_ea.machine import AresMachine
from pigp_torch.machines.ares_ea.simulation import (
    INCOMING_NAMES,
    AresSegment,
    load_lattice,
    load_trials,
)

D = torch.float64
OFF = torch.zeros(5, dtype=D)  # every magnet off: the segment is a drift


@pytest.fixture(scope="module")
def trials():
    return load_trials()


@pytest.fixture(scope="module")
def segment():
    return AresSegment()


def drift_reading(seg: AresSegment, inc: torch.Tensor, mis: torch.Tensor) -> torch.Tensor:
    """Closed form of the screen reading with all magnets off: a drift of the segment's length
    L, an uncorrelated beam (mu + L mu', sqrt(sigma^2 + L^2 sigma'^2)), minus the screen's
    misalignment."""
    L = seg.length
    v = dict(zip(INCOMING_NAMES, inc.unbind(), strict=True))
    return torch.stack(
        [
            v["mu_x"] + L * v["mu_xp"] - mis[6],
            (v["sigma_x"] ** 2 + L**2 * v["sigma_xp"] ** 2).sqrt(),
            v["mu_y"] + L * v["mu_yp"] - mis[7],
            (v["sigma_y"] ** 2 + L**2 * v["sigma_yp"] ** 2).sqrt(),
        ]
    )


def machine(trial, case):
    t, seg = case_machine_parts(trial, case)
    return AresMachine(t, objective="mae", segment=seg)


def test_drift_closed_form_matches_the_segment(trials, segment):
    """The closed form the case tests use is right for the published trial (2.05 m drift)."""
    t = trials[7]
    torch.testing.assert_close(
        segment.observe(OFF, t.incoming, t.misalignments),
        drift_reading(segment, t.incoming, t.misalignments),
        rtol=1e-12,
        atol=1e-15,
    )


def test_beam_outside_is_outside_the_ranges_as_stated(trials):
    """beam-outside: the 8 transverse parameters are 1.25-2x the prior range's limit (centroids
    with the trial's sign), energy, bunch length and energy spread unchanged, deterministic per
    trial and different between trials."""
    rng = load_lattice()["incoming_beam_ranges"]
    lo, hi = torch.tensor(rng["low"], dtype=D), torch.tensor(rng["high"], dtype=D)
    for idx in (0, 11, 49):
        t = trials[idx]
        inc = beam_outside(t)
        torch.testing.assert_close(inc, beam_outside(t), rtol=0, atol=0)
        for i in range(1, 9):
            limit = hi[i] if INCOMING_NAMES[i].startswith("sigma") else hi[i].abs()
            ratio = float(inc[i].abs() / limit)
            assert 1.25 <= ratio <= 2.0, (idx, INCOMING_NAMES[i], ratio)
            assert not (lo[i] <= inc[i] <= hi[i])
        for i in (1, 2, 3, 4):
            assert (inc[i] < 0) == (t.incoming[i] < 0)
        for i in (0, 9, 10):
            assert inc[i] == t.incoming[i]
    assert not torch.equal(beam_outside(trials[0])[1:9], beam_outside(trials[1])[1:9])


def test_beam_outside_machine_reads_the_transformed_beam(trials, segment):
    """The beam-outside machine's reading with the magnets off is the drift of the transformed
    beam, not of the trial's; the target stays the trial's."""
    t = trials[4]
    m = machine(t, "beam-outside")
    got = m.true_observables(OFF)
    torch.testing.assert_close(got, drift_reading(segment, beam_outside(t), t.misalignments))
    published = drift_reading(segment, t.incoming, t.misalignments)
    assert float((got - published).abs().max()) > 100e-6
    assert torch.equal(m.target, t.target)


def test_misalign_3x_shifts_the_screen_reading_by_twice_the_screen_offset(trials, segment):
    """misalign-3x: misalignments are 3x the trial's; with the magnets off (a misaligned
    quadrupole at k1 = 0 is a drift) the reading moves by -2x the screen's own offset, sizes
    unchanged."""
    t = trials[9]
    assert torch.equal(case_trial(t, "misalign-3x").misalignments, 3 * t.misalignments)
    m = machine(t, "misalign-3x")
    diff = m.true_observables(OFF) - segment.observe(OFF, t.incoming, t.misalignments)
    expected = torch.stack([-2 * t.misalignments[6], D_0(), -2 * t.misalignments[7], D_0()])
    torch.testing.assert_close(diff, expected, rtol=1e-9, atol=1e-15)
    assert float(diff.abs().max()) > 10e-6  # trial 9's screen offset is not negligible
    # with the quadrupoles on, the quadrupoles' misalignments steer the beam too
    on = torch.tensor([10.0, -10.0, 0.0, 10.0, 0.0], dtype=D)
    d_on = m.true_observables(on) - segment.observe(on, t.incoming, t.misalignments)
    assert float((d_on[[0, 2]] - expected[[0, 2]]).abs().max()) > 1e-6


def D_0():
    return torch.zeros((), dtype=D)


def test_quad_cal_10_acts_with_110_percent_of_k1(trials, segment):
    """quad-cal-10: the machine at setting x reads what the nominal segment reads at the
    quadrupoles' k1 x 1.10 (correctors as set); with the quadrupoles off nothing changes."""
    t = trials[2]
    m = machine(t, "quad-cal-10")
    x = torch.tensor([12.0, -8.0, 1e-3, 5.0, -2e-3], dtype=D)
    scaled = x * torch.tensor([1.1, 1.1, 1.0, 1.1, 1.0], dtype=D)
    nominal = segment.observe(scaled, t.incoming, t.misalignments)
    torch.testing.assert_close(m.true_observables(x), nominal, rtol=1e-12, atol=1e-15)
    assert float((m.true_observables(x) - segment.observe(x, t.incoming, t.misalignments)).abs()
                 .max()) > 10e-6  # fmt: skip
    correctors_only = torch.tensor([0.0, 0.0, 1e-3, 0.0, -2e-3], dtype=D)
    torch.testing.assert_close(
        m.true_observables(correctors_only),
        segment.observe(correctors_only, t.incoming, t.misalignments),
        rtol=1e-12,
        atol=1e-15,
    )
    # the machine's knobs are the settings, not what the magnets do
    m.set(x)
    torch.testing.assert_close(m.get(), x)


def test_none_is_the_trial_and_unknown_cases_fail(trials):
    t = trials[0]
    assert case_trial(t, "none") is t and case_trial(t, "quad-cal-10") is t
    with pytest.raises(ValueError, match="unknown model-error case 'bogus'"):
        check_case("bogus")
    assert MODEL_ERROR_HELP == CASE_TEXT and tuple(CASE_TEXT) == MODEL_ERROR_CASES


def test_bench_names_the_case_and_none_keeps_trajectories(tmp_path, capsys):
    """--model-error misalign-3x: every row, the summary and run.json name the case and the
    readings differ from the published machine's; --model-error none is the default run, bit
    for bit."""
    base = ["bench", "ares", "--trial-ids", "3", "--methods", "published-nm", "--steps", "4"]
    assert main([*base, "-o", str(tmp_path / "default"), "--quiet"]) == 0
    assert main([*base, "--model-error", "none", "-o", str(tmp_path / "none"), "--quiet"]) == 0
    assert main([*base, "--model-error", "misalign-3x", "-o", str(tmp_path / "m3"), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "machine: misalign-3x" in text
    default = pd.read_csv(tmp_path / "default" / "steps.csv", keep_default_na=False)
    none = pd.read_csv(tmp_path / "none" / "steps.csv", keep_default_na=False)
    m3 = pd.read_csv(tmp_path / "m3" / "steps.csv", keep_default_na=False)
    pd.testing.assert_frame_equal(default, none)
    assert set(none["model_error"]) == {"none"} and set(m3["model_error"]) == {"misalign-3x"}
    assert (m3["mae_true"] - none["mae_true"]).abs().iloc[0] > 1e-6
    summary = pd.read_csv(tmp_path / "m3" / "summary.csv")
    assert list(summary["model_error"]) == ["misalign-3x"]
    run = json.loads((tmp_path / "m3" / "run.json").read_text())
    assert run["model_error"] == "misalign-3x" and run["trial_ids"] == [3]
    assert run["noise_m"] == 0.0
