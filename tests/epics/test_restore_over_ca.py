"""The restore over real Channel Access (the shared simulated IOC on 127.0.0.1): a put the IOC
refuses (control limits narrowed mid-run) on one knob while the others are restored exactly; a
readback offset that pushes a knob at its bound past it (the IOC lives on); puts that stall for
less than the run's ``restore_timeout`` (the restore completes). Each test reads what the IOC
holds through a CA client of its own and, where it matters, the IOC's put log.
"""

from __future__ import annotations

import threading
import time

import pytest
import torch

from pigp_torch import cli
from pigp_torch.data.runlog import read_log
from pigp_torch.machine.epics import EpicsMachine
from pigp_torch.machine.errors import PutRefused

from .ca_runs import KNOBS, private_locks, start_of, with_optimize, write_config  # noqa: F401
from .conftest import FAST

pytestmark = pytest.mark.usefixtures("private_locks", "with_optimize")  # from ca_runs


def after_puts(ioc, n: int, action, timeout: float = 60.0) -> threading.Thread:
    """A thread that runs ``action()`` once the IOC has accepted ``n`` more puts (bounded)."""
    mark = ioc.n_puts()

    def watch() -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if ioc.n_puts() >= mark + n:
                action()
                return
            time.sleep(0.02)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def test_a_refused_put_on_one_knob_leaves_every_other_knob_at_its_target(
    ioc, probe, ring, tmp_path, capsys
):
    """After 4 puts the IOC narrows knob 1's control limits to +-1 A, below its initial 3 A:
    its puts are refused. Exit 3; knob 2 ends exactly at its initial setpoint; the refusal is
    named as such (ECA_PUTFAIL, the IOC's limits), not as a put without an answer; the end record
    and the exit line say which knob reached its target."""
    start = start_of(ring)
    assert float(start[0]) > 1.0  # knob 1 starts outside the narrowed limits
    probe.write_many(ioc.setpoint_pvs[:2], start)

    def narrow() -> None:
        probe.write(ioc.narrow_knob_pv, 1)
        probe.write(ioc.narrow_limit_pv, 1.0)

    watcher = after_puts(ioc, 4, narrow)
    config = write_config(tmp_path, ioc, ring, budget=12, restore_attempts=2)
    code = cli.main(["optimize", "--config", config, "--quiet"])
    watcher.join(timeout=5.0)
    captured = capsys.readouterr()
    assert code == 3, captured.err
    assert f"at the target: {KNOBS[1]}; NOT at the target: {KNOBS[0]}" in captured.err
    assert "refused" in captured.out and "ECA_PUTFAIL" in captured.out
    assert "Limits are set to -1.0 and 1.0" in captured.out
    now = probe.read_many(ioc.setpoint_pvs[:2])
    assert float(now[1]) == float(start[1])  # exactly at its target
    end = read_log(tmp_path / "run.jsonl").last_end
    assert end["restored"] is False
    assert float(now[0]) == end["last_setpoint"][0] != float(start[0])  # its last accepted put
    assert end["knobs_at_target"] == [KNOBS[1]] and end["knobs_not_at_target"] == [KNOBS[0]]
    assert "no answer" not in " ".join(end["restore_errors"])


def test_a_refused_put_is_reported_at_once(ioc, probe, ca_context):
    """A set outside narrowed control limits raises PutRefused naming the PV and the IOC's
    reason well within the machine's timeout; the other knob's put is made."""
    d = len(ioc.knob_names)
    lim = torch.full((d,), 0.015, dtype=torch.float64)
    with EpicsMachine(
        ioc.knob_names, torch.stack([-lim, lim]), ioc.loss_rate_pv,
        **{**FAST, "timeout": 2.0}, context=ca_context,
    ) as m:  # fmt: skip
        probe.write(ioc.narrow_knob_pv, 1)
        probe.write(ioc.narrow_limit_pv, 0.005)
        x = torch.zeros(d, dtype=torch.float64)
        x[0], x[1] = 0.01, -0.01
        t0 = time.monotonic()
        with pytest.raises(PutRefused, match=r"refused the put\(s\) to 01G-QSS4:CurrSetpt") as err:
            m.set(x)
        assert time.monotonic() - t0 < 1.0  # not the 2 s timeout
        assert "ECA_PUTFAIL" in str(err.value) and err.value.pvs == [ioc.setpoint_pvs[0]]
        assert probe.read(ioc.setpoint_pvs[0]) == 0.0 and probe.read(ioc.setpoint_pvs[1]) == -0.01


def test_a_readback_offset_past_a_bound_clips_and_the_ioc_lives(ioc, probe, ring):
    """A knob at its upper bound and a readback offset of +1 A: the readback reads the bound,
    the IOC keeps refreshing the loss rate (its timestamp advances) and answers puts."""
    sp, rb = ioc.setpoint_pvs[0], ioc.readback_pvs[0]
    upper = float(ring.bounds[1, 0])
    probe.write(sp, upper)
    probe.write(ioc.readback_offset_pv, 1.0)
    assert float(probe.wait_for([rb], [upper], 2.0)[0]) == upper
    stamp = probe.pv(ioc.loss_rate_pv).read(data_type="time").metadata.timestamp
    time.sleep(0.3)  # six refreshes
    assert probe.pv(ioc.loss_rate_pv).read(data_type="time").metadata.timestamp > stamp
    probe.write(ioc.readback_offset_pv, -1.0)
    assert float(probe.wait_for([rb], [upper - 1.0], 2.0)[0]) == upper - 1.0
    probe.write(sp, 0.0)
    assert ioc.alive()


def test_a_stall_shorter_than_restore_timeout_ends_restored(ioc, probe, ring, tmp_path, capsys,
                                                            run_mode):  # fmt: skip
    """After 4 puts the IOC stalls every put for 3 s (each then refused: an IOC restarting)
    and the run aborts; with restore_timeout 8 s the restore retries through the stall and sets
    the knobs exactly back (exit 1); with restore_timeout 0 and one attempt it ends in exit 3."""
    start = start_of(ring)
    results = {}
    for window, attempts, name in ((8.0, 1, "long"), (0.0, 1, "short")):
        probe.write_many(ioc.setpoint_pvs[:2], start)
        log = f"{name}.jsonl"
        watcher = after_puts(ioc, 4, lambda: probe.write(ioc.stall_puts_pv, 3.0))
        config = write_config(tmp_path, ioc, ring, name=f"{name}.yaml", budget=12, log=log,
                              restore_timeout=window, restore_attempts=attempts,
                              **run_mode)  # fmt: skip
        results[name] = cli.main(["optimize", "--config", config, "--quiet"])
        watcher.join(timeout=5.0)
        results[name + "_sp"] = probe.read_many(ioc.setpoint_pvs[:2])
        time.sleep(3.2)  # the stall is over before the next run
    captured = capsys.readouterr()
    assert results["long"] == 1, captured.err
    assert torch.equal(results["long_sp"], start)
    assert results["short"] == 3
    assert not torch.equal(results["short_sp"], start)


@pytest.mark.slow  # an IOC of its own, killed and restarted: ~45 s on a busy host
def test_an_ioc_restart_within_restore_timeout_ends_restored_in_one_line_each(
    tmp_path, capsys, run_mode
):
    """The IOC is killed after 6 puts and restarted on its port 3 s later (its knobs at their
    power-on zeros): the run aborts, the restore retries through the restart (restore_timeout
    30 s) and puts the knobs exactly back at the start (exit 1); caproto's reconnection records
    are one line each (no traceback in stderr)."""
    from pigp_torch.simulated_epics.ioc import start_sim_ioc
    from pigp_torch.simulation import Spear3Coupling

    from .conftest import Probe

    ring = Spear3Coupling(1)
    start = start_of(ring)
    with start_sim_ioc(1, update_period=0.05) as own:
        probe = Probe()
        probe.write_many(own.setpoint_pvs[:2], start)
        box = {}

        def restart() -> None:
            own.kill()
            time.sleep(3.0)
            box["ioc"] = start_sim_ioc(1, port=own.port, update_period=0.05,
                                       set_client_env=False)  # fmt: skip
            box["handle"] = box["ioc"].__enter__()

        watcher = after_puts(own, 6, restart)
        config = write_config(tmp_path, own, ring, budget=30, restore_timeout=30.0, **run_mode)
        try:
            code = cli.main(["optimize", "--config", config, "--quiet"])
            watcher.join(timeout=60.0)
            now = probe.wait_for(own.setpoint_pvs[:2], start, 5.0)
        finally:
            probe.close()
            if "ioc" in box:
                box["ioc"].__exit__(None, None, None)
    captured = capsys.readouterr()
    assert code == 1, captured.err
    assert torch.equal(now, start)
    assert "knobs restored to initial" in captured.out
    assert "Traceback" not in captured.err
