"""The simulated IOC: PV layout, limits, readback delay, NaN injection, seeded noisy readings.

Most checks drive the PV group in-process (``asyncio.run``, no network) on a closed-form ring;
the last ones go over Channel Access to the shared IOC.
"""

import argparse
import asyncio
import os
import socket
from types import SimpleNamespace

import pytest
import torch
from caproto import CaprotoTimeoutError

from pigp_torch.machine import SimulatedMachine
from pigp_torch.simulated_epics import SIM_CA_PORT
from pigp_torch.simulated_epics.ioc import (
    client_environment,
    free_port,
    patched_environ,
    server_environment,
    sim_ioc_class,
)


class Paraboloid:
    """f(x) = 1 - |x|^2 on [-1, 1] x [-2, 2]: a ring stand-in with a closed form."""

    knob_names = ("A:K", "B:K")
    bounds = torch.tensor([[-1.0, -2.0], [1.0, 2.0]], dtype=torch.float64)

    def evaluate(self, x):
        x = torch.as_tensor(x, dtype=torch.float64)
        return SimpleNamespace(loss_rate=1.0 - (x**2).sum(-1))


def make_ioc(noise=0.0, seed=0, **options):
    sim = Paraboloid()
    cls = sim_ioc_class(sim.knob_names, sim.bounds, prefix="T:", **options)
    return cls(prefix="", machine=SimulatedMachine(sim, noise=noise, seed=seed))


def test_pv_names_limits_and_initial_values():
    """Setpoint/readback per knob, loss rate and switches under the prefix; limits = bounds."""
    ioc = make_ioc(x_init=[0.5, -1.0], readback_delay=0.2, nan_readings=3)
    assert ioc.pv_names == [
        "A:K:CurrSetpt",
        "A:K:Curr1",
        "B:K:CurrSetpt",
        "B:K:Curr1",
        "T:BeamLossRate",
        "T:Sim:ReadbackDelay",
        "T:Sim:NanReadings",
        "T:Sim:Frozen",
        "T:Sim:RebootOnRead",
        "T:Sim:GlitchReadings",
        "T:Sim:StuckKnob",
        "T:Sim:NarrowKnob",
        "T:Sim:GlitchValue",
        "T:Sim:ReadbackOffset",
        "T:Sim:NarrowLimit",
        "T:Sim:StallPuts",
        "T:Sim:AlarmSeverity",
        "T:Sim:AlarmReadings",
        "T:Sim:AlarmKnob",
    ]
    assert ioc.loss_rate_pv == "T:BeamLossRate"
    assert [sp.value for sp in ioc.setpoints] == [0.5, -1.0]
    assert [rb.value for rb in ioc.readbacks] == [0.5, -1.0]
    assert (ioc.setpoints[1].lower_ctrl_limit, ioc.setpoints[1].upper_ctrl_limit) == (-2.0, 2.0)
    assert ioc.readback_delay.value == 0.2 and ioc.nan_readings.value == 3


def test_out_of_bounds_setpoint_refused_in_process():
    """A put outside the control limits raises; setpoint and readback keep their values."""
    ioc = make_ioc()

    async def scenario():
        with pytest.raises(Exception, match=r"Cannot write data 2.5. Limits are set to -2.0"):
            await ioc.setpoints[1].write(2.5)
        await ioc.setpoints[0].write(-1.0)  # the bound itself is allowed

    asyncio.run(scenario())
    assert ioc.setpoints[1].value == 0.0 and ioc.readbacks[1].value == 0.0
    assert ioc.readbacks[0].value == -1.0


def test_loss_rate_is_taken_at_the_readbacks():
    """With a readback delay the reading follows the readbacks, not the setpoints."""
    ioc = make_ioc(readback_delay=0.1)

    async def scenario():
        await ioc.setpoints[0].write(0.5)
        before = (ioc.readbacks[0].value, ioc._refresh())
        await asyncio.sleep(0.25)
        return before, (ioc.readbacks[0].value, ioc._refresh())

    before, after = asyncio.run(scenario())
    assert before == (0.0, 1.0)  # f(0, 0)
    assert after == (0.5, 0.75)  # f(0.5, 0) = 1 - 0.25


def test_latest_put_wins_over_a_delayed_readback():
    """Two puts within the delay: the readback ends at the second value."""
    ioc = make_ioc(readback_delay=0.1)

    async def scenario():
        await ioc.setpoints[1].write(1.0)
        await asyncio.sleep(0.03)
        await ioc.setpoints[1].write(-1.5)
        await asyncio.sleep(0.25)

    asyncio.run(scenario())
    assert ioc.readbacks[1].value == -1.5


def test_nan_readings_count_client_reads():
    """Sim:NanReadings = 2: the next two reads are NaN, then the published value returns."""
    ioc = make_ioc(x_init=[0.5, 0.5])

    async def reads():
        await ioc.nan_readings.write(2)
        return [await ioc._on_read() for _ in range(3)]

    values = asyncio.run(reads())
    assert [v != v for v in values[:2]] == [True, True]
    assert values[2] is None  # the stored value is served ...
    assert ioc.loss_rate.value == 0.5  # ... and it is the published one again: 1 - 0.25 - 0.25
    assert ioc.nan_readings.value == 0


def test_client_reads_keep_the_refresh_timestamp_and_frozen_stops_refreshes():
    """A client read does not renew the loss rate's timestamp; with Sim:Frozen = 1 the refresh
    loop publishes nothing (value and timestamp stay), with 0 it publishes again."""
    from caproto import ChannelType

    ioc = make_ioc(x_init=[0.5, 0.5])
    ioc.update_period = 0.02

    class Lib:  # the async_lib the server passes to startup hooks
        class library:
            sleep = staticmethod(asyncio.sleep)

    async def scenario():
        task = asyncio.ensure_future(ioc._refresh_loop(Lib))
        await asyncio.sleep(0.05)
        await ioc.frozen.write(1)
        await asyncio.sleep(0.03)
        stamp = ioc.loss_rate.timestamp
        for _ in range(3):
            await ioc.loss_rate.read(ChannelType.TIME_DOUBLE)
        await asyncio.sleep(0.1)
        frozen_stamp = ioc.loss_rate.timestamp
        await ioc.frozen.write(0)
        await asyncio.sleep(0.1)
        task.cancel()
        return stamp, frozen_stamp, ioc.loss_rate.timestamp

    stamp, frozen_stamp, later = asyncio.run(scenario())
    assert frozen_stamp == stamp and later > stamp


def test_reboot_on_read_drops_the_knobs_to_their_power_on_values():
    """Sim:RebootOnRead = 2: the first read changes nothing, the second is answered and then
    every setpoint and readback is back at the initial knobs."""
    ioc = make_ioc(x_init=[0.5, -1.0])

    async def scenario():
        await ioc.setpoints[0].write(0.25)
        await ioc.setpoints[1].write(1.5)
        await ioc.reboot_on_read.write(2)
        await ioc._on_read()
        first = [sp.value for sp in ioc.setpoints]
        await ioc._on_read()
        return first

    first = asyncio.run(scenario())
    assert first == [0.25, 1.5]
    assert [sp.value for sp in ioc.setpoints] == [0.5, -1.0]
    assert [rb.value for rb in ioc.readbacks] == [0.5, -1.0]
    assert ioc.reboot_on_read.value == 0


def test_noise_is_the_seeded_simulated_machine_noise():
    """Successive refreshes equal a SimulatedMachine with the same noise and seed, reading by
    reading (the IOC adds no randomness of its own)."""
    ioc = make_ioc(noise=0.04, seed=7, x_init=[0.3, -0.4])
    twin = SimulatedMachine(Paraboloid(), noise=0.04, seed=7, x_init=[0.3, -0.4])
    got = [ioc._last_reading] + [ioc._refresh() for _ in range(4)]  # first one at construction
    assert got == [twin.read() for _ in range(5)]
    assert len(set(got)) == 5


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"knob_names": ["A"]}, r"1 knob names for 2 knobs"),
        ({"knob_names": ["A", "A"]}, r"knob names must be unique"),
        ({"x_init": [0.0, 3.0]}, r"outside bounds"),
        ({"readback_delay": -1.0}, r"readback_delay must be finite and >= 0"),
        ({"nan_readings": -1}, r"nan_readings must be >= 0"),
    ],
)
def test_ioc_class_validation(kwargs, message):
    """Inconsistent knob names, an initial setting outside the bounds or bad switches."""
    args = {"knob_names": ["A", "B"], **kwargs}
    with pytest.raises(ValueError, match=message):
        sim_ioc_class(bounds=Paraboloid.bounds, **args)


def test_update_period_must_be_positive():
    cls = sim_ioc_class(Paraboloid.knob_names, Paraboloid.bounds)
    with pytest.raises(ValueError, match="update_period must be positive"):
        cls(prefix="", machine=SimulatedMachine(Paraboloid(), noise=0.0), update_period=0.0)


def test_environment_helpers():
    """Loopback-only server/client variables; patched_environ restores what was there."""
    assert server_environment(6000)["EPICS_CAS_INTF_ADDR_LIST"] == "127.0.0.1"
    assert server_environment(6000)["EPICS_CA_SERVER_PORT"] == "6000"
    env = client_environment(6000)
    assert env["EPICS_CA_ADDR_LIST"] == "127.0.0.1:6000"
    assert env["EPICS_CA_AUTO_ADDR_LIST"] == "NO"
    before = os.environ.get("EPICS_CA_ADDR_LIST")
    with patched_environ(env):
        assert os.environ["EPICS_CA_ADDR_LIST"] == "127.0.0.1:6000"
    assert os.environ.get("EPICS_CA_ADDR_LIST") == before


def test_free_port_is_free_for_tcp_and_udp():
    port = free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
        tcp.bind(("127.0.0.1", port))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("127.0.0.1", port))


def test_the_docs_point_clients_at_the_default_port():
    """README, docs/xopt.md and the examples name serve-sim's default port, never CA's 5064."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    for name in ("README.md", "docs/xopt.md", "examples/run_epics.yaml",
                 "examples/badger_routine.py"):  # fmt: skip
        text = (root / name).read_text(encoding="utf-8")
        assert str(SIM_CA_PORT) in text and "5064" not in text, name


def test_serve_sim_parser():
    """`pigp serve-sim` registers with its options and defaults."""
    from pigp_torch.commands import serve_sim

    parser = argparse.ArgumentParser(prog="pigp")
    sub = parser.add_subparsers(dest="command", required=True)
    bench = sub.add_parser("bench").add_subparsers(dest="bench_command")
    serve_sim.register(sub, bench)
    assert set(sub.choices) == {"bench", "serve-sim"} and not bench.choices
    args = parser.parse_args(["serve-sim"])
    assert (args.seed, args.knobs, args.noise, args.prefix) == (1, "paper13", 0.04, "SPEAR:")
    assert (args.port, args.update_period, args.readback_delay) == (SIM_CA_PORT, 0.1, 0.0)
    assert SIM_CA_PORT not in (5064, 5065, 5075, 5076)  # CA's and pvAccess's standard ports
    from pigp_torch.integrations.badger import SERVE_HINT

    assert f"127.0.0.1:{SIM_CA_PORT}" in SERVE_HINT and f"ca_port {SIM_CA_PORT}" in SERVE_HINT
    assert "5064" not in SERVE_HINT  # badger-setup's hint names the default, not CA's port
    assert args.func is serve_sim.cmd_serve_sim
    args = parser.parse_args(
        ["serve-sim", "--seed", "3", "--port", "5999", "--prefix", "X:", "--readback-delay", "2"]
    )
    assert (args.seed, args.port, args.prefix, args.readback_delay) == (3, 5999, "X:", 2.0)


# ----------------------------------------------------------------------------- over CA
def test_ioc_refuses_out_of_bounds_put_over_ca(ioc, probe):
    """A raw CA put outside the knob bounds fails; setpoint and readback are unchanged."""
    sp, rb = ioc.setpoint_pvs[2], ioc.readback_pvs[2]
    with pytest.raises(CaprotoTimeoutError):  # caproto's client: a refused put never completes
        probe.write(sp, 30.01, timeout=0.5)  # amps: just beyond the windings' +-30 A
    assert probe.read(sp) == 0.0 and probe.read(rb) == 0.0
    probe.write(sp, -30.0)  # the bound itself is accepted
    assert probe.read(rb) == -30.0


def test_readback_delay_over_ca(ioc, probe):
    """Sim:ReadbackDelay delays the readback of a put by that many seconds."""
    import time

    probe.write(ioc.readback_delay_pv, 0.4)
    t0 = time.monotonic()
    probe.write(ioc.setpoint_pvs[0], 0.004)
    assert probe.read(ioc.readback_pvs[0]) == 0.0
    got = probe.wait_for([ioc.readback_pvs[0]], [0.004], timeout=3.0)
    assert float(got[0]) == 0.004
    assert time.monotonic() - t0 >= 0.4


def _serve_sim(tmp_path, args, *, sigint, ready):
    """Start `pigp serve-sim ARGS` with SIGINT set to ``sigint`` in the child; wait (<= 90 s)
    until its log shows ``ready``. Returns ``(process, log path, log text)``."""
    import signal
    import subprocess
    import sys
    import time

    code = (
        "import argparse, sys; from pigp_torch.commands import serve_sim; "
        "p = argparse.ArgumentParser(); serve_sim.register(p.add_subparsers(), None); "
        "a = p.parse_args(sys.argv[1:]); sys.exit(a.func(a))"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    log = tmp_path / "serve-sim.log"
    with open(log, "wb") as sink:  # a file, not a pipe: polling it never blocks
        proc = subprocess.Popen(
            [sys.executable, "-c", code, "serve-sim", *args],
            stdout=sink,
            stderr=subprocess.STDOUT,
            env=env,
            preexec_fn=lambda: signal.signal(signal.SIGINT, sigint),
        )
    deadline = time.monotonic() + 90
    while ready not in (out := log.read_text()):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait(10)
            raise AssertionError(out)
        time.sleep(0.1)
    return proc, log, out


@pytest.mark.slow
def test_serve_sim_runs_in_the_foreground_and_stops_on_ctrl_c(tmp_path):
    """`pigp serve-sim` prints the PVs, answers over CA on 127.0.0.1, exits 0 on SIGINT."""
    import signal

    from caproto.threading.client import Context

    port = free_port()
    # A job started in the background (nohup, CI runners) inherits SIGINT ignored, and Python
    # then installs no KeyboardInterrupt handler: give the child the default disposition.
    proc, log, out = _serve_sim(tmp_path, ["--port", str(port), "--prefix", "SIM:"],
                                sigint=signal.SIG_DFL, ready="  SIM:Sim:NanReadings")  # fmt: skip
    try:
        assert f"ready on 127.0.0.1:{port}" in out
        assert "  01G-QSS4:CurrSetpt\n" in out and "  SIM:BeamLossRate\n" in out
        with patched_environ(client_environment(port)):
            ctx = Context()
            (pv,) = ctx.get_pvs("SIM:BeamLossRate", timeout=5.0)
            value = float(pv.read(timeout=5.0).data[0])
            ctx.disconnect()
        assert 0.3 < value < 0.7  # seed 1, skews off: 0.50 mA/min + noise
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0, log.read_text()
        assert "simulated IOC stopped" in log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


@pytest.mark.slow  # a Python start with torch and pyAT imports: ~4 s idle, >10 s on a busy host
def test_start_sim_ioc_reports_a_failed_start():
    """An IOC that exits during start-up: RuntimeError with its log; no process left behind."""
    from pigp_torch.simulated_epics.ioc import start_sim_ioc

    with pytest.raises(RuntimeError, match=r"(?s)simulated IOC exited with code 1.*noise must be"):
        with start_sim_ioc(1, noise=-1.0, startup_timeout=60):
            pass  # pragma: no cover - never reached


def test_a_single_winding_is_accepted_by_knobs():
    """`--knobs 01G-QSS4` (one winding, no comma) is a list of one; sets stay names; unknown
    windings are refused with the simulator's message."""
    import argparse

    from pigp_torch.commands.ring_options import add_ring_arguments, ring_spec_from_args

    parser = add_ring_arguments(argparse.ArgumentParser())

    def spec(text):
        return ring_spec_from_args(parser.parse_args(["--knobs", text]))

    assert spec("01G-QSS4").knobs == ("01G-QSS4",)
    assert spec("01G-QSS4, 02G-QSS3").knobs == ("01G-QSS4", "02G-QSS3")
    assert spec("paper13").knobs == "paper13"
    with pytest.raises(ValueError, match="unknown winding names"):
        spec("NOT-A-WINDING").build(1)


@pytest.mark.slow  # a Python start with torch and pyAT imports (~5-10 s)
def test_serve_sim_started_in_the_background_stops_on_sigterm(tmp_path):
    """`pigp serve-sim --knobs 01G-QSS4` started as a script's background job (SIGINT ignored)
    serves the one knob and exits 0 on SIGTERM."""
    import signal

    port = free_port()
    args = ["--port", str(port), "--knobs", "01G-QSS4"]
    proc, log, out = _serve_sim(tmp_path, args, sigint=signal.SIG_IGN,
                                ready="  SPEAR:Sim:RebootOnRead")  # fmt: skip
    try:
        assert "  01G-QSS4:CurrSetpt\n" in out and "02G-QSS3" not in out
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0, log.read_text()
        assert "simulated IOC stopped" in log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
