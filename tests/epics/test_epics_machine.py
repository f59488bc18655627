"""EpicsMachine over real Channel Access against the simulated IOC (127.0.0.1)."""

import gc
import math
import os
import time

import pytest
import torch

from pigp_torch.machine.base import Machine
from pigp_torch.machine.epics import TOLERANCE_ABS, TOLERANCE_REL, EpicsMachine
from pigp_torch.machine.errors import MachineError, ReadbackError, ReadError

from .conftest import FAST, NOISE, UPDATE_PERIOD


def make_machine(handle, context=None, **options):
    opts = {**FAST, "context": context, **options}
    bounds = opts.pop("bounds", None)
    if bounds is None:
        lim = torch.full((len(handle.knob_names),), 0.015, dtype=torch.float64)
        bounds = torch.stack([-lim, lim])
    return EpicsMachine(handle.knob_names, bounds, handle.loss_rate_pv, **opts)


def pattern(d: int, scale: float = 0.004) -> torch.Tensor:
    """A distinctive in-bounds setting: every knob different and nonzero, signs alternating."""
    signs = torch.tensor([(-1.0) ** i for i in range(d)], dtype=torch.float64)
    return scale * signs * torch.linspace(0.1, 1.0, d, dtype=torch.float64)


def test_round_trip_set_get_read(ioc, probe, ring):
    """A set reaches the IOC, get() returns the readbacks, read() matches the simulator."""
    x = pattern(len(ioc.knob_names))
    with make_machine(ioc, n_average=1) as m:
        assert isinstance(m, Machine)
        m.set(x)
        assert torch.equal(probe.read_many(ioc.setpoint_pvs), x)
        assert torch.equal(probe.read_many(ioc.readback_pvs), x)
        assert torch.equal(m.get(), x)
        n = 10
        readings = []
        for _ in range(n):
            readings.append(m.read())
            time.sleep(1.5 * UPDATE_PERIOD)  # let the IOC publish a fresh noisy value
    f_true = float(ring.loss_rate(x))
    mean = sum(readings) / n
    assert abs(mean - f_true) < 5 * NOISE / math.sqrt(n), (mean, f_true)
    assert len(set(readings)) >= n // 2  # fresh readings, not one repeated value
    assert m.n_reads == n and m.n_invalid_readings == 0


def test_read_averages_n_readings(ioc, ring, ca_context):
    """n_average readings spaced by average_interval: the mean is within 5 sigma/sqrt(n)."""
    with make_machine(ioc, ca_context, n_average=8, average_interval=1.5 * UPDATE_PERIOD) as m:
        y = m.read()
        assert m.n_reads == 8
    f_true = float(ring.loss_rate(torch.zeros(len(ioc.knob_names), dtype=torch.float64)))
    assert abs(y - f_true) < 5 * NOISE / math.sqrt(8)


def test_get_reads_the_readbacks_not_a_cache(ioc, probe, ca_context):
    """A change made by another client shows in get() at once."""
    x = pattern(len(ioc.knob_names), 0.003)
    with make_machine(ioc, ca_context) as m:
        assert torch.equal(m.get(), torch.zeros(len(ioc.knob_names), dtype=torch.float64))
        probe.write_many(ioc.setpoint_pvs, x)
        assert torch.equal(m.get(), x)


def test_bounds_and_max_step_refused_before_any_write(ioc, probe, ca_context):
    """Out-of-bounds or too-large steps raise ValueError and leave every IOC setpoint unchanged."""
    d = len(ioc.knob_names)
    x0 = pattern(d, 0.002)
    probe.write_many(ioc.setpoint_pvs, x0)
    with make_machine(ioc, ca_context, max_step=0.05) as m:  # 0.05 * 0.015 = 7.5e-4 per set
        assert torch.allclose(m.max_step, torch.full((d,), 7.5e-4, dtype=torch.float64))
        out = x0.clone()
        out[4] = 0.0151  # one knob just outside; the others would be allowed
        with pytest.raises(ValueError, match=r"outside bounds"):
            m.set(out)
        assert torch.equal(probe.read_many(ioc.setpoint_pvs), x0)
        big = x0.clone()
        big[7] += 1e-3  # > 7.5e-4
        with pytest.raises(ValueError, match=r"step too large on knob indices \[7\]"):
            m.set(big)
        assert torch.equal(probe.read_many(ioc.setpoint_pvs), x0)
        ok = x0.clone()
        ok[7] += 7e-4
        m.set(ok)
        assert torch.equal(probe.read_many(ioc.setpoint_pvs), ok)


def test_max_step_is_measured_from_the_readbacks(ioc, probe, ca_context):
    """If another client moved the knobs, max_step applies from where they really are."""
    d = len(ioc.knob_names)
    with make_machine(ioc, ca_context, max_step=0.05) as m:
        moved = torch.full((d,), 0.005, dtype=torch.float64)
        probe.write_many(ioc.setpoint_pvs, moved)
        with pytest.raises(ValueError, match="step too large"):
            m.set(torch.zeros(d, dtype=torch.float64))  # 0.005 > 7.5e-4 from the readbacks
        m.set(moved + 5e-4)  # a small step from the real position is fine


def test_put_refused_by_the_ioc_raises_machine_error(ioc, probe, ca_context, ring):
    """Machine bounds wider than the IOC's limits (the start-up check switched off): the IOC
    refuses the put, the machine raises PutRefused naming the PV and the IOC's reason."""
    wide = ring.bounds * 4 / 3
    x = torch.zeros(len(ioc.knob_names), dtype=torch.float64)
    x[0] = float(ring.bounds[1, 0]) * 1.2  # inside the machine's bounds, outside the IOC's
    with make_machine(ioc, ca_context, bounds=wide, check_control_limits=False) as m:
        with pytest.raises(MachineError, match=r"IOC refused the put\(s\) to 01G-QSS4:CurrSetpt: "
                           r"ECA_PUTFAIL .*Limits are set to -30.0 and 30.0"):  # fmt: skip
            m.set(x)
    assert probe.read(ioc.setpoint_pvs[0]) == 0.0
    assert probe.read(ioc.readback_pvs[0]) == 0.0


def test_bounds_outside_the_ioc_control_limits_are_refused_at_start(ioc, ca_context, ring):
    """Bounds wider than the setpoint PVs' DRVL/DRVH: ValueError at connection, naming the knob
    and both ranges; bounds inside them are accepted and the limits are kept."""
    wide = ring.bounds.clone()
    wide[1, 2] = float(ring.bounds[1, 2]) * 2
    with pytest.raises(ValueError, match=rf"{ioc.knob_names[2]}: bounds .* outside DRVL/DRVH"):
        make_machine(ioc, ca_context, bounds=wide)
    with make_machine(ioc, ca_context, bounds=ring.bounds / 2) as m:
        assert torch.equal(m.control_limits, ring.bounds)


def test_nan_readings_are_retried(ioc, probe, ca_context):
    """Up to read_retries NaN readings are retried; one more raises ReadError."""
    with make_machine(ioc, ca_context, read_retries=2) as m:
        probe.write(ioc.nan_readings_pv, 2)
        y = m.read()
        assert math.isfinite(y)
        assert m.n_invalid_readings == 2 and m.n_reads == 1
        assert probe.read(ioc.nan_readings_pv) == 0
        probe.write(ioc.nan_readings_pv, 3)
        with pytest.raises(ReadError, match=r"in 3 attempts: non-finite value nan"):
            m.read()
        assert m.n_invalid_readings == 5


def test_slow_readback_raises_readback_error(ioc, probe, ca_context):
    """Readbacks later than settle_time + timeout: ReadbackError naming the knobs."""
    d = len(ioc.knob_names)
    probe.write(ioc.readback_delay_pv, 1.0)
    x = pattern(d, 0.001)
    with make_machine(ioc, ca_context, settle_time=0.1, timeout=0.4) as m:
        t0 = time.monotonic()
        with pytest.raises(ReadbackError, match=r"13 knob\(s\) did not reach .* 01G-QSS4"):
            m.set(x)
        assert 0.5 <= time.monotonic() - t0 < 1.0  # settle + timeout, not the full delay
    assert torch.equal(probe.read_many(ioc.setpoint_pvs), x)  # the puts were made
    assert torch.equal(probe.wait_for(ioc.readback_pvs, x, timeout=3.0), x)


def test_readback_within_delay_is_accepted(ioc, probe, ca_context):
    """A readback delay shorter than settle_time + timeout is waited for."""
    probe.write(ioc.readback_delay_pv, 0.3)
    x = pattern(len(ioc.knob_names), 0.001)
    with make_machine(ioc, ca_context, settle_time=0.1, timeout=1.0) as m:
        m.set(x)
        assert torch.equal(m.get(), x)


def test_default_tolerance(ioc, ca_context):
    """Default tolerance 1e-6 of each knob's range + 1e-9; explicit scalar or per-knob values."""
    d = len(ioc.knob_names)
    with make_machine(ioc, ca_context) as m:
        expected = TOLERANCE_REL * 0.03 + TOLERANCE_ABS
        assert torch.allclose(m.tolerance, torch.full((d,), expected, dtype=torch.float64))
    with make_machine(ioc, ca_context, tolerance=1e-5) as m:
        assert torch.equal(m.tolerance, torch.full((d,), 1e-5, dtype=torch.float64))


def test_connection_failure_lists_missing_pvs(ioc):
    """PVs that do not answer within timeout are all named in the error."""
    names = list(ioc.knob_names)
    setpoints = [f"{n}:CurrSetpt" for n in names]
    setpoints[3] = "NO:SUCH:SETPOINT"
    lim = torch.full((len(names),), 0.015, dtype=torch.float64)
    t0 = time.monotonic()
    with pytest.raises(
        MachineError, match=r"2 PV\(s\) did not connect within 0.5 s: NO:SUCH:SETPOINT, NO:SUCH:PV"
    ) as err:
        EpicsMachine(
            names, torch.stack([-lim, lim]), "NO:SUCH:PV", setpoint_pvs=setpoints, timeout=0.5
        )
    assert time.monotonic() - t0 < 3.0
    assert "EPICS_CA_ADDR_LIST" in str(err.value) and "EPICS_CA_AUTO_ADDR_LIST" in str(err.value)


def test_close_and_context_manager(ioc):
    """close() is idempotent; a closed machine raises MachineError."""
    with make_machine(ioc) as m:
        m.get()
    with pytest.raises(MachineError, match="closed"):
        m.get()
    with pytest.raises(MachineError, match="closed"):
        m.read()
    m.close()
    assert "closed" in repr(m)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"setpoint_pvs": ["A", "B"]}, r"setpoint_pvs: 2 PV names for 13 knobs"),
        ({"n_average": 0}, r"n_average must be an integer >= 1"),
        ({"read_retries": -1}, r"read_retries must be an integer >= 0"),
        ({"settle_time": -0.1}, r"settle_time must be finite and >= 0"),
        ({"timeout": 0.0}, r"timeout must be positive and finite"),
        ({"tolerance": [1e-5, 1e-5]}, r"tolerance must be a scalar or \(13,\)"),
        ({"tolerance": -1e-5}, r"tolerance entries must be finite and >= 0"),
        ({"max_step": 0.0}, r"max_step entries must be positive"),
        ({"knob_names": ["K"] * 13}, r"knob names must be unique"),
    ],
)
def test_invalid_options_rejected_before_connecting(options, message):
    """Bad options raise ValueError at once (no PV is searched for)."""
    options = dict(options)
    names = options.pop("knob_names", [f"K{i}" for i in range(13)])
    lim = torch.full((13,), 0.015, dtype=torch.float64)
    with pytest.raises(ValueError, match=message):
        EpicsMachine(names, torch.stack([-lim, lim]), "OBJ", **options)


def test_readbacks_outside_bounds_at_start_refused(ioc, probe, ca_context):
    """A machine whose knobs already sit outside the given bounds is not constructed."""
    d = len(ioc.knob_names)
    probe.write_many(ioc.setpoint_pvs, torch.full((d,), 0.01, dtype=torch.float64))
    lim = torch.full((d,), 0.005, dtype=torch.float64)
    with pytest.raises(ValueError, match="the knobs' current readbacks are not allowed"):
        make_machine(ioc, ca_context, bounds=torch.stack([-lim, lim]))


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd")
def test_open_close_cycles_leak_no_file_descriptors(ioc):
    """Each EpicsMachine with a context of its own opens sockets and two selector (epoll)
    descriptors; close() releases all of them: after 5 open/read/close cycles the process holds
    no more descriptors than before (a long-lived process, e.g. Badger, opens one per run; a
    leak adds at least 3 per cycle). Fewer is no leak: a descriptor that an earlier test's
    caproto thread closes during the count (seen on a loaded machine, 35 before and 33 after)."""

    def n_fds() -> int:
        return len(os.listdir("/proc/self/fd"))

    def cycle():
        with make_machine(ioc) as m:  # no shared context: the machine owns one
            m.read()

    cycle()  # warm-up: caproto's one-per-process state
    gc.collect()  # descriptors of objects earlier tests dropped close now, not mid-count
    before = n_fds()
    for _ in range(5):
        cycle()
    gc.collect()
    assert n_fds() <= before


def test_the_step_limit_is_measured_from_the_setpoints_not_the_readbacks(ioc, probe):
    """With every readback 0.001 A above its setpoint, a set of exactly max_step from the
    setpoint is accepted and one a little beyond is refused before anything is written; the
    IOC's put log shows the accepted step, and last_acknowledged follows the puts."""
    d = len(ioc.knob_names)
    probe.write(ioc.readback_offset_pv, 0.001)
    m_step = 0.004
    with make_machine(ioc, max_step=torch.full((d,), m_step), tolerance=0.002) as m:
        x0 = m.setpoints()
        assert torch.equal(m.last_acknowledged, x0) and torch.equal(x0, torch.zeros(d))
        assert torch.allclose(m.get(), x0 + 0.001, atol=1e-12)  # the readbacks read off
        mark = ioc.n_puts()
        x1 = x0 - m_step  # 0.005 from the readbacks: refused if measured from them
        m.set(x1)
        assert torch.equal(m.last_acknowledged, x1)
        steps = [abs(p["value"] - p["previous"]) for p in ioc.puts(mark)]
        assert len(steps) == d and max(steps) == pytest.approx(m_step, abs=1e-15)
        with pytest.raises(ValueError, match="step too large"):
            m.set(x1 - m_step * 1.01)
        assert ioc.n_puts() == mark + d  # nothing written
        assert torch.equal(probe.read_many(ioc.setpoint_pvs), x1)
