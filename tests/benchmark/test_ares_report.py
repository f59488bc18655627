"""benchmarks/ares_report.py: several ARES runs -> one table, per-trial scores and a figure."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("cheetah")

from pigp_torch.cli import main
from tests.benchmark.conftest import load_script

STEPS = 4
BASE = ["bench", "ares", "--trial-ids", "10-12", "--steps", str(STEPS), "--quiet"]


@pytest.fixture(scope="module")
def script():
    return load_script("ares_report")


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """Tiny runs: noise-free in two folders (methods apart), 5 um noise, misalign-3x, and an old
    folder written before run.json and the model_error column (noise-free, trials 13-14)."""
    root = tmp_path_factory.mktemp("ares_runs")
    runs = {
        "free_bo": ["--methods", "published-bo"],
        "free_nm": ["--methods", "published-nm"],
        "noisy": ["--methods", "published-bo", "published-nm", "--noise", "5e-6"],
        "m3": ["--methods", "published-nm", "--model-error", "misalign-3x"],
        "old": ["--methods", "published-nm"],
    }
    for name, extra in runs.items():
        args = [*BASE, *extra, "-o", str(root / name)]
        if name == "old":
            args[3] = "13-14"
        assert main(args) == 0
    old = root / "old"
    (old / "run.json").unlink()
    pd.read_csv(old / "steps.csv").drop(columns="model_error").to_csv(
        old / "steps.csv", index=False
    )
    return root


def test_conditions_table_scores_and_figure(script, folders, tmp_path):
    """The table has one row per condition and method with the median [IQR] of the per-trial
    scores, which are those of the step tables; the figure is written."""
    dirs = [str(folders / n) for n in ("m3", "noisy", "free_nm", "free_bo", "old")]
    md, csv, png = tmp_path / "t.md", tmp_path / "s.csv", tmp_path / "f.png"
    args = [*dirs, "--markdown", str(md), "--scores-csv", str(csv), "--figure", str(png)]
    assert script.main(args) == 0
    scores = pd.read_csv(csv)
    # 5 trials noise-free nm (10-14), 3 noise-free bo, 3 + 3 noisy, 3 misalign-3x
    counts = scores.groupby(["condition", "method"]).size().to_dict()
    assert counts == {
        ("noise-free", "published-bo"): 3,
        ("noise-free", "published-nm"): 5,
        ("noise 5 µm", "published-bo"): 3,
        ("noise 5 µm", "published-nm"): 3,
        ("misalign-3x, noise-free", "published-nm"): 3,
    }
    assert list(dict.fromkeys(scores["condition"])) == [
        "noise-free",
        "noise 5 µm",
        "misalign-3x, noise-free",
    ]
    assert (scores["readings"] == STEPS).all()
    # per-trial final MAE = the noise-free MAE of the set-back row of that run
    steps = pd.read_csv(folders / "m3" / "steps.csv")
    last = steps[steps["step"] == STEPS].set_index("trial")["mae_true"]
    got = scores[scores["condition"] == "misalign-3x, noise-free"].set_index("trial")["final_mae"]
    np.testing.assert_allclose(got.sort_index(), last.sort_index(), rtol=1e-12)
    # the table: median [IQR] of those numbers in um
    table = md.read_text().splitlines()
    assert len(table) == 2 + 5
    row = next(r for r in table if r.startswith("| misalign-3x, noise-free | `published-nm`"))
    q = np.quantile(last.to_numpy() * 1e6, [0.25, 0.5, 0.75])
    assert f"| {q[1]:.3g} [{q[0]:.3g}, {q[2]:.3g}] |" in row
    assert "| 3 | 4 |" in row
    assert png.stat().st_size > 5000


def test_quantiles_per_step_and_old_folders(script, folders):
    """The figure's median at step 0 is the median start MAE; an old folder (no run.json, no
    model_error column) is read as the published machine, noise-free."""
    runs = script.load_runs([folders / "free_nm", folders / "old"])
    assert set(runs["condition"]) == {"noise-free"} and set(runs["case"]) == {"none"}
    q = script.mae_quantiles(runs)
    start = runs[runs["step"] == 0]["mae_true"].to_numpy() * 1e6
    first = q[(q["step"] == 0)].iloc[0]
    assert first["median"] == pytest.approx(np.median(start))
    assert first["trials"] == 5
    assert q["step"].max() == STEPS - 1  # the set-back row is not a step of the curve
    assert script.condition_label("quad-cal-10", 5e-6) == "quad-cal-10, noise 5 µm"


def test_old_and_new_tables_merge_in_score_runs(folders):
    """A table merged from a folder written before the model_error column (empty there) and a
    new one scores every run as the published machine."""
    from pigp_torch.machines.ares_ea.benchmark import score_runs

    merged = pd.concat(
        [pd.read_csv(folders / n / "steps.csv") for n in ("old", "free_nm")], ignore_index=True
    )
    assert merged["model_error"].isna().any()
    scores = score_runs(merged)
    assert len(scores) == 5 and set(scores["model_error"]) == {"none"}


def test_common_and_duplicates(script, folders):
    """--common keeps the trials every method ran (10-12 of nm's 10-14); a run given twice
    under one condition is an error."""
    dirs = [folders / "free_bo", folders / "free_nm", folders / "old"]
    runs = script.load_runs(dirs, common=True)
    assert sorted(runs["trial"].unique()) == [10, 11, 12]
    with pytest.raises(ValueError, match="ran twice under 'noise-free'"):
        script.load_runs([folders / "free_nm", folders / "free_nm"])


def test_methods_of_a_folder(script, folders):
    """DIR::M keeps only method M of that folder (the noisy folder has both recipes); a method
    the folder lacks is an error."""
    both = script.load_runs([folders / "noisy"])
    assert set(both["method"]) == {"published-bo", "published-nm"}
    nm = script.load_runs([f"{folders / 'noisy'}::published-nm"])
    assert set(nm["method"]) == {"published-nm"}
    assert len(nm) == (both["method"] == "published-nm").sum()
    with pytest.raises(ValueError, match="no runs of \\['ares-physics'\\]"):
        script.load_runs([f"{folders / 'noisy'}::ares-physics"])
