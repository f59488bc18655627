"""benchmarks/noisy_end_bound.py: the ideal estimator's runs against closed forms (the running
mean of the noise, one reading, no noise) and the printout."""

from __future__ import annotations

import numpy as np
import pytest

from tests.benchmark.conftest import load_script


@pytest.fixture(scope="module")
def bound():
    return load_script("noisy_end_bound")


def test_one_reading_ends_at_the_mean_of_its_noise(bound):
    # One reading: it is taken at the prior's estimate, the final is that reading's noise.
    final, best, lucky = bound.ideal_runs((1.0, 2.0), 1, 3, seed=5)
    rng = np.random.default_rng(5)
    eps = rng.normal(size=(3, 1, 2)) * np.array([1.0, 2.0])
    e0 = rng.normal(size=(3, 2)) * np.array([1.0, 2.0])
    np.testing.assert_allclose(final, np.abs(eps[:, 0]).mean(-1))
    np.testing.assert_allclose(best, np.abs(e0).mean(-1))
    np.testing.assert_allclose(lucky, best)


def test_the_final_error_shrinks_as_one_over_root_n(bound):
    # Without forgetting the final is the mean of N draws: E|e_N| = s sqrt(2 / (pi N)).
    final, best, lucky = bound.ideal_runs((1.0,), 100, 20000, seed=1)
    assert final.mean() == pytest.approx(np.sqrt(2 / (np.pi * 100)), rel=0.03)
    assert (best <= lucky).all()  # the final is no reading: it may be below the best
    assert np.median(final / best) > 1.2  # one observable: a reading's error crosses 0
    # With forgetting 0.9 the estimate keeps ~19 readings: sd sqrt((1 - l) / (1 + l)) at large N.
    final9, _, _ = bound.ideal_runs((1.0,), 100, 20000, forget=0.9, seed=1)
    assert final9.mean() == pytest.approx(np.sqrt(2 / np.pi * 0.1 / 1.9), rel=0.03)


def test_noise_free_observables_cost_nothing(bound):
    final, best, _ = bound.ideal_runs((0.0, 0.0), 10, 4, seed=0)
    assert (final == 0).all() and (best == 0).all()
    with pytest.raises(ValueError, match="readings >= 1"):
        bound.ideal_runs((1.0,), 0, 4)


def test_the_printout_has_a_row_per_scale_and_forgetting(bound, capsys):
    assert bound.main(["--readings", "20", "--runs", "200"]) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines()[2:]]
    assert [r[:2] for r in rows] == [[s, f] for s in bound.SCALES for f in ("1.00", "0.90")]
    ratio = {(r[0], r[1]): float(r[2]) for r in rows}
    # Forgetting makes the final worse against the best on every scale.
    assert all(ratio[s, "0.90"] > ratio[s, "1.00"] > 1.0 for s in bound.SCALES)
