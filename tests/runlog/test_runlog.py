"""Tests of the run log: records on disk after every write, crash tolerance, replay and resume."""

from __future__ import annotations

import json
import os

import pytest
import torch

from pigp_torch.data.runlog import FORMAT_TAG, ReplayError, RunLog, file_sha256, read_log, replay
from pigp_torch.loop import optimize
from pigp_torch.loop.run import advance_simulated_noise, build_run, validate_config
from pigp_torch.optimizers import RCDS, NelderMead
from pigp_torch.prior import PhysicsPrior

D = torch.float64
BOUNDS = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=D)


def bowl(x) -> float:
    """1 - |x - (0.3, -0.2)|^2."""
    return float(
        1.0 - ((torch.as_tensor(x, dtype=D) - torch.tensor([0.3, -0.2], dtype=D)) ** 2).sum()
    )


def test_records_round_trip_exactly_and_each_is_fsynced(tmp_path, monkeypatch):
    """Header, start, evaluations and end come back as written (floats bit for bit), and every
    record is followed by an fsync of the file."""
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    path = tmp_path / "sub" / "run.jsonl"
    x = [0.1 + 0.2, -1 / 3]
    with RunLog.create(path, {"knob_names": ["a", "b"], "config": {"budget": 2}}) as log:
        n0 = len(synced)
        log.log_start([0.0, 0.5], budget=2, first_step=0)
        log.log_evaluation(0, torch.tensor(x, dtype=D), 2 / 3, reads=1)
        log.log_evaluation(1, [0.25, 0.5], -7.125, reads=3)
        log.log_end("completed", restored_to="initial", final_knobs=[0.0, 0.5])
        assert len(synced) - n0 == 4  # one fsync per record (plus the directory's at create)
    r = read_log(path)
    assert r.header["format"] == FORMAT_TAG and r.knob_names == ["a", "b"]
    assert r.header["config"] == {"budget": 2} and "package_version" in r.header
    assert r.evaluations[0]["x"] == x and r.evaluations[0]["y"] == 2 / 3
    assert [e["reads"] for e in r.evaluations] == [1, 3]
    assert r.starts[0]["initial_knobs"] == [0.0, 0.5]
    assert r.last_end["status"] == "completed" and r.n_evaluations == 2
    step, xb, yb = r.best()
    assert (step, xb.tolist(), yb) == (0, x, 2 / 3)
    assert r.best(maximize=False)[0] == 1


def test_refuses_to_clobber_and_rejects_bad_records(tmp_path):
    """An existing log is never overwritten by create(); non-finite values and unknown statuses
    are refused before anything is written."""
    path = tmp_path / "run.jsonl"
    log = RunLog.create(path, {"knob_names": ["a"]})
    with pytest.raises(FileExistsError):
        RunLog.create(path, {"knob_names": ["a"]})
    size = path.stat().st_size
    with pytest.raises(ValueError, match="JSON-serializable"):
        log.log_evaluation(0, [0.0], float("nan"))
    with pytest.raises(ValueError, match="status"):
        log.log_end("exploded")
    log.close()
    assert path.stat().st_size == size
    with pytest.raises(ValueError, match="closed"):
        log.log_evaluation(0, [0.0], 1.0)


def test_a_line_cut_short_by_a_crash_is_ignored_and_cut_off_on_append(tmp_path):
    """A partial last line warns on read; append() removes it and continues on a fresh line."""
    path = tmp_path / "run.jsonl"
    with RunLog.create(path, {"knob_names": ["a"]}) as log:
        log.log_evaluation(0, [0.5], 1.0)
    with open(path, "a") as f:
        f.write('{"type":"evaluation","step":1,"x":[0.')
    with pytest.warns(UserWarning, match="cut short"):
        assert read_log(path).n_evaluations == 1
    with pytest.warns(UserWarning, match="cut short"):
        log = RunLog.append(path)
    log.log_evaluation(1, [0.25], 2.0)
    log.close()
    r = read_log(path)
    assert [e["x"] for e in r.evaluations] == [[0.5], [0.25]]


def test_inconsistent_logs_are_refused_with_the_line(tmp_path):
    """Not a log, a step gap, a wrong knob count: ValueError naming the file and line."""
    path = tmp_path / "x.jsonl"
    path.write_text('{"type": "start"}\n')
    with pytest.raises(ValueError, match="not a run log"):
        read_log(path)
    with RunLog.create(path, {"knob_names": ["a", "b"]}, overwrite=True) as log:
        log.log_evaluation(0, [0.0, 0.0], 1.0)
        log.log_evaluation(2, [0.0, 0.0], 1.0)
    with pytest.raises(ValueError, match=r"x.jsonl:3: evaluation step 2, expected 1"):
        read_log(path)
    with RunLog.create(path, {"knob_names": ["a", "b"]}, overwrite=True) as log:
        log.log_evaluation(0, [0.0], 1.0)
    with pytest.raises(ValueError, match="x must be a list of 2"):
        read_log(path)
    path.write_text('{"type": "header", "format": "other"}\n')
    with pytest.raises(ValueError, match="format tag"):
        read_log(path)


@pytest.mark.parametrize("make", [lambda: NelderMead(BOUNDS), lambda: RCDS(BOUNDS, noise=0.01)])
def test_replay_rebuilds_the_state(tmp_path, make):
    """After replaying a logged run a fresh optimizer asks exactly what the original asks next."""
    original = make()
    table = optimize(bowl, original, [-0.5, 0.4], 15, log=tmp_path / "r.jsonl")
    rebuilt = make()
    assert replay(rebuilt, read_log(tmp_path / "r.jsonl")) == 15
    assert rebuilt.Y == table["y"].tolist()
    assert torch.equal(rebuilt.ask(), original.ask())


def test_replay_detects_divergence_and_needs_a_fresh_optimizer(tmp_path):
    """A logged point the optimizer would not ask, or a used optimizer: ReplayError."""
    optimize(bowl, NelderMead(BOUNDS), [-0.5, 0.4], 6, log=tmp_path / "r.jsonl")
    evaluations = read_log(tmp_path / "r.jsonl").evaluations
    with pytest.raises(ReplayError, match="diverged at step 1"):
        replay(NelderMead(BOUNDS, initial_simplex_size=0.2), evaluations)
    tampered = [dict(e) for e in evaluations]
    tampered[4]["x"] = [0.0, 0.0]
    with pytest.raises(ReplayError, match=r"diverged at step 4: the optimizer asks .* log holds"):
        replay(NelderMead(BOUNDS), tampered)
    used = NelderMead(BOUNDS)
    used.tell(torch.zeros(2, dtype=D), 0.0)
    with pytest.raises(ReplayError, match="fresh optimizer"):
        replay(used, evaluations)


# --------------------------------------------------------------------------------------------
# resume through the configuration path: 6 evaluations, crash, resume to 12 == 12 in one go
KNOBS = ["01G-QSS4", "02G-QSS3"]


def write_prior(path) -> None:
    """A small hand-made physics prior on the two simulated knobs (peak near skews-off)."""
    PhysicsPrior(
        x0=torch.tensor([-0.003, 0.002], dtype=D),
        f_x0=0.9,
        f_inf=0.2,
        precision=torch.tensor([[4e4, 1e4], [1e4, 3e4]], dtype=D),
        amplitude=0.05,
        noise=0.04,
        knob_names=KNOBS,
        bounds=torch.tensor([[-0.015] * 2, [0.015] * 2], dtype=D),
        provenance={"made_by": "test_runlog"},
    ).save(path)


def sim_config(tmp_path, method: dict, budget: int, log: str) -> dict:
    return {
        "machine": {"kind": "sim", "error_seed": 1, "noise": 0.04, "seed": 5},
        "knobs": {k: [-0.01, 0.01] for k in KNOBS},
        "method": method,
        "prior": "prior.json",
        "budget": budget,
        "max_step": 0.2,
        "log": log,
    }


@pytest.mark.parametrize(
    "method",
    [
        {"name": "nelder-mead", "options": {"initial_simplex_size": 0.1}},
        {"name": "rcds", "options": {"noise": 0.04, "step": 0.1}},
        {"name": "pigp", "seed": 3, "options": {"num_restarts": 2, "raw_samples": 32}},
    ],
    ids=lambda m: m["name"],
)
def test_crash_then_resume_gives_the_uninterrupted_rows(tmp_path, method):
    """6 evaluations, an exception, a resume to 12: the rows (knobs, readings) are identical to
    those of an uninterrupted 12-evaluation run with the same seeds; the log holds all 12."""
    write_prior(tmp_path / "prior.json")
    cols = [*KNOBS, "y"]
    whole = build_run(
        validate_config(sim_config(tmp_path, method, 12, "a.jsonl"), base_dir=tmp_path)
    )
    reference = whole.run(log=tmp_path / "a.jsonl")

    def crash(row):
        if row["step"] == 5:
            raise RuntimeError("power cut")

    cfg = validate_config(sim_config(tmp_path, method, 12, "b.jsonl"), base_dir=tmp_path)
    first = build_run(cfg)
    with pytest.raises(RuntimeError, match="power cut"):
        first.run(log=tmp_path / "b.jsonl", callback=crash)
    records = read_log(tmp_path / "b.jsonl")
    assert records.n_evaluations == 6 and records.last_end["status"] == "failed"
    assert records.last_end["final_knobs"] == records.starts[0]["initial_knobs"]

    second = build_run(cfg)  # a fresh process would do the same: new machine, new optimizer
    advance_simulated_noise(second.machine, sum(e["reads"] for e in records.evaluations))
    resumed = second.run(log=tmp_path / "b.jsonl", resume=records)
    assert resumed[cols].values.tolist() == reference[cols].values.tolist()
    assert resumed["step"].tolist() == list(range(12))
    log = read_log(tmp_path / "b.jsonl")
    assert log.n_evaluations == 12 and [s["first_step"] for s in log.starts] == [0, 6]
    assert log.X().tolist() == reference[KNOBS].values.tolist()
    assert log.last_end["status"] == "completed"


def test_prior_provenance_in_the_header(tmp_path):
    """The header written for a configured run names the prior file, its sha256 and metadata."""
    write_prior(tmp_path / "prior.json")
    method = {"name": "nelder-mead"}
    setup = build_run(
        validate_config(sim_config(tmp_path, method, 2, "h.jsonl"), base_dir=tmp_path)
    )
    setup.run(log=RunLog.create(tmp_path / "h.jsonl", setup.header()))
    header = read_log(tmp_path / "h.jsonl").header
    assert header["prior"]["sha256"] == file_sha256(tmp_path / "prior.json")
    assert header["prior"]["path"] == str((tmp_path / "prior.json").resolve())
    assert header["prior"]["metadata"] == {"made_by": "test_runlog"}
    assert header["config"]["method"]["name"] == "nelder-mead"
    assert json.loads(json.dumps(header["config"]))["knobs"] == {k: [-0.01, 0.01] for k in KNOBS}


def test_a_log_without_end_record_hard_kill_resumes(tmp_path):
    """A process killed hard leaves no end record: the log still resumes to the same rows."""
    reference = optimize(bowl, NelderMead(BOUNDS), [-0.5, 0.4], 9)
    path = tmp_path / "r.jsonl"
    optimize(bowl, NelderMead(BOUNDS), [-0.5, 0.4], 5, log=path)
    lines = path.read_text().splitlines(keepends=True)
    assert '"type":"end"' in lines[-1]
    path.write_text("".join(lines[:-1]))  # as if killed (SIGKILL) after the last evaluation
    records = read_log(path)
    assert records.last_end is None and records.n_evaluations == 5
    resumed = optimize(bowl, NelderMead(BOUNDS), None, 9, log=path, resume=records)
    assert (
        resumed[["x0", "x1", "y"]].values.tolist() == reference[["x0", "x1", "y"]].values.tolist()
    )
    assert read_log(path).last_end["status"] == "completed"
    with pytest.raises(ValueError, match="already holds 9 evaluations"):
        optimize(bowl, NelderMead(BOUNDS), None, 9, resume=read_log(path))
