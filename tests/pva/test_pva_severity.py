"""Alarm severity over real pvAccess (the simulated ring's p4p server on 127.0.0.1): a reading
posted with alarm.severity INVALID is never an evaluation, as over Channel Access."""

from __future__ import annotations

import torch

from pigp_torch import optimize
from pigp_torch.data.runlog import read_log
from pigp_torch.machine.pva import PvaMachine
from pigp_torch.optimizers import NelderMead
from pigp_torch.simulated_epics import ALARM_SEVERITY_SUFFIX
from pigp_torch.simulated_epics.pva import ALARM_POSTS_SUFFIX

from .conftest import FAST, KNOBS, setpoints


def test_an_invalid_reading_is_never_an_evaluation(ring, pva_client, tmp_path):
    """After evaluation 2 every loss-rate refresh is posted INVALID until the client has read
    one (then the server posts clean values again): each INVALID reading is logged as
    discarded naming the PV and the severity, read again, and none of the values the server
    posted with the alarm is an evaluation or a reading averaged into one; the run completes
    and the knobs are restored."""
    server, conf = ring
    start = server.bounds[1] * torch.tensor([0.1, -0.1], dtype=torch.float64)
    pva_client.put([f"{n}:CurrSetpt" for n in KNOBS], start.tolist(), timeout=2.0)
    posts = server.pv(ALARM_POSTS_SUFFIX)
    pva_client.put(server.pv(ALARM_SEVERITY_SUFFIX), 3.0, timeout=2.0)
    state = {"armed": False, "refused": 0}
    # no retries of the machine's own: the loop re-reads, as in a run of `pigp optimize`
    b = server.bounds / 2
    with PvaMachine(KNOBS, b, server.loss_rate_pv, context=conf, read_retries=0, **FAST) as m:
        real = m._ca.read_timed

        def read_timed(name, timeout):
            out = real(name, timeout)
            if state["armed"] and out[2] >= 3:
                state["refused"] += 1
                if state["refused"] == 2:  # the alarm ends with the next refresh
                    pva_client.put(posts, 0.0, timeout=2.0)
            return out

        m._ca.read_timed = read_timed

        def callback(row):
            if row["step"] == 1:
                pva_client.put(posts, -1.0, timeout=2.0)
                state["armed"] = True

        opt = NelderMead(m.bounds, initial_simplex_size=0.5)
        optimize(m, opt, budget=5, callback=callback, log=tmp_path / "r.jsonl",
                 read_retries=4, retry_interval=0.05)  # fmt: skip
    log = read_log(tmp_path / "r.jsonl")
    assert state["refused"] >= 2 and server.alarm_values
    refused = [d for d in log.discarded if "alarm severity INVALID" in d["reason"]]
    assert refused and all(server.loss_rate_pv in d["reason"] for d in refused)
    assert all(d["y"] in server.alarm_values for d in refused)
    taken = [e["y"] for e in log.evaluations]
    taken += [v for e in log.evaluations for v in e["reading"]["values"]]
    assert not set(taken) & set(server.alarm_values)
    assert log.n_evaluations == 5 and log.last_end["restored"] is True
    assert torch.allclose(setpoints(pva_client), start, rtol=0, atol=1e-15)
