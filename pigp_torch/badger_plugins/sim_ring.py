r"""Badger environment ``pigp_sim``: the simulated ring of ``pigp serve-sim`` over Channel Access.

Variables: the 13 skew windings (``<name>:CurrSetpt`` / ``:Curr1``), in amps, within ±30 A;
observable ``loss_rate`` (``SPEAR:BeamLossRate``, mA/min). Every setting goes through
:class:`pigp_torch.machine.epics.EpicsMachine` (bounds, readback check, fresh readings).

Knobs at the end of a routine. Badger 1.6 leaves the knobs at the routine's last point and has
no end-of-routine hook for environments, so the environment keeps the setpoints it finds at the
start of a routine and puts them back (``end_knobs="initial"``, the default) or sets the best
reading's knobs (``end_knobs="best"``: the highest loss rate read) when the routine ends, from
inside the routine's life:

* start: ``get_system_states()`` (called by ``badger.core.run_routine`` before anything is
  set), ``reset_environment()`` (called by Badger's GUI in the routine's own process), or else
  the first ``set_variables``;
* end, headless: :func:`pigp_torch.integrations.badger.run_routine` calls :meth:`end_routine`
  when Badger's loop returns or raises (stop, error, Ctrl-C);
* end, Badger's own loop (``badger.core.run_routine`` in a script, as Badger's examples run it
  headless, stopped through its active callback): Badger tells the environment nothing, so the
  routine ends at the first of: the next routine's start on this environment (its knobs are set
  back before the new start is recorded), the environment's garbage collection
  (``__del__``), or the end of the process — a hook run at interpreter exit *before* the
  thread pools shut down (``threading``'s exit hooks run last-registered first, so one
  registered after caproto's pool is created runs while its put callbacks still work), also
  after an uncaught exception;
* end, Badger GUI: the routine runs in a process of its own, which exits when the routine
  ends. There :meth:`end_routine` is registered as a ``multiprocessing`` finalizer (these run
  when the process function returns or raises, before Python shuts its threads down, so the
  Channel Access client still works), and SIGTERM — the GUI's Stop when the process does not
  stop within 0.1 s — raises Badger's own ``BadgerRunTerminated`` between evaluations (the
  routine then ends the same way), or lets the evaluation under way finish, sets the knobs and
  ends the process.

A restore from ``atexit`` would not work: by then the thread pool of caproto's client refuses
new work and the puts time out (hence the earlier ``threading`` exit hook).
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.util
import os
import signal
import threading
import weakref
from typing import Any, ClassVar, Literal

import torch
from badger import environment
from pydantic import Field, PrivateAttr

from pigp_torch._utils import DTYPE
from pigp_torch.integrations.badger import ENVIRONMENT, OBJECTIVE_PV, SIM_KNOBS, SIM_LIMIT_A

logger = logging.getLogger(__name__)

#: Attempts and seconds between them when the knobs are put back at the end of a routine.
RESTORE_ATTEMPTS = 3
RESTORE_INTERVAL_S = 0.5


class SimRingEnvironment(environment.Environment):
    r"""Badger environment of the simulated ring served by ``pigp serve-sim`` (see the module).

    Attributes:
        ca_port: Channel Access port of the IOC on 127.0.0.1 (default 0: keep the process's
            ``EPICS_CA_*`` settings).
        timeout: seconds for connections, reads, puts and readbacks (default 5).
        end_knobs: knobs when a routine ends or is aborted: ``"initial"`` (default: the
            setpoints found at its start) or ``"best"`` (the knobs of the highest loss rate read
            during the routine; the start's when none was read).
    """

    name: ClassVar[str] = ENVIRONMENT
    variables: ClassVar[dict[str, list[float]]] = {
        k: [-SIM_LIMIT_A, SIM_LIMIT_A] for k in SIM_KNOBS
    }
    observables: ClassVar[list[str]] = ["loss_rate"]

    ca_port: int = Field(0, ge=0, le=65535, description="CA port of the IOC on 127.0.0.1")
    timeout: float = Field(5.0, gt=0, description="seconds for CA connections, puts, readbacks")
    end_knobs: Literal["initial", "best"] = Field(
        "initial", description="knobs at the end of a routine: initial (restore) or best"
    )

    _epics: Any = PrivateAttr(None)
    _start: torch.Tensor | None = PrivateAttr(None)  # setpoints at the routine's start (A)
    _last: torch.Tensor | None = PrivateAttr(None)  # the last setting written (A)
    _best: tuple[float, torch.Tensor] | None = PrivateAttr(None)  # (loss rate, knobs)
    _ending: bool = PrivateAttr(False)
    _in_evaluation: bool = PrivateAttr(False)  # from set_variables to get_observables
    _sigterm: bool = PrivateAttr(False)  # SIGTERM during an evaluation: stop after it
    _exit_hooked: bool = PrivateAttr(False)  # the process-exit hook is registered

    # -- the machine ------------------------------------------------------------------------------
    def _machine(self):
        if self._epics is None:
            from pigp_torch.machine.epics import EpicsMachine

            if self.ca_port:
                os.environ["EPICS_CA_ADDR_LIST"] = f"127.0.0.1:{int(self.ca_port)}"
                os.environ["EPICS_CA_AUTO_ADDR_LIST"] = "NO"
            bounds = torch.tensor(
                [[-SIM_LIMIT_A] * len(SIM_KNOBS), [SIM_LIMIT_A] * len(SIM_KNOBS)], dtype=DTYPE
            )
            self._epics = EpicsMachine(
                list(SIM_KNOBS), bounds, objective_pv=OBJECTIVE_PV, timeout=self.timeout
            )
        return self._epics

    @property
    def knobs_at_start(self) -> dict[str, float] | None:
        """The setpoints found at the start of the current routine (A), ``None`` outside one."""
        if self._start is None:
            return None
        return dict(zip(SIM_KNOBS, self._start.tolist(), strict=True))

    # -- the routine's life -----------------------------------------------------------------------
    def begin_routine(self) -> dict[str, float]:
        """Record the knobs' setpoints now as the routine's start (A); returns them. A routine
        still open on this environment (Badger's own loop never says when one ends) is ended
        first: its knobs are set back, then the new start is read."""
        if self._start is not None and not self._ending:
            self.end_routine()
        self._start = self._machine().setpoints()
        self._last, self._best, self._ending = None, None, False
        self._end_at_exit()
        return self.knobs_at_start

    def _end_at_exit(self) -> None:
        """End the routine when the process ends (once per environment): a ``threading`` exit
        hook, run before the thread pools of caproto's client shut down. It holds the
        environment weakly; garbage collection ends the routine through ``__del__``."""
        if self._exit_hooked:
            return
        ref = weakref.ref(self)

        def at_exit() -> None:
            env = ref()
            if env is not None:
                env._end_in_process_exit()

        try:
            threading._register_atexit(at_exit)
        except RuntimeError:  # the interpreter is shutting down already
            return
        self._exit_hooked = True

    def __del__(self) -> None:
        """Garbage collection ends an open routine (knobs set back); never raises."""
        try:
            if getattr(self, "__pydantic_private__", None) and self._start is not None:
                self._end_in_process_exit()
        except Exception:  # the interpreter may be tearing modules down: nothing to tell
            pass

    def end_routine(self) -> dict[str, float] | None:
        """End the routine: set the knobs to ``end_knobs`` (checked, readbacks verified, up to
        :data:`RESTORE_ATTEMPTS` attempts). Idempotent; ``None`` when no routine is running.

        Returns:
            the knobs set (A).

        Raises:
            MachineError: the knobs could not be set back (the message gives the target).
        """
        if self._start is None or self._ending:
            return None
        self._ending = True  # from here a SIGTERM no longer interrupts (see _on_sigterm)
        from pigp_torch.loop.moves import restore_knobs
        from pigp_torch.machine.errors import MachineError

        m = self._machine()
        target = self._start
        if self.end_knobs == "best" and self._best is not None:
            target = self._best[1]
        err, made, errors = restore_knobs(
            m,
            target.clone(),
            m.bounds,
            None,
            attempts=RESTORE_ATTEMPTS,
            interval=RESTORE_INTERVAL_S,
            readback_tol=1e-6,
            on_set=None,
        )
        self._start = None
        knobs = dict(zip(SIM_KNOBS, target.tolist(), strict=True))
        if err is not None:
            raise MachineError(
                f"{ENVIRONMENT}: the knobs were NOT set back to {knobs} (A) after {made} "
                f"attempt(s): {errors[-1] if errors else err}"
            )
        logger.info("%s: knobs set to the %s setting %s (A)", ENVIRONMENT, self.end_knobs, knobs)
        return knobs

    def _end_in_process_exit(self) -> None:
        try:
            self.end_routine()
        except Exception as err:  # the GUI's process is ending: log, do not raise
            logger.error("%s", err)

    def _on_sigterm(self, signum, frame) -> None:
        """SIGTERM in a routine's own process: Badger's own stop between evaluations; during
        one, the setting or reading under way is finished first (Xopt's evaluator turns any
        exception, even ``SystemExit``, into a failed measurement), then
        :meth:`_stop_if_asked` ends the routine. Ignored once the routine is ending, so that the
        restore is never interrupted."""
        if self._start is None or self._ending:
            return
        if self._in_evaluation:
            self._sigterm = True
            return
        from badger.errors import BadgerRunTerminated

        raise BadgerRunTerminated(f"{ENVIRONMENT}: stopped by SIGTERM")

    def _stop_if_asked(self) -> None:
        """After an evaluation interrupted by SIGTERM: set the knobs (``end_knobs``), then end
        the process as SIGTERM asked (no exception can leave Xopt's evaluator cleanly)."""
        if self._sigterm:
            self._sigterm = False
            try:
                self.end_routine()
            except Exception as err:
                logger.error("%s", err)
            finally:
                self._exit_process(0)

    #: how :meth:`_stop_if_asked` ends the routine's process (replaced in tests)
    _exit_process: ClassVar = staticmethod(os._exit)

    def _end_with_this_process(self) -> None:
        """In a routine's own process (Badger's GUI): end the routine when the process ends."""
        multiprocessing.util.Finalize(None, self._end_in_process_exit, exitpriority=100)
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._on_sigterm)

    # -- Badger's hooks ---------------------------------------------------------------------------
    def get_system_states(self) -> dict[str, Any]:
        """Start of a headless routine (``badger.core.run_routine``): record the knobs."""
        return {"knobs_at_start_A": self.begin_routine()}

    def reset_environment(self) -> None:
        """Start of a routine in Badger's GUI (its own process): record the knobs and end the
        routine when that process ends."""
        self.begin_routine()
        if multiprocessing.parent_process() is not None:
            self._end_with_this_process()

    def get_variables(self, variable_names):
        values = dict(zip(SIM_KNOBS, self._machine().get().tolist(), strict=True))
        return {v: values[v] for v in variable_names}

    def set_variables(self, variable_inputs: dict[str, float]):
        self._stop_if_asked()
        m = self._machine()
        if self._start is None:
            self.begin_routine()
        self._in_evaluation = True
        try:
            now = dict(zip(SIM_KNOBS, m.setpoints().tolist(), strict=True))
            now.update({k: float(v) for k, v in variable_inputs.items()})
            x = torch.tensor([now[k] for k in SIM_KNOBS], dtype=DTYPE)
            m.set(x)
        except BaseException:
            self._in_evaluation = False
            raise
        self._last = x

    def get_observables(self, observable_names):
        self._in_evaluation = True
        try:
            y = float(self._machine().read())
        finally:
            self._in_evaluation = False
        if self._last is not None and (self._best is None or y > self._best[0]):
            self._best = (y, self._last.clone())
        self._stop_if_asked()
        return {k: y for k in observable_names if k == "loss_rate"}
