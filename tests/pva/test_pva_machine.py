"""PvaMachine over real pvAccess against the simulated ring's p4p server (127.0.0.1): the same
machine interface and the same safety checks as over Channel Access."""

from __future__ import annotations

import math
import time

import pytest
import torch
import yaml

from pigp_torch import cli, optimize
from pigp_torch.data.runlog import read_log
from pigp_torch.machine import Machine
from pigp_torch.machine.errors import MachineError, ReadError
from pigp_torch.machine.pva import PvaMachine
from pigp_torch.optimizers import NelderMead

from .conftest import FAST, KNOBS, UPDATE_PERIOD, setpoints


def machine(server, conf, bounds=None, **options):
    b = server.bounds / 2 if bounds is None else bounds
    return PvaMachine(KNOBS, b, server.loss_rate_pv, context=conf, **{**FAST, **options})


def test_round_trip_limits_and_a_refused_put(ring, pva_client):
    """set/get/setpoints/read over pvAccess; fresh timestamped readings near the simulator's
    value; bounds outside the control limits refused at start; a put the server refuses is a
    MachineError naming the PV."""
    server, conf = ring
    x = server.bounds[1] * torch.tensor([0.2, -0.3], dtype=torch.float64)
    with machine(server, conf) as m:
        assert isinstance(m, Machine) and torch.equal(m.control_limits, server.bounds)
        m.set(x)
        assert torch.equal(m.get(), x) and torch.equal(m.setpoints(), x)
        assert torch.equal(setpoints(pva_client), x)
        readings = []
        for _ in range(4):
            readings.append(m.read())
            time.sleep(1.5 * UPDATE_PERIOD)
        stamps = [m.last_reading["stamps"][0]]
        m.read()
        stamps.append(m.last_reading["stamps"][0])
        assert stamps[1] > stamps[0] and m.disconnections == 0
    f_true = float(server.machine.true_value(x))
    assert abs(sum(readings) / 4 - f_true) < 5 * 0.04 / math.sqrt(4)
    with pytest.raises(ValueError, match=r"01G-QSS4: bounds .* outside control"):
        machine(server, conf, bounds=server.bounds * 2)
    with machine(server, conf, bounds=server.bounds * 2, check_control_limits=False) as m:
        with pytest.raises(MachineError, match=r"01G-QSS4:CurrSetpt: RemoteError: .* outside"):
            m.set(server.bounds[1] * 1.5)
    assert torch.equal(setpoints(pva_client), x)  # the refused put changed nothing


def test_a_frozen_objective_pv_stops_the_run(ring, pva_client, tmp_path):
    """The loss-rate PV stops updating after step 1: the run ends with stale readings
    (ReadError), not 'completed'; knobs restored."""
    server, conf = ring

    def callback(row):
        if row["step"] == 1:
            pva_client.put(server.pv("Sim:Frozen"), 1.0, timeout=2.0)

    with machine(server, conf, stale_timeout=0.3) as m:
        opt = NelderMead(m.bounds, initial_simplex_size=0.5)
        with pytest.raises(ReadError, match=r"has not updated for 0\.3 s"):
            optimize(m, opt, budget=12, callback=callback, log=tmp_path / "r.jsonl")
    log = read_log(tmp_path / "r.jsonl")
    assert log.n_evaluations in (2, 3) and log.last_end["status"] == "aborted"
    assert torch.equal(setpoints(pva_client), torch.zeros(2, dtype=torch.float64))


def test_a_reboot_during_an_averaged_reading_is_discarded(ring, pva_client, tmp_path):
    """The server 'reboots' (knobs to their power-on values) between two readings of step 2's
    average: the reading is discarded (logged), never an evaluation; the run aborts with
    MachineError and the initial knobs are put back."""
    server, conf = ring
    start = server.bounds[1] * torch.tensor([0.1, 0.1], dtype=torch.float64)
    pva_client.put([f"{n}:CurrSetpt" for n in KNOBS], start.tolist(), timeout=2.0)
    state = {"armed": False, "reads": 0}

    with machine(server, conf, n_average=3, average_interval=0.06) as m:
        real = m._ca.read_timed

        def read_timed(name, timeout):
            out = real(name, timeout)
            if state["armed"]:
                state["reads"] += 1
                if state["reads"] == 2:
                    pva_client.put(server.pv("Sim:Reboot"), 1.0, timeout=2.0)
            return out

        m._ca.read_timed = read_timed

        def callback(row):
            if row["step"] == 1:
                state["armed"] = True

        opt = NelderMead(m.bounds, initial_simplex_size=0.5)
        with pytest.raises(MachineError, match="reading discarded and the knobs moved"):
            optimize(m, opt, budget=6, callback=callback, log=tmp_path / "r.jsonl")
    log = read_log(tmp_path / "r.jsonl")
    assert log.n_evaluations == 2 and [d["step"] for d in log.discarded] == [2]
    assert log.last_end["restored"] is True
    assert torch.allclose(setpoints(pva_client), start, rtol=0, atol=1e-15)


def test_pigp_optimize_over_pvaccess_and_the_machine_lock(
    ring, pva_client, tmp_path, monkeypatch, capsys
):
    """`pigp optimize` with `protocol: pva`: a run completes with the knobs restored; while
    another run holds the machine's PVs the run is refused (exit 4)."""
    from pigp_torch.data.runlock import holding, machine_locks

    server, conf = ring
    for key, value in conf.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setenv("PIGP_LOCK_DIR", str(tmp_path / "locks"))
    monkeypatch.setattr(
        cli, "COMMAND_MODULES", tuple(dict.fromkeys((*cli.COMMAND_MODULES, "optimize")))
    )
    b = server.bounds / 2
    data = {
        "machine": {"kind": "epics", "protocol": "pva", "settle_time": 0.1, "timeout": 1.0},
        "knobs": {k: [float(b[0, i]), float(b[1, i])] for i, k in enumerate(KNOBS)},
        "objective": {"pv": server.loss_rate_pv},
        "method": {"name": "nelder-mead", "options": {"initial_simplex_size": 0.5}},
        "budget": 4,
        "max_step": 0.2,
        "log": "run.jsonl",
    }
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(data))
    start = b[1] * torch.tensor([0.3, -0.2], dtype=torch.float64)
    pva_client.put([f"{n}:CurrSetpt" for n in KNOBS], start.tolist(), timeout=2.0)
    with holding(machine_locks([server.loss_rate_pv])):
        assert cli.main(["optimize", "--config", str(tmp_path / "run.yaml")]) == 4
    assert "machine PVs SPEAR:* is in use" in capsys.readouterr().err
    assert cli.main(["optimize", "--config", str(tmp_path / "run.yaml"), "--quiet"]) == 0
    log = read_log(tmp_path / "run.jsonl")
    assert log.n_evaluations == 4 and log.last_end["restored"] is True
    assert torch.allclose(setpoints(pva_client), start, rtol=0, atol=1e-15)
