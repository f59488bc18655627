"""End-to-end test of ``pigp train-surrogate`` (and its script) on a tiny dataset file."""

from __future__ import annotations

import argparse
import inspect

import pytest
import torch

from pigp_torch.cli import main as pigp
from pigp_torch.commands.train_surrogate import add_train_arguments
from pigp_torch.data.dataset import Dataset
from pigp_torch.surrogate import load_surrogate, train_surrogate


def main(argv):
    return pigp(["train-surrogate", *argv])


@pytest.fixture
def tiny_npz(tmp_path, landscape3):
    """A 300-sample dataset of the 3-D landscape written with Dataset.save."""
    x = landscape3.sample(300, seed=11)
    y = landscape3(x)
    meta = {
        "f_inf": landscape3.f_inf,
        "bounds": landscape3.bounds.tolist(),
        "knob_names": ["Q1", "Q2", "Q3"],
        "error_seed": 4,
        "design": "half uniform, half gaussian",
    }
    ones = torch.ones_like(y)
    ds = Dataset(x=x, loss_rate=y, eps_x=ones, eps_y=ones, metadata=meta)
    return ds.save(tmp_path / "data" / "tiny.npz"), meta


def test_main_trains_saves_and_reports(tiny_npz, tmp_path, capsys):
    """main() returns 0, writes a loadable model with provenance metadata and prints the metrics."""
    path, meta = tiny_npz
    out = tmp_path / "models" / "m.pt"
    argv = [str(path), "-o", str(out), "--widths", "16", "16", "--epochs", "20", "--seed", "2"]
    rc = main([*argv, "--quiet", "--device", "cpu", "--activation", "tanh", "--members", "1"])
    assert rc == 0
    model, saved = load_surrogate(out)
    assert saved["knob_names"] == ["Q1", "Q2", "Q3"]
    assert saved["f_inf"] == meta["f_inf"] and saved["bounds"] == meta["bounds"]
    assert saved["data_file"] == "tiny.npz"
    assert saved["data_metadata"]["error_seed"] == 4
    assert saved["metrics"]["epochs"] <= 20 and saved["metrics"]["n_train"] == 270
    assert saved["metrics"]["seed"] == 2
    assert model.widths == (16, 16) and model.activation == "tanh"
    text = capsys.readouterr().out
    assert "relative RMSE of the loss rate" in text and "R^2 of log(loss - f_inf)" in text
    assert f"{100 * saved['metrics']['val_rel_rmse']:.3f} %" in text
    assert "training time" in text and str(out) in text


def test_parser_reusable_by_cli_and_defaults_match_trainer():
    """build_parser adds its arguments to a given parser; defaults equal train_surrogate's."""
    p = add_train_arguments(argparse.ArgumentParser(prog="pigp train-surrogate"))
    args = p.parse_args(["d.npz", "-o", "m.pt"])
    defaults = inspect.signature(train_surrogate).parameters
    assert args.epochs == defaults["max_epochs"].default
    assert tuple(args.widths) == tuple(defaults["widths"].default)
    assert args.target == defaults["target"].default and args.lr == defaults["lr"].default
    with pytest.raises(SystemExit):
        p.parse_args(["d.npz", "-o", "m.pt", "--activation", "relu"])


def test_main_missing_file_is_a_clear_error(tmp_path, capsys):
    """A missing dataset file is reported (exit code 2) before any training."""
    assert main([str(tmp_path / "none.npz"), "-o", str(tmp_path / "m.pt"), "--quiet"]) == 2
    assert "dataset file not found" in capsys.readouterr().err
