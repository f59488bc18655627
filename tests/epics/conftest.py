"""One simulated IOC shared by the EPICS tests, and a separate CA client that watches it.

Everything runs over real Channel Access on 127.0.0.1, on a free port chosen per IOC. The
shared fixtures are package-scoped: the IOC stops when the last test of tests/epics is done.
"""

import importlib.util
import time

import pytest
import torch

if importlib.util.find_spec("caproto") is None:  # the `epics` extra is not installed
    collect_ignore_glob = ["test_*.py"]

IOC_SEED = 1  # error seed of the simulated ring served by the shared IOC
UPDATE_PERIOD = 0.05  # s between loss-rate refreshes of the test IOCs
NOISE = 0.04  # mA/min, the IOC's loss-rate noise
#: Fast EpicsMachine options for tests (seconds).
FAST = {"settle_time": 2 * UPDATE_PERIOD, "timeout": 0.5, "retry_interval": 0.0}


class Probe:
    """A caproto client of its own (not the machine's): reads and writes PVs directly."""

    def __init__(self, broadcaster=None, timeout: float = 2.0) -> None:
        from caproto.threading.client import Context

        self.context = Context(broadcaster, timeout=timeout)
        self.timeout = timeout
        self._pvs = {}

    def pv(self, name):
        if name not in self._pvs:
            (pv,) = self.context.get_pvs(name, timeout=self.timeout)
            pv.wait_for_connection(timeout=self.timeout)
            self._pvs[name] = pv
        return self._pvs[name]

    def read(self, name) -> float:
        return float(self.pv(name).read(timeout=self.timeout).data[0])

    def read_many(self, names) -> torch.Tensor:
        return torch.tensor([self.read(n) for n in names], dtype=torch.float64)

    def write(self, name, value, timeout=None) -> None:
        self.pv(name).write([value], wait=True, timeout=timeout or self.timeout)

    def write_many(self, names, values) -> None:
        for name, value in zip(names, torch.as_tensor(values).tolist(), strict=True):
            self.write(name, value)

    def wait_for(self, names, values, timeout: float) -> torch.Tensor:
        """Poll ``names`` until they equal ``values`` or ``timeout`` s pass; return the last."""
        values = torch.as_tensor(values, dtype=torch.float64)
        deadline = time.monotonic() + timeout
        while True:
            now = self.read_many(names)
            if torch.equal(now, values) or time.monotonic() > deadline:
                return now
            time.sleep(0.02)

    def close(self) -> None:
        self.context.disconnect(wait=False)  # its daemon threads end on their own


@pytest.fixture(scope="package")
def sim_ioc():
    """The shared IOC (ring seed 1, noise 0.04 mA/min, refresh every 50 ms)."""
    from pigp_torch.simulated_epics.ioc import start_sim_ioc

    with start_sim_ioc(IOC_SEED, update_period=UPDATE_PERIOD) as handle:
        yield handle


@pytest.fixture(scope="package")
def broadcaster(sim_ioc):
    """One UDP search client shared by the session's contexts (each one costs a teardown)."""
    from caproto.threading.client import SharedBroadcaster

    shared = SharedBroadcaster()
    yield shared
    shared.disconnect(wait=False)


@pytest.fixture(scope="package")
def probe(broadcaster):
    client = Probe(broadcaster)
    yield client
    client.close()


@pytest.fixture(scope="package")
def ca_context(broadcaster):
    """A caproto Context shared by the tests' machines (closing a machine leaves it open)."""
    from caproto.threading.client import Context

    context = Context(broadcaster)
    yield context
    context.disconnect(wait=False)


def reset(handle, client) -> None:
    client.write(handle.readback_delay_pv, 0.0)
    client.write(handle.nan_readings_pv, 0)
    client.write(handle.frozen_pv, 0)
    client.write(handle.reboot_on_read_pv, 0)
    client.write(handle.glitch_readings_pv, 0)
    client.write(handle.glitch_value_pv, 1e30)
    client.write(handle.stuck_knob_pv, 0)
    client.write(handle.readback_offset_pv, 0.0)
    client.write(handle.stall_puts_pv, 0.0)
    client.write(handle.narrow_knob_pv, 0)
    client.write(handle.narrow_limit_pv, 0.0)
    client.write_many(handle.setpoint_pvs, torch.zeros(len(handle.knob_names)))


@pytest.fixture
def ioc(sim_ioc, probe):
    """The shared IOC with the knobs at zero and the fault switches off (before and after)."""
    reset(sim_ioc, probe)
    yield sim_ioc
    if sim_ioc.alive():
        reset(sim_ioc, probe)


@pytest.fixture(scope="package")
def ring():
    """The simulator the shared IOC serves (for true values)."""
    from pigp_torch.simulation import Spear3Coupling

    return Spear3Coupling(IOC_SEED)


#: Run-file keys of each run mode for the fault tests: a track run (ended by its count, its
#: time limit far away) with its default end, restore: estimate; after a failure both modes set
#: the initial knobs back, which is what the parametrized tests assert at the IOC.
RUN_MODES = {"optimize": {}, "track": {"mode": "track", "time_limit": "10 min"}}


@pytest.fixture(params=list(RUN_MODES))
def run_mode(request) -> dict:
    """The run-file keys of a one-shot run and of a track run (the test runs in both)."""
    return dict(RUN_MODES[request.param])
