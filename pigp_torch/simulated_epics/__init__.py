"""Alias: the simulated EPICS servers (the ring as a Channel Access IOC and a pvAccess server,
for tests and demos) moved whole to the ring kind's folder,
:mod:`pigp_torch.machines.ring.simulated_epics` (what they serve is the ring's);
``pigp_torch.simulated_epics`` and each of its modules (``pigp_torch.simulated_epics.ioc``, ...
as the moved module itself) still import, and so does the older ``pigp_torch.testing``."""

from pigp_torch._utils.aliases import alias_package
from pigp_torch.machines.ring.simulated_epics import (
    ALARM_KNOB_SUFFIX,
    ALARM_READINGS_SUFFIX,
    ALARM_SEVERITY_SUFFIX,
    DEFAULT_PREFIX,
    FROZEN_SUFFIX,
    GLITCH_READINGS_SUFFIX,
    GLITCH_VALUE_SUFFIX,
    LOOPBACK,
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
    SIM_CA_PORT,
    STALL_PUTS_SUFFIX,
    STUCK_KNOB_SUFFIX,
    add_ioc_arguments,
    free_ports,
)

alias_package(__name__, "pigp_torch.machines.ring.simulated_epics")

__all__ = [
    "ALARM_KNOB_SUFFIX",
    "ALARM_READINGS_SUFFIX",
    "ALARM_SEVERITY_SUFFIX",
    "DEFAULT_PREFIX",
    "FROZEN_SUFFIX",
    "GLITCH_READINGS_SUFFIX",
    "GLITCH_VALUE_SUFFIX",
    "LOOPBACK",
    "LOSS_RATE_LIMITS",
    "LOSS_RATE_SUFFIX",
    "NAN_READINGS_SUFFIX",
    "NARROW_KNOB_SUFFIX",
    "NARROW_LIMIT_SUFFIX",
    "READBACK_DELAY_SUFFIX",
    "READBACK_OFFSET_SUFFIX",
    "READBACK_SUFFIX",
    "REBOOT_ON_READ_SUFFIX",
    "SETPOINT_SUFFIX",
    "SIM_CA_PORT",
    "STALL_PUTS_SUFFIX",
    "STUCK_KNOB_SUFFIX",
    "add_ioc_arguments",
    "free_ports",
]
