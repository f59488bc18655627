"""A ring that is not the built-in SPEAR3 goes through the whole CLI chain from a lattice file."""

import json
import shutil

from pigp_torch.cli import main
from pigp_torch.data.tables import read_table
from pigp_torch.prior import PhysicsPrior
from pigp_torch.simulation.deck import deck_path

KNOBS = "01G-QSS4,02G-QSS3,05G-QSS3"


def test_design_deck_file_through_the_cli(tmp_path, capsys):
    """The SPEAR3 design deck given as a user's file: generate-data -> train-surrogate ->
    build-prior (with an error ensemble of that ring) -> compare, with knobs by element name."""
    lattice = tmp_path / "my_ring.json"
    shutil.copy(deck_path("design"), lattice)
    ring = ["--lattice", str(lattice), "--knobs", KNOBS, "--knob-calibration", "5.15e-4"]
    data, model, prior = tmp_path / "d.npz", tmp_path / "m.pt", tmp_path / "p.json"
    assert main(["generate-data", *ring, "--seed", "0", "--n", "3000", "-o", str(data)]) == 0
    assert main(["train-surrogate", str(data), "-o", str(model), "--members", "1",
                 "--epochs", "30", "--target", "log_excess"]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["build-prior", str(model), "-o", str(prior), "--center-ensemble", "4"]) == 0
    assert f"saved prior to {prior.resolve()}" in capsys.readouterr().out  # not "to None"
    assert main(["build-prior", str(model), "-o", str(prior), "--center-ensemble", "3"]) == 2
    assert "too small for 3 knobs" in capsys.readouterr().err
    p = PhysicsPrior.load(prior)
    assert p.knob_names == KNOBS.split(",")
    assert p.center_cov is not None and p.center_cov.shape == (3, 3)
    assert json.loads(prior.read_text())["provenance"]["center_ensemble_seeds"] == [1001, 1004, 4]
    out = tmp_path / "cmp"
    argv = ["compare", *ring, "--methods", "pigp", "nelder-mead", "--seeds", "1", "--budget-gp",
            "6", "--budget-direct", "6", "--center-ensemble", "0", "--prior-source", "exact",
            "-o", str(out)]  # fmt: skip
    assert main(argv) == 0

    runs = read_table(out / "runs.csv")
    assert set(runs["method"]) == {"pigp", "nelder-mead"} and len(runs) == 12
    assert set(KNOBS.split(",")) <= set(runs.columns)
    assert (runs["gain_fraction"] <= 1 + 1e-9).all()
    assert (out / "fig2b_runs.png").exists()


def test_lattice_options_are_checked():
    """--lattice without element names or calibration is refused before anything is built."""
    assert main(["generate-data", "--lattice", "x.json", "--n", "10", "-o", "d.npz"]) == 2
    assert main(["generate-data", "--lattice", "x.json", "--knobs", "A,B", "--n", "10",
                 "-o", "d.npz"]) == 2  # fmt: skip
    assert main(["generate-data", "--knob-calibration", "1e-3", "--n", "10", "-o", "d.npz"]) == 2
