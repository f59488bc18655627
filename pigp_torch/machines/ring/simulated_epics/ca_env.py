r"""The Channel Access environment of the test IOC (loopback only) and of its clients."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping

from pigp_torch.machines.ring.simulated_epics import (
    LOOPBACK,
    free_ports,
)

#: Printed by the IOC once its sockets are bound; :func:`start_sim_ioc` waits for it.
READY_MESSAGE = "pigp sim IOC ready"


# ----------------------------------------------------------------------------- environment
def server_environment(port: int) -> dict[str, str]:
    """EPICS variables that keep a server on 127.0.0.1 at ``port`` (searches, TCP, beacons).

    Beacons go to 127.0.0.1 at ``port`` too, i.e. to the server's own search socket, which
    ignores them: they never leave the host, and no "connection refused" error is logged every
    beacon period when no CA repeater listens on 5065 (as on a test machine).
    """
    return {
        "EPICS_CAS_INTF_ADDR_LIST": LOOPBACK,
        "EPICS_CA_SERVER_PORT": str(int(port)),
        "EPICS_CAS_SERVER_PORT": str(int(port)),
        "EPICS_CAS_AUTO_BEACON_ADDR_LIST": "NO",
        "EPICS_CAS_BEACON_ADDR_LIST": LOOPBACK,
        "EPICS_CAS_BEACON_PORT": str(int(port)),
    }


def client_environment(port: int) -> dict[str, str]:
    """EPICS variables that make a client search only 127.0.0.1 at ``port``."""
    return {
        "EPICS_CA_ADDR_LIST": f"{LOOPBACK}:{int(port)}",
        "EPICS_CA_AUTO_ADDR_LIST": "NO",
        "EPICS_CA_SERVER_PORT": str(int(port)),
    }


@contextlib.contextmanager
def patched_environ(values: Mapping[str, str]) -> Iterator[None]:
    """Set ``os.environ`` entries for the block and restore the previous values after it.

    caproto clients read ``EPICS_CA_ADDR_LIST`` & co. from ``os.environ`` whenever they search,
    so this is how a test points its clients at one IOC.
    """
    old = {k: os.environ.get(k) for k in values}
    os.environ.update({k: str(v) for k, v in values.items()})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def free_port(attempts: int = 50) -> int:
    """A port free for both TCP and UDP on 127.0.0.1 (chosen by the OS; bounded attempts)."""
    return free_ports(1, attempts)[0]
