r"""One run of :func:`pigp_torch.loop.optimize`: its checked start (:func:`start_run`), its run log
(:func:`open_log`), its steps (:func:`run_all_steps`) and what its moves and reads share
(:class:`Run`: the intent records, the acknowledged setpoints, the evaluation of one setting).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import torch

from pigp_torch._utils import DTYPE, as_knob_tensor, check_bounds
from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.data.runlog import RunLog, RunRecords, evaluation_rows, replay
from pigp_torch.loop.moves import (
    averaged_parts,
    checked_read,
    effective_max_step,
    move,
    read,
    restore_knobs,
    setpoints_of,
)
from pigp_torch.loop.noise import logged_noise, measure_noise
from pigp_torch.loop.options import RunOptions
from pigp_torch.loop.readings import ReadingJudge
from pigp_torch.loop.steps import (
    StepContext,
    knob_columns,
    logged_initial_knobs,
    observables_of,
    run_steps,
)
from pigp_torch.machine.base import check_setting, is_machine_objective
from pigp_torch.optimizers.base import AskTellOptimizer


@dataclasses.dataclass(eq=False)
class Run:
    r"""The state of one run that its steps and its end share.

    ``x_found`` / ``rb_found`` (``d``, knob units) are the setpoints and readbacks found at the
    start (``None`` for a plain callable); ``x_initial`` is the restore target (``x_found``, or on a
    resume the logged run's initial knobs); ``bounds`` (``2 x d``), ``limit`` (the step limit) and
    ``read_tol`` (``d``, knob units) are set for a machine only. ``sent`` records the last
    setting written (``last``), the last acknowledged (``acked``) and the step and purpose of the
    current move (for the intent records).
    """

    objective: object
    opts: RunOptions
    budget: int
    is_machine: bool
    logged: list[dict]
    x0: torch.Tensor | None
    x_found: torch.Tensor | None
    rb_found: torch.Tensor | None
    x_initial: torch.Tensor | None
    names: list[str]
    label: str
    maximize: bool
    bounds: torch.Tensor | None = None
    limit: object = None
    read_tol: torch.Tensor | None = None
    objective_range: object = None
    judge: ReadingJudge | None = None
    log: RunLog | None = None
    own_log: bool = False
    noise_info: dict | None = None
    sent: dict = dataclasses.field(
        default_factory=lambda: {"last": None, "acked": None, "step": None, "purpose": "evaluation"}
    )

    def on_set(self, x: torch.Tensor, k: int, n: int) -> None:
        """Before part ``k`` of ``n`` of a move is written: its intent record, then remember it."""
        sent = self.sent
        if self.log is not None:
            known = self.log.write_error  # a failed write already reported
            try:
                self.log.log_intent(x, purpose=sent["purpose"], step=sent["step"], part=k, parts=n)
            except Exception as err:
                if not sent["purpose"].startswith("restore"):
                    raise  # no move of a run without its intent on disk
                # a restore goes on even when the log cannot be written (disk full)
                if known is None:
                    warnings.warn(f"could not log the restore's intent: {err!r}", stacklevel=2)
        sent["last"] = x.tolist()

    def on_ack(self, x: torch.Tensor) -> None:
        self.sent["acked"] = x.tolist()

    def last_acknowledged(self):
        """The setpoints the machine last confirmed (its own account where it keeps one)."""
        acked = self.objective.last_acknowledged if self.is_machine else None
        return acked.tolist() if isinstance(acked, torch.Tensor) else self.sent["acked"]

    def on_discard_at(self, step):
        """The callback that logs a reading discarded at ``step``."""

        def on_discard(reason: str, y: float) -> None:
            if self.log is not None:
                self.log.write("discarded", step=step, y=y, reason=reason, time=_utc_now())

        return on_discard

    def evaluate(self, x: torch.Tensor, step: int) -> tuple[float, int]:
        """Move to ``x`` (a machine: by the checked ramp) and read the objective."""
        opts, objective = self.opts, self.objective
        if self.is_machine:
            self.sent["step"], self.sent["purpose"] = step, "evaluation"
            move(objective, x, self.bounds, self.limit, on_set=self.on_set, on_ack=self.on_ack)
            on_discard = self.on_discard_at(step)
            if not opts.check_readings:
                return read(
                    objective.read, opts.read_retries, opts.retry_interval, self.judge,
                    on_discard, lambda: averaged_parts(objective),
                )  # fmt: skip
            return checked_read(
                objective, x, self.read_tol, opts.read_retries, opts.retry_interval, on_discard,
                self.judge,
            )  # fmt: skip
        return read(
            lambda: objective(x), opts.read_retries, opts.retry_interval, self.judge,
            self.on_discard_at(step),
        )  # fmt: skip

    def restore_to(self, goal, purpose: str, ref):
        """Set the knobs to ``goal`` with the run's restore rules: ``(error, attempts, errors)``."""
        self.sent["purpose"], self.sent["step"] = purpose, None
        opts = self.opts
        return restore_knobs(
            self.objective,
            goal,
            self.bounds,
            self.limit,
            attempts=opts.restore_attempts,
            interval=opts.restore_interval,
            window=opts.restore_timeout,
            readback_tol=opts.readback_tol,
            on_set=self.on_set,
            on_ack=self.on_ack,
            reference=ref,
        )

    def fresh(self, x, step, what):
        """A reader of checked readings at ``x`` (knobs already there) for the end of the run;
        its discarded readings are logged at ``step`` as ``what: reason``."""

        def discard(reason: str, y: float) -> None:
            self.on_discard_at(step)(f"{what}: {reason}", y)

        opts = self.opts
        return lambda: checked_read(
            self.objective, x, self.read_tol, opts.read_retries, opts.retry_interval, discard,
            ReadingJudge(None, self.objective_range),
        )[0]  # fmt: skip


def _logged_evaluations(resume, x0, budget: int) -> list[dict]:
    """The evaluation records of the run to continue (``[]`` without ``resume``), checked."""
    if resume is None:
        return []
    if x0 is not None:
        raise ValueError("x0 must be None when resuming: the start point is in the log")
    logged = list(resume.evaluations if isinstance(resume, RunRecords) else resume)
    if not logged:
        raise ValueError("nothing to resume: the log holds no evaluation")
    if len(logged) >= budget:
        raise ValueError(
            f"the log already holds {len(logged)} evaluations and the budget is {budget}: "
            "raise the budget to continue the run"
        )
    return logged


def _start_point(optimizer, x0, resume, logged, x_initial, is_machine: bool):
    """``(x0, d)``: the checked start point (``None`` on a resume) and the number of knobs."""
    if resume is not None:
        return x0, optimizer.dim
    if x0 is None:
        if not is_machine:
            raise ValueError("x0 is required when the objective is a plain callable")
        x0 = x_initial
    if not isinstance(x0, torch.Tensor):  # lists/arrays straight to float64, not via float32
        x0 = torch.as_tensor(x0, dtype=DTYPE)
    d = optimizer.dim
    return as_knob_tensor(x0.reshape(-1), d, name="x0")[0][0], d


def _machine_limits(run: Run, d: int) -> None:
    """A machine's bounds, step limit and readback tolerance; the logged initial knobs checked."""
    objective, opts = run.objective, run.opts
    run.bounds = bounds = check_bounds(objective.bounds)
    if bounds.shape[1] != d:
        raise ValueError(f"the machine has {bounds.shape[1]} knobs, the optimizer {d}")
    run.limit = effective_max_step(objective, bounds, opts.max_step)
    if run.x_initial is not run.x_found:
        try:
            check_setting(run.x_initial, bounds)
        except ValueError as err:
            raise ValueError(f"the logged initial knobs are not allowed: {err}") from err
    machine_tol = objective.tolerance
    if machine_tol is not None:
        run.read_tol = torch.as_tensor(machine_tol, dtype=DTYPE).expand(d).clone()
    else:
        run.read_tol = opts.readback_tol * (bounds[1] - bounds[0])


def start_run(objective, optimizer, x0, budget: int, *, knob_names, method, resume, opts) -> Run:
    """Check the arguments and read the machine's start state (setpoints, then readbacks)."""
    if not isinstance(optimizer, AskTellOptimizer):
        raise ValueError(
            f"the optimizer ({type(optimizer).__name__}) must be an AskTellOptimizer: the loop "
            "reads its name, dim, maximize, notices and uses_observables"
        )
    is_machine = is_machine_objective(objective)
    logged = _logged_evaluations(resume, x0, budget)
    # the restore target: the SETPOINTS found at the start (never readbacks); the readbacks
    # found are the reference of a knob that already read off its setpoint
    x_found = setpoints_of(objective) if is_machine else None
    rb_found = (
        torch.as_tensor(objective.get(), dtype=DTYPE).reshape(-1).clone() if is_machine else None
    )
    x_initial = x_found
    logged_initial = logged_initial_knobs(resume)
    if is_machine and logged_initial is not None:
        if logged_initial.shape != x_found.shape:
            raise ValueError(
                f"the log's initial knobs have {logged_initial.numel()} values, the machine "
                f"{x_found.numel()}"
            )
        x_initial = logged_initial
    x0, d = _start_point(optimizer, x0, resume, logged, x_initial, is_machine)
    if knob_names is None and is_machine:
        knob_names = objective.knob_names
    names = knob_columns(knob_names, d)
    label = method if method is not None else optimizer.name
    if isinstance(resume, RunRecords) and resume.knob_names and resume.knob_names != names:
        raise ValueError(f"the resumed log has knobs {resume.knob_names}, the run has {names}")
    run = Run(objective, opts, budget, is_machine, logged, x0, x_found, rb_found, x_initial,
              names, label, bool(optimizer.maximize))  # fmt: skip
    if is_machine:
        _machine_limits(run, d)
    if optimizer.uses_observables and not (is_machine and objective.observable_names):
        raise ValueError(f"{label} fits the observables of each reading; this machine reports none")
    run.objective_range = opts.objective_range
    if run.objective_range is None and is_machine:
        run.objective_range = objective.objective_limits
    run.judge = ReadingJudge(opts.noise, run.objective_range, readings=[r["y"] for r in logged])
    _noise_in_force(run, resume)
    return run


def _noise_in_force(run: Run, resume) -> None:
    """The noise of the run's start record: stated, logged by the run resumed (then used), or
    to be measured at the start (:mod:`~pigp_torch.loop.noise`); ``None``: none."""
    opts = run.opts
    if opts.noise is not None:
        run.noise_info = {"sigma": float(opts.noise), "source": "stated"}
        return
    run.noise_info = logged_noise(resume) if isinstance(resume, RunRecords) else None
    if run.noise_info is not None:
        run.judge.noise = run.noise_info["sigma"]
    elif run.is_machine and opts.noise_reads > 0:
        run.noise_info = {"source": "to measure", "n": opts.noise_reads}


def open_log(run: Run, log: RunLog | str | Path | None, resume) -> None:
    """The run's log: a given :class:`RunLog`, or a path created (continued on a resume)."""
    own_log = log is not None and not isinstance(log, RunLog)
    if own_log:
        if resume is not None:
            log = RunLog.append(log)
        else:
            header = {"knob_names": run.names, "method": run.label, "budget": run.budget}
            if run.bounds is not None:
                header["bounds"] = run.bounds.tolist()
            if run.is_machine:  # what a reading also measures
                m = run.objective
                for key, value in (("observable_names", m.observable_names),
                                   ("observable_units", m.observable_units)):  # fmt: skip
                    if value is not None:
                        header[key] = [str(v) for v in value]
            log = RunLog.create(log, header)
    run.log, run.own_log = log, own_log
    if log is not None and log.header.get("knob_names") not in (None, run.names):
        if own_log:
            log.close()
        raise ValueError(
            f"the run log has knobs {log.header['knob_names']}, the run has {run.names}"
        )


def run_all_steps(
    run: Run, optimizer, rows: list[dict], *, progress, callback, guard, stop=None, record=None
) -> None:
    """Replay the logged evaluations (a resume), then ask -> evaluate -> tell up to the budget
    (or until ``stop()``); every row is appended to ``rows`` as it is made (``stop``,
    ``record``: see :class:`~pigp_torch.loop.steps.StepContext`)."""
    if run.logged:
        replay(optimizer, run.logged, progress=progress)
        rows.extend(evaluation_rows(run.logged, run.names, run.label))
    noise = run.noise_info
    if noise is not None and noise["source"] == "to measure":  # before anything moves
        run.noise_info = noise = measure_noise(run, noise["n"])
    objective = run.objective
    ctx = StepContext(
        run.evaluate,
        run.names,
        run.label,
        log=run.log,
        x_initial=run.x_initial,
        x_found=run.x_found,
        rb_found=run.rb_found,
        reading_info=(lambda: objective.last_reading) if run.is_machine else (lambda: None),
        observables=(lambda: observables_of(objective)) if run.is_machine else (lambda: None),
        objective_floor=run.opts.objective_floor,
        callback=callback,
        progress=progress,
        start_fields={} if noise is None else {"noise": noise},
        stop=stop,
        record=record,
    )
    run_steps(ctx, optimizer, run.x0, rows, first=len(run.logged), budget=run.budget, guard=guard)
