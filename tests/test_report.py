"""`pigp report`: the figure and the self-contained page of a run log and of a compare folder."""

from __future__ import annotations

import base64
import re

import pandas as pd
import pytest
import torch
import yaml

from pigp_torch import cli
from pigp_torch.prior import PhysicsPrior
from pigp_torch.reporting.report import run_report, write_report

KNOBS = ["01G-QSS4", "02G-QSS3"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def write_prior(path) -> None:
    d = len(KNOBS)
    PhysicsPrior(
        x0=torch.zeros(d, dtype=torch.float64),
        f_x0=0.9,
        f_inf=0.2,
        precision=4e-3 * torch.eye(d, dtype=torch.float64),
        amplitude=0.05,
        noise=0.04,
        knob_names=list(KNOBS),
        bounds=torch.tensor([[-30.0] * d, [30.0] * d], dtype=torch.float64),
    ).save(path)


def write_run(folder, method="pigp-physics", budget=6, **over) -> str:
    write_prior(folder / "prior.json")
    data = {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04, "seed": 2},
        "knobs": {k: [-30, 30] for k in KNOBS},
        "method": {"name": method},
        "prior": "prior.json",
        "budget": budget,
        "max_step": 0.2,
        "log": "run.jsonl",
        **over,
    }
    path = folder / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture(scope="module")
def physics_log(tmp_path_factory):
    folder = tmp_path_factory.mktemp("run")
    assert cli.main(["optimize", "--config", write_run(folder), "--quiet"]) == 0
    return folder / "run.jsonl"


def test_report_of_a_simulated_pigp_physics_run(physics_log, capsys):
    data = run_report(physics_log)
    assert data["method"] == "pigp-physics" and data["X"].shape == (6, 2)
    assert data["noise"] == 0.04 and data["true"].shape == (6,)  # simulated: noise-free values
    fit = data["fit"]
    assert fit["center"].shape == (2,) and bool((fit["center_std"] > 0).all())
    assert fit["value_std"] > 0 and any("ended completed" in s for s in data["notices"])
    out = physics_log.parent / "rep"
    assert cli.main(["report", str(physics_log), "-o", str(out)]) == 0
    png, page = out.with_suffix(".png"), out.with_suffix(".html")
    assert png.read_bytes().startswith(PNG_MAGIC)
    text = page.read_text()
    embedded = re.search(r"src='data:image/png;base64,([^']+)'", text).group(1)
    assert base64.b64decode(embedded) == png.read_bytes()
    # self-contained: no external link outside the embedded image (whose base64 may spell "http")
    assert "http" not in text.replace("<!DOCTYPE html>", "").replace(embedded, "")
    assert "best true value" in text and "fitted optimum" in text
    out = capsys.readouterr().out  # a line before each step that takes a while
    assert "building the simulated ring (error seed 1) ..." in out
    assert "searching its true optimum within the run's bounds" in out
    assert "refitting pigp-physics's form to the 6 readings ..." in out


def full_search(machine, bounds, X, true):
    """The wide search the report's seeded one is checked against: 8 Sobol starts, the zero
    knobs and the run's best setting."""
    from pigp_torch._utils.multistart import find_optimum

    best = X[int(true.argmax())]
    starts = torch.stack([torch.zeros_like(best), best])
    return find_optimum(machine.sim.sim.loss_rate, bounds, n_starts=8, x_init=starts)


def seeded_equals_full_search(log) -> None:
    """The report's optimum (L-BFGS-B from the run's best settings, on one torch thread) is the
    wide search's: value within 1e-9 relative, setting within 0.01 A (the maximum is flat)."""
    from pigp_torch.loop.run import build_machine
    from pigp_torch.reporting.report import _load_run_config, read_log

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        data = run_report(log, fit=False)
        assert torch.get_num_threads() == 2  # pinned to one inside, the caller's count restored
    finally:
        torch.set_num_threads(threads)
    machine = build_machine(_load_run_config(read_log(log)))
    x_full, f_full = full_search(machine, data["bounds"], data["X"], data["true"])
    x_star, f_star = data["optimum"]
    assert f_star == pytest.approx(f_full, rel=1e-9)
    assert float((x_star - x_full).abs().max()) < 1e-2
    assert f_star >= float(data["true"].max())


def test_seeded_optimum_search_equals_the_full_search(physics_log):
    seeded_equals_full_search(physics_log)


def test_report_notices_a_knob_at_its_limit_and_a_running_log(tmp_path):
    """Nelder-Mead (no fitted optimum) from a start on a bound; a log cut before its end."""
    config = write_run(tmp_path, method="nelder-mead", budget=3)
    c = yaml.safe_load(open(config))
    c["machine"]["x_init"] = {"01G-QSS4": 30.0, "02G-QSS3": 0.0}
    open(config, "w").write(yaml.safe_dump(c))
    assert cli.main(["optimize", "--config", config, "--quiet"]) == 0
    log = tmp_path / "run.jsonl"
    lines = log.read_text().splitlines()
    log.write_text("\n".join(ln for ln in lines if '"type":"end"' not in ln) + "\n")
    data = run_report(log)
    assert data["fit"] is None and data["status"] == "running (no end record)"
    assert "01G-QSS4 reached its limit at evaluation 1" in data["notices"]
    png, page = write_report(log)
    assert png == tmp_path / "run_report.png" and page.is_file()


def test_report_of_a_compare_folder(tmp_path):
    rows = []
    for method in ("a", "b"):
        for seed in (1, 2):
            for step in range(5):
                g = (step + seed) / 10 * (2 if method == "a" else 1)
                rows.append(dict(method=method, machine_seed=seed, step=step, y=g,
                                 best_f_true=g, gain_fraction=g))  # fmt: skip
    pd.DataFrame(rows).to_csv(tmp_path / "runs.csv", index=False)
    assert cli.main(["report", str(tmp_path)]) == 0
    assert (tmp_path / "report.png").read_bytes().startswith(PNG_MAGIC)
    assert "data:image/png;base64," in (tmp_path / "report.html").read_text()


def test_report_refuses_what_it_cannot_draw(tmp_path, capsys):
    assert cli.main(["report", str(tmp_path)]) == 2  # a folder without runs.csv
    assert "no runs.csv" in capsys.readouterr().err


@pytest.mark.slow  # ~10 s: two 13-D optimum searches
def test_units_true_optimum_and_knob_colours_of_a_13_knob_run(tmp_path):
    """A 13-knob simulated run: the axes say mA/min and A, the page's text carries the units and
    the true optimum (the simulated machine's largest loss rate within the bounds, at least every
    noise-free value seen), the legend names the noise band in mA/min, and the 13 knob traces
    have 13 different colours."""
    import matplotlib.pyplot as plt

    from pigp_torch.reporting.report import draw_run
    from pigp_torch.simulation import Spear3Coupling

    knobs = Spear3Coupling(1).knob_names
    data = {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04, "seed": 2},
        "knobs": {k: [-30, 30] for k in knobs},
        "method": {"name": "nelder-mead"},
        "budget": 15,
        "max_step": 0.2,
        "log": "run.jsonl",
    }
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data))
    assert cli.main(["optimize", "--config", str(tmp_path / "run.yaml"), "--quiet"]) == 0
    report = run_report(tmp_path / "run.jsonl")
    f_star = report["optimum"][1]
    assert f_star == pytest.approx(1.7, abs=1e-2)  # seed 1 in ±30 A: the map's anchor
    assert f_star >= float(report["true"].max())
    fig, (ax, axk) = draw_run(report)
    try:
        assert ax.get_ylabel() == "objective (mA/min)"
        assert axk.get_ylabel() == "knob setting (A)" and axk.get_xlabel() == "evaluation"
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert "noise band ±0.04 mA/min" in labels
        assert any(t.startswith("true optimum 1.7") and "mA/min" in t for t in labels)
        assert any(abs(line.get_ydata()[0] - f_star) < 1e-12 for line in ax.get_lines())
        colours = {tuple(line.get_color()) for line in axk.get_lines()[:13]}
        assert len(colours) == 13
    finally:
        plt.close(fig)
    _, page = write_report(tmp_path / "run.jsonl")
    text = page.read_text()
    assert re.search(r"best reading [0-9.]+ mA/min at evaluation", text)
    assert f"true optimum of the simulated machine {f_star:.6g} mA/min" in text
    assert "reading noise σ = 0.04 mA/min" in text and "knob settings in A" in text


@pytest.mark.slow  # ~20 s: two 13-knob machines, each searched twice
@pytest.mark.parametrize("error_seed", [1, 4])
def test_seeded_optimum_search_equals_the_full_search_on_13_knobs(tmp_path, error_seed):
    """A short 13-knob run (its best settings still far from the optimum): the report's seeded
    search finds the wide search's optimum."""
    from pigp_torch.simulation import Spear3Coupling

    data = {
        "machine": {"kind": "sim", "error_seed": error_seed, "noise": 0.04, "seed": 2},
        "knobs": {k: [-30, 30] for k in Spear3Coupling(1).knob_names},
        "method": {"name": "rcds", "options": {"noise": 0.04, "step": 0.05}},
        "budget": 12,
        "max_step": 0.1,
        "log": "run.jsonl",
    }
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data))
    assert cli.main(["optimize", "--config", str(tmp_path / "run.yaml"), "--quiet"]) == 0
    seeded_equals_full_search(tmp_path / "run.jsonl")


def test_an_epics_style_log_gets_its_run_file_units(tmp_path):
    """A run file's own units reach both axes (no simulated machine needed for the labels)."""
    import matplotlib.pyplot as plt

    from pigp_torch.reporting.report import draw_run

    path = write_run(tmp_path, method="nelder-mead", budget=3, objective_unit="counts/s",
                     knob_unit="mrad")  # fmt: skip
    assert cli.main(["optimize", "--config", path, "--quiet"]) == 0
    report = run_report(tmp_path / "run.jsonl", fit=False)
    fig, (ax, axk) = draw_run(report)
    try:
        assert (
            ax.get_ylabel() == "objective (counts/s)" and axk.get_ylabel() == "knob setting (mrad)"
        )
    finally:
        plt.close(fig)
