"""The simulated ring over pvAccess (p4p, in this process, 127.0.0.1), shared by tests/pva.

Skipped as a whole when p4p (the ``pva`` extra) is not installed.
"""

import pytest
import torch

try:
    import p4p  # noqa: F401
except ImportError:  # the `pva` extra is not installed: nothing here is collected
    collect_ignore_glob = ["test_*.py"]

KNOBS = ["01G-QSS4", "02G-QSS3"]
UPDATE_PERIOD = 0.05
FAST = {"settle_time": 0.1, "timeout": 0.5, "retry_interval": 0.0}


@pytest.fixture(scope="package")
def pva_ring():
    """(server, client configuration) of ring seed 1 with two knobs, refreshed every 50 ms."""
    from pigp_torch.simulated_epics.pva import start_sim_pva

    with start_sim_pva(1, knobs=KNOBS, update_period=UPDATE_PERIOD) as served:
        yield served


@pytest.fixture(scope="package")
def pva_client(pva_ring):
    from p4p.client.thread import Context

    _, conf = pva_ring
    ctx = Context("pva", conf=conf, useenv=False)
    yield ctx
    ctx.close()


@pytest.fixture
def ring(pva_ring, pva_client):
    """The served ring with knobs at zero and the switches off (before and after)."""
    server, conf = pva_ring

    def reset():
        pva_client.put(server.pv("Sim:ReadbackDelay"), 0.0, timeout=2.0)
        pva_client.put(server.pv("Sim:Frozen"), 0.0, timeout=2.0)
        names = [f"{n}:CurrSetpt" for n in KNOBS]
        pva_client.put(names, [0.0] * len(names), timeout=2.0)

    reset()
    yield server, conf
    reset()


def setpoints(client, names=KNOBS) -> torch.Tensor:
    return torch.tensor(
        [float(v) for v in client.get([f"{n}:CurrSetpt" for n in names], timeout=2.0)],
        dtype=torch.float64,
    )
