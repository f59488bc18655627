"""Badger environment: the simulated SPEAR3 ring served by ``pigp serve-sim``, over Channel Access.

Variables: the 13 skew windings (``<name>:CurrSetpt`` / ``:Curr1``), in amps, within ±30 A;
observable ``loss_rate`` (``SPEAR:BeamLossRate``, mA/min). Every setting goes through
:class:`pigp_torch.machine.epics.EpicsMachine` (bounds, readback check, fresh readings). The IOC
is found at ``127.0.0.1:<ca_port>`` (parameter ``ca_port``; 0 keeps the process's EPICS_CA_*
settings).
"""

from __future__ import annotations

import os
from typing import ClassVar

from badger import environment

from pigp_torch.integrations.badger import OBJECTIVE_PV, SIM_KNOBS, SIM_LIMIT_A


class Environment(environment.Environment):
    name = "pigp_sim"
    variables: ClassVar[dict[str, list[float]]] = {
        k: [-SIM_LIMIT_A, SIM_LIMIT_A] for k in SIM_KNOBS
    }
    observables: ClassVar[list[str]] = ["loss_rate"]

    ca_port: int = 0
    timeout: float = 5.0

    def _machine(self):
        m = getattr(self, "_epics", None)
        if m is None:
            import torch

            from pigp_torch.machine.epics import EpicsMachine

            if self.ca_port:
                os.environ["EPICS_CA_ADDR_LIST"] = f"127.0.0.1:{int(self.ca_port)}"
                os.environ["EPICS_CA_AUTO_ADDR_LIST"] = "NO"
            bounds = torch.tensor([[-SIM_LIMIT_A] * len(SIM_KNOBS), [SIM_LIMIT_A] * len(SIM_KNOBS)])
            m = EpicsMachine(
                list(SIM_KNOBS), bounds.double(), objective_pv=OBJECTIVE_PV, timeout=self.timeout
            )
            object.__setattr__(self, "_epics", m)
        return m

    def get_variables(self, variable_names):
        values = dict(zip(SIM_KNOBS, self._machine().get().tolist(), strict=True))
        return {v: values[v] for v in variable_names}

    def set_variables(self, variable_inputs: dict[str, float]):
        m = self._machine()
        now = dict(zip(SIM_KNOBS, m.get().tolist(), strict=True))
        now.update({k: float(v) for k, v in variable_inputs.items()})
        import torch

        m.set(torch.tensor([now[k] for k in SIM_KNOBS], dtype=torch.float64))

    def get_observables(self, observable_names):
        y = float(self._machine().read())
        return {k: y for k in observable_names if k == "loss_rate"}
