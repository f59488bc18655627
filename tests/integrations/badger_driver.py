"""Driver of the Badger tests, run in a subprocess with a fresh HOME (Badger keeps its settings
in process-wide singletons): ``python badger_driver.py CASE ...`` prints one JSON line.

Cases (each against its own simulated IOC on 127.0.0.1, knobs first set to ``START_A``):

* ``headless``: :func:`pigp_torch.integrations.badger.run_routine` (Badger's ``core.run_routine``)
  to the end, with ``end_knobs`` initial and best, then a Ctrl-C (``KeyboardInterrupt`` from a
  callback) in the middle of a routine;
* ``core``: a script of its own (a child process) runs a routine with Badger's own
  ``badger.core.run_routine`` and stops it through the active callback after 4 evaluations,
  then: catches Badger's ``BadgerRunTerminated`` and exits; lets it end the process (uncaught);
  or drops the routine and collects the garbage, reading the setpoints before ``os._exit``
  (no exit hook runs);
* ``gui``: Badger's GUI runner without the GUI: ``badger.core_subprocess.run_routine_subprocess``
  in a ``multiprocessing.Process`` fed as ``BadgerRoutineSubprocess`` feeds it, ended by its
  termination condition, then stopped as the GUI's Stop button does (stop event, 0.1 s, SIGTERM).
"""

from __future__ import annotations

import json
import math
import sys
import time

import pandas as pd
import torch
from badger.settings import init_settings

import pigp_torch.integrations.badger as pb
from pigp_torch.prior import PhysicsPrior

#: Knobs at the start of every routine (A): not zero, not round, so a restore is visible.
START_A = [round(1.5 * math.sin(3.0 * k + 1.0) + 0.1 * k, 6) for k in range(len(pb.SIM_KNOBS))]

#: The start of the keep-the-best routine: far from the ring's peak, so that the routine finds
#: higher loss rates than the start's.
BEST_START_A = [round(x - 20.0, 6) for x in START_A]


def _prior() -> PhysicsPrior:
    d = len(pb.SIM_KNOBS)
    return PhysicsPrior(
        x0=torch.zeros(d, dtype=torch.float64),
        f_x0=1.5,
        f_inf=0.2,
        precision=2e-3 * torch.eye(d, dtype=torch.float64),
        amplitude=0.1,
        noise=0.04,
        knob_names=list(pb.SIM_KNOBS),
        bounds=torch.tensor([[-30.0] * d, [30.0] * d], dtype=torch.float64),
    )


def _routine(port: int, end_knobs: str = "initial", start=START_A):
    from badger.routine import Routine
    from gest_api.vocs import VOCS

    from pigp_torch.integrations.xopt_physics import PhysicsGenerator

    vocs = VOCS(
        variables={k: [-30.0, 30.0] for k in pb.SIM_KNOBS}, objectives={"loss_rate": "MAXIMIZE"}
    )
    gen = PhysicsGenerator(vocs=vocs, prior=_prior(), max_travel_distances=0.1, n_starts=2)
    return Routine(
        name="pigp-physics on the simulated ring",
        generator=gen,
        environment={"name": "pigp_sim", "ca_port": port, "end_knobs": end_knobs},
        initial_points=pd.DataFrame([dict(zip(pb.SIM_KNOBS, start, strict=True))]),
    )


class Probe:
    """A Channel Access client of its own (not the environment's)."""

    def __init__(self, timeout: float = 5.0) -> None:
        from caproto.threading.client import Context

        self.context, self.timeout, self._pvs = Context(timeout=timeout), timeout, {}

    def pv(self, name):
        if name not in self._pvs:
            (pv,) = self.context.get_pvs(name, timeout=self.timeout)
            pv.wait_for_connection(timeout=self.timeout)
            self._pvs[name] = pv
        return self._pvs[name]

    def read_many(self, names) -> torch.Tensor:
        return torch.tensor(
            [float(self.pv(n).read(timeout=self.timeout).data[0]) for n in names],
            dtype=torch.float64,
        )

    def write_many(self, names, values) -> None:
        for name, value in zip(names, values, strict=True):
            self.pv(name).write([float(value)], wait=True, timeout=self.timeout)


def _setpoints(probe, ioc) -> list[float]:
    return probe.read_many(ioc.setpoint_pvs).tolist()


def _moved(data: pd.DataFrame, start=START_A) -> float:
    x = torch.tensor(data[list(pb.SIM_KNOBS)].to_numpy(dtype=float))
    return float((x - torch.tensor(start)).abs().max())


def headless(port_ioc, probe) -> dict:
    out = {}
    for end_knobs, start in (("initial", START_A), ("best", BEST_START_A)):
        probe.write_many(port_ioc.setpoint_pvs, start)
        routine = _routine(port_ioc.port, end_knobs, start)
        data = pb.run_routine(routine, max_evaluations=6)
        best = data.loc[data["loss_rate"].idxmax(), list(pb.SIM_KNOBS)].astype(float).tolist()
        out[end_knobs] = {
            "n": len(data),
            "start": start,
            "moved": _moved(data, start),
            "end": _setpoints(probe, port_ioc),
            "best": best,
        }
    # Ctrl-C in the middle of a routine (the callback runs after each evaluation)
    probe.write_many(port_ioc.setpoint_pvs, START_A)
    routine = _routine(port_ioc.port)
    calls = []

    def interrupt(result):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt

    try:
        pb.run_routine(routine, max_evaluations=50, evaluate_callback=interrupt)
        raised = None
    except KeyboardInterrupt:
        raised = "KeyboardInterrupt"
    out["interrupt"] = {
        "raised": raised,
        "n": len(routine.data),
        "moved": _moved(routine.data),
        "end": _setpoints(probe, port_ioc),
    }
    return out


def _gui_run(port: int, probe, ioc, *, stop_after: int | None, max_eval: int | None) -> dict:
    """One routine the way Badger's GUI runs it (see the module docstring)."""
    import multiprocessing as mp

    from badger.archive import BADGER_ARCHIVE_ROOT
    from badger.core_subprocess import run_routine_subprocess

    probe.write_many(ioc.setpoint_pvs, START_A)
    routine = _routine(port)
    fname = f".tmp-pigp-{time.time_ns()}.yaml"
    folder = f"{BADGER_ARCHIVE_ROOT}/.tmp"
    import os

    os.makedirs(folder, exist_ok=True)
    routine.dump(f"{folder}/{fname}")
    queue, pipe, dialog = mp.Queue(), mp.Pipe(), mp.Queue()
    stop, pause, wait = mp.Event(), mp.Event(), mp.Event()
    config_path = init_settings()._instance.config_path
    process = mp.Process(
        target=run_routine_subprocess,
        args=(queue, pipe, stop, pause, wait, config_path, None, dialog),
    )
    process.start()
    queue.put(
        {
            "routine_id": routine.id,
            "routine_filename": fname,
            "routine_name": routine.name,
            "variable_ranges": routine.vocs.variables,
            "initial_points": routine.initial_points,
            "evaluate": True,
            "archive": False,
            "termination_condition": None
            if max_eval is None
            else {"tc_idx": 0, "max_eval": max_eval},
            "start_time": time.time(),
            "testing": True,
            "run_data": False,
            "init_points": True,
        }
    )
    wait.set()
    pause.set()
    n, data, stopped_by = 0, None, None
    deadline = time.monotonic() + 120.0
    while process.is_alive() and time.monotonic() < deadline:
        if pipe[1].poll(0.05):
            try:
                data, _ = pipe[1].recv()
            except EOFError:
                break
            n = len(data)
        if stop_after is not None and n >= stop_after:
            stop.set()  # BadgerRoutineSubprocess.stop_routine, as the GUI's Stop button
            process.join(timeout=0.1)
            stopped_by = "stop event"
            if process.is_alive():
                process.terminate()
                stopped_by = "SIGTERM"
            break
    process.join(timeout=60.0)
    return {
        "n": n,
        "moved": _moved(data) if data is not None else 0.0,
        "stopped_by": stopped_by,
        "exitcode": process.exitcode,
        "end": _setpoints(probe, ioc),
    }


def gui(ioc, probe) -> dict:
    return {
        "finished": _gui_run(ioc.port, probe, ioc, stop_after=None, max_eval=4),
        "stopped": _gui_run(ioc.port, probe, ioc, stop_after=3, max_eval=None),
    }


CORE_SCRIPT = """
import gc, json, os, sys
sys.path.insert(0, sys.argv[1])
import badger_driver as d
from badger.core import run_routine
from badger.errors import BadgerRunTerminated

how, port = sys.argv[2], int(sys.argv[3])
routine = d._routine(port)
stop = lambda: 2 if routine.data is not None and len(routine.data) >= 4 else 0
if how == "uncaught":
    run_routine(routine, stop, lambda c: None, None, None, verbose=0)
try:
    run_routine(routine, stop, lambda c: None, None, None, verbose=0)
except BadgerRunTerminated:
    pass
out = {"n": len(routine.data), "moved": d._moved(routine.data)}
if how == "gc":
    del routine, stop
    gc.collect()
    probe = d.Probe()
    out["inside"] = probe.read_many([k + ":CurrSetpt" for k in d.pb.SIM_KNOBS]).tolist()
    print(json.dumps(out), flush=True)
    os._exit(0)
print(json.dumps(out), flush=True)
"""


def core(ioc, probe) -> dict:
    """Each way a script of Badger's own loop ends (see the module docstring)."""
    import os
    import subprocess
    from pathlib import Path

    out = {}
    for how in ("caught", "uncaught", "gc"):
        probe.write_many(ioc.setpoint_pvs, START_A)
        proc = subprocess.run(
            [sys.executable, "-c", CORE_SCRIPT, str(Path(__file__).parent), how, str(ioc.port)],
            capture_output=True, text=True, timeout=240, env={**os.environ, **ioc.client_env},
        )  # fmt: skip
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
        out[how] = {
            "returncode": proc.returncode,
            "end": _setpoints(probe, ioc),
            **(json.loads(lines[-1]) if lines else {"stderr": proc.stderr[-2000:]}),
        }
    return out


def main() -> None:
    from pigp_torch.simulated_epics.ioc import start_sim_ioc

    pb.setup(startup_hook=False)  # Badger's folders in the fresh HOME, pigp_sim in its plugins
    case = sys.argv[1]
    with start_sim_ioc(1, update_period=0.05) as ioc:
        probe = Probe()
        run = {"headless": headless, "gui": gui, "core": core}[case]
        result = {"start": START_A, **run(ioc, probe)}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
