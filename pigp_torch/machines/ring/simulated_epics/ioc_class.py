"""The PVs of the simulated ring IOC as a class: :func:`sim_ioc_class` adds one setpoint and one
readback PV per knob, the loss rate and the switches (the table in
:mod:`~.ioc_pvs`) to
:class:`~.ioc_pvs.SimRingIOC`."""

from __future__ import annotations

import math

import torch
from caproto import ChannelType
from caproto.server import pvproperty

from pigp_torch._utils import DTYPE, check_bounds
from pigp_torch.machine.base import check_setting
from pigp_torch.machines.ring.simulated_epics import (
    ALARM_KNOB_SUFFIX,
    ALARM_READINGS_SUFFIX,
    ALARM_SEVERITY_SUFFIX,
    DEFAULT_PREFIX,
    FROZEN_SUFFIX,
    GLITCH_READINGS_SUFFIX,
    GLITCH_VALUE_SUFFIX,
    LOSS_RATE_LIMITS,
    LOSS_RATE_SUFFIX,
    NAN_READINGS_SUFFIX,
    NARROW_KNOB_SUFFIX,
    NARROW_LIMIT_SUFFIX,
    READBACK_DELAY_SUFFIX,
    READBACK_OFFSET_SUFFIX,
    READBACK_SUFFIX,
    REBOOT_ON_READ_SUFFIX,
    SETPOINT_SUFFIX,
    STALL_PUTS_SUFFIX,
    STUCK_KNOB_SUFFIX,
)
from pigp_torch.machines.ring.simulated_epics.ioc_pvs import SimRingIOC


async def _put_alarm_knob(group, instance, value):
    await group._on_alarm_knob(int(value))


def sim_ioc_class(
    knob_names,
    bounds,
    *,
    prefix: str = DEFAULT_PREFIX,
    setpoint_suffix: str = SETPOINT_SUFFIX,
    readback_suffix: str = READBACK_SUFFIX,
    x_init=None,
    readback_delay: float = 0.0,
    nan_readings: int = 0,
    units: str = "A",
) -> type[SimRingIOC]:
    r"""A :class:`SimRingIOC` subclass with the PVs of ``knob_names`` (see the module table).

    The pvproperties are created here because caproto collects them at class creation and the
    knob names are data. Each setpoint has control limits :math:`[\ell_i, h_i]` from ``bounds``,
    so caproto itself refuses a put outside them (the put fails with an error status; the
    setpoint and readback are unchanged).

    Args:
        knob_names: ``K`` knob names (PV name stems, e.g. ``"01G-QSS4"``).
        bounds: ``2 x K`` knob bounds.
        prefix: prefix of the loss-rate and switch PVs.
        setpoint_suffix, readback_suffix: appended to each knob name.
        x_init: ``K`` initial setpoints and readbacks (default zeros: skews off).
        readback_delay: initial value of the ``Sim:ReadbackDelay`` switch (s, >= 0).
        nan_readings: initial value of the ``Sim:NanReadings`` switch (>= 0).
        units: engineering units of the knob PVs (default ``"A"``).
    """
    names = [str(n) for n in knob_names]
    bounds = check_bounds(bounds)
    if len(names) != bounds.shape[1]:
        raise ValueError(f"{len(names)} knob names for {bounds.shape[1]} knobs")
    if len(set(names)) != len(names):
        raise ValueError("knob names must be unique")
    x0 = torch.zeros(len(names), dtype=DTYPE) if x_init is None else x_init
    x0 = check_setting(x0, bounds).tolist()
    if not (0.0 <= float(readback_delay) < math.inf):
        raise ValueError(f"readback_delay must be finite and >= 0, got {readback_delay}")
    if int(nan_readings) < 0:
        raise ValueError(f"nan_readings must be >= 0, got {nan_readings}")
    attrs: dict = {"knob_names": tuple(names), "__module__": __name__}
    _add_knobs(attrs, names, bounds, x0, (setpoint_suffix, readback_suffix), str(units))
    attrs["loss_rate"] = _loss_rate(prefix)
    _add_switches(attrs, prefix, len(names), float(readback_delay), int(nan_readings), str(units))
    _add_alarm_switches(attrs, prefix, len(names))
    return type("SimRingIOCWithKnobs", (SimRingIOC,), attrs)


def _add_knobs(attrs: dict, names, bounds, x0, suffixes: tuple[str, str], units: str) -> None:
    """One setpoint (control limits ``bounds``, put through ``_on_setpoint``) and one read-only
    readback PV (its own alarm) per knob, starting at ``x0``."""
    setpoint_suffix, readback_suffix = suffixes
    for i, name in enumerate(names):
        lo, hi = float(bounds[0, i]), float(bounds[1, i])
        setpoint = pvproperty(
            value=x0[i],
            name=f"{name}{setpoint_suffix}",
            dtype=ChannelType.DOUBLE,
            lower_ctrl_limit=lo,
            upper_ctrl_limit=hi,
            precision=6,
            units=str(units),
            doc=f"setpoint of {name} ({units}), limits [{lo}, {hi}]",
        )

        async def put(group, instance, value, _i=i):
            await group._on_setpoint(_i, value)

        setpoint.putter(put)
        attrs[f"setpoint_{i}"] = setpoint
        attrs[f"readback_{i}"] = pvproperty(
            value=x0[i],
            name=f"{name}{readback_suffix}",
            dtype=ChannelType.DOUBLE,
            read_only=True,
            precision=6,
            units=str(units),
            alarm_group=f"readback_{i}",  # its own alarm (caproto shares one per group)
            doc=f"readback of {name} ({units})",
        )


def _loss_rate(prefix: str):
    """The loss-rate PV (mA/min): read through ``_on_read``; its startup starts the refreshes."""
    loss_rate = pvproperty(
        value=float("nan"),
        name=f"{prefix}{LOSS_RATE_SUFFIX}",
        dtype=ChannelType.DOUBLE,
        read_only=True,
        precision=4,
        units="mA/min",
        lower_disp_limit=LOSS_RATE_LIMITS[0],
        upper_disp_limit=LOSS_RATE_LIMITS[1],
        alarm_group="loss_rate",
        doc="simulated loss rate at the readbacks plus Gaussian noise (mA/min)",
    )

    async def start_refresh(group, instance, async_lib):
        await group._refresh_loop(async_lib)

    async def get_loss_rate(group, instance):
        return await group._on_read()

    loss_rate.startup(start_refresh)
    loss_rate.getter(get_loss_rate)
    return loss_rate


def _add_switches(attrs: dict, prefix: str, d: int, readback_delay, nan_readings, units) -> None:
    """The fault-injection switches of the module table of :mod:`~.ioc_pvs` but the severity
    hooks (``d`` knobs; the initial ``readback_delay`` in s and ``nan_readings``)."""
    attrs["readback_delay"] = pvproperty(
        value=float(readback_delay),
        name=f"{prefix}{READBACK_DELAY_SUFFIX}",
        dtype=ChannelType.DOUBLE,
        lower_ctrl_limit=0.0,
        upper_ctrl_limit=3600.0,
        units="s",
        doc="fault injection: seconds before a readback follows its setpoint",
    )
    switches = (  # (attribute, suffix, initial value, upper limit, meaning)
        ("nan_readings", NAN_READINGS_SUFFIX, int(nan_readings), 1_000_000,
         "fault injection: the next N reads of the loss rate return NaN"),
        ("frozen", FROZEN_SUFFIX, 0, 1,
         "fault injection (tests): 1 stops the loss-rate refreshes"),
        ("reboot_on_read", REBOOT_ON_READ_SUFFIX, 0, 1_000_000,
         "fault injection (tests): reboot (knobs to power-on values) at the N-th read"),
        ("glitch_readings", GLITCH_READINGS_SUFFIX, 0, 1_000_000,
         "fault injection: the next N reads of the loss rate return GlitchValue"),
        ("stuck_knob", STUCK_KNOB_SUFFIX, 0, d,
         "fault injection: k >= 1 freezes the readback of knob k (1-based); 0 releases it"),
        ("narrow_knob", NARROW_KNOB_SUFFIX, 0, d,
         "fault injection: the knob (1-based) NarrowLimit narrows; 0: every knob"),
    )  # fmt: skip
    for attr, suffix, value, upper, doc in switches:
        attrs[attr] = pvproperty(
            value=value,
            name=f"{prefix}{suffix}",
            dtype=ChannelType.LONG,
            lower_ctrl_limit=0,
            upper_ctrl_limit=upper,
            doc=doc,
        )
    attrs["glitch_value"] = pvproperty(
        value=1e30,
        name=f"{prefix}{GLITCH_VALUE_SUFFIX}",
        dtype=ChannelType.DOUBLE,
        doc="fault injection: the value a glitch reading returns",
    )
    offset = pvproperty(
        value=0.0,
        name=f"{prefix}{READBACK_OFFSET_SUFFIX}",
        dtype=ChannelType.DOUBLE,
        units=str(units),
        doc="fault injection: every readback is its setpoint plus this offset",
    )

    async def put_offset(group, instance, value):
        await group._on_offset(float(value))

    offset.putter(put_offset)
    attrs["readback_offset"] = offset
    for attr, suffix, unit, hook, doc in (
        ("narrow_limit", NARROW_LIMIT_SUFFIX, str(units), "_on_narrow",
         "fault injection: L > 0 narrows the control limits to [-L, L]; 0: the bounds"),
        ("stall_puts", STALL_PUTS_SUFFIX, "s", "_on_stall",
         "fault injection: setpoint puts stall this many seconds from now, then fail"),
    ):  # fmt: skip
        prop = pvproperty(
            value=0.0,
            name=f"{prefix}{suffix}",
            dtype=ChannelType.DOUBLE,
            units=unit,
            lower_ctrl_limit=0.0,
            upper_ctrl_limit=1e6,
            doc=doc,
        )

        async def put_hook(group, instance, value, _hook=hook):
            await getattr(group, _hook)(float(value))

        prop.putter(put_hook)
        attrs[attr] = prop


def _add_alarm_switches(attrs: dict, prefix: str, d: int) -> None:
    """The severity hooks (module table of :mod:`~.ioc_pvs`): the severity
    served, on how many loss-rate reads (-1: every one), on which knob's readback."""
    alarms = (
        ("alarm_severity", ALARM_SEVERITY_SUFFIX, 3, 0, 3,
         "fault injection: the alarm severity served (0 NO_ALARM .. 3 INVALID)"),
        ("alarm_readings", ALARM_READINGS_SUFFIX, 0, -1, 1_000_000,
         "fault injection: the next N reads of the loss rate carry AlarmSeverity; -1 every one"),
        ("alarm_knob", ALARM_KNOB_SUFFIX, 0, 0, d,
         "fault injection: k >= 1 serves knob k's readback with AlarmSeverity; 0 none"),
    )  # fmt: skip
    for attr, suffix, value, lower, upper, doc in alarms:
        attrs[attr] = pvproperty(
            value=value,
            name=f"{prefix}{suffix}",
            dtype=ChannelType.LONG,
            lower_ctrl_limit=lower,
            upper_ctrl_limit=upper,
            doc=doc,
        )
    attrs["alarm_knob"].putter(_put_alarm_knob)
