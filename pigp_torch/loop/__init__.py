r"""The optimization loop: measure the start point, then ask -> evaluate -> tell until the budget.

:func:`optimize` (:mod:`~pigp_torch.loop.core`) with its safety options
(:class:`~pigp_torch.loop.options.RunOptions`); the machine boundary is
:mod:`~pigp_torch.loop.moves`, the signals and exceptions :mod:`~pigp_torch.loop.signals`.

The loop is the only place that talks to both an optimizer and a machine; it records every
evaluation in a tidy table (and, optionally, in a :class:`~pigp_torch.data.runlog.RunLog` on disk)
and, on a :class:`~pigp_torch.machine.base.Machine`, enforces the safety rules below.

**Safety rules on a machine** (any :class:`~pigp_torch.machine.base.Machine`, not only EPICS):

1. *Bounds and step limit at the machine boundary.* Every setting the loop sends passes
   :func:`~pigp_torch.machine.base.check_setting` against the machine's ``bounds`` and the step
   limit :math:`m` (the elementwise minimum of the machine's ``max_step`` and the loop's
   ``max_step``), measured from the previous setting sent, *before* ``machine.set`` is called —
   on top of whatever the machine itself checks and of the optimizer's own rules (BayesOpt's trust
   box). A setting that breaks a rule is refused with ``ValueError`` and the run ends as below.
2. *How a proposal is reached.* Everything happens in *setpoint space*: a move
   starts from the machine's setpoints (``setpoints()``, read from the control system; else its
   ``last_acknowledged`` setting; only a machine with neither, from ``get()``), never from its
   readbacks, which are only checked against the setpoints (a readback offset or a stuck
   readback cannot widen a step or move the restore target). The start point, the first point
   after a resume and every restore are always reached by a ramp: the move :math:`\Delta` is
   cut into
   :math:`n = \lceil \max_i |\Delta_i| / (0.99\, m_i) \rceil` equal steps on the segment (all
   inside the convex box; the 1 % margin leaves room for a machine that measures the step from
   readbacks sitting within their tolerance of the setpoints). Every proposal is reached the
   same way (a move within :math:`0.99\, m`, or with no step limit, is one ``set``) and the
   objective is read once, after the last step; the optimizer's algorithm is untouched, so
   Nelder–Mead and RCDS, which have no step limit of their own, respect the machine's limit, and
   BayesOpt keeps its trust box (which bounds the distance from the best point, not from the
   last one).
3. *Invalid readings.* A reading that is NaN or infinite, or a read that raises
   :class:`~pigp_torch.machine.errors.ReadError` or ``TimeoutError``, is retried up to
   ``read_retries`` times, ``retry_interval`` seconds apart; then the run aborts with
   ``ReadError``. (Give a machine that retries on its own, like ``EpicsMachine``, zero retries
   of its own, or the two counts multiply.)
   *Plausible readings* (:mod:`~pigp_torch.loop.readings`): a reading outside the physical
   range ``objective_range`` (default: the machine's ``objective_limits``, for EPICS the
   objective PV's DRVL/DRVH, else LOPR/HOPR) is discarded (a ``discarded`` record) and read
   again; so is an averaged reading one of whose single readings is (the machine's
   ``last_reading["values"]``: an average would dilute a glitch into the range). With the
   reading noise :math:`\sigma` stated (``noise``), a reading more than :math:`5 s` from the
   median of the run's accepted readings,
   :math:`s = \max(\sigma, 1.4826\,\mathrm{MAD})` (from the 5th reading; :math:`s = \sigma`
   before), is read again at the same setting and kept only if the re-read agrees within
   :math:`4\sqrt2\,\sigma` (the value is their mean); otherwise it is discarded (logged). A
   genuine improvement repeats, a glitch does not; a discarded reading never becomes an
   evaluation or the best. Without a stated noise, ``noise_reads`` (> 0) readings at the setting
   found measure it before the first evaluation (:mod:`~pigp_torch.loop.noise`; logged in the
   start record, reused on a resume). A reading the machine refuses for its alarm severity
   (``SeverityError``: INVALID, or MAJOR by option) is discarded and read again; one that stays
   so stops the run naming the PV and the severity.
   *Readings checked against the machine's state* (``check_readings``, default on): the knob
   readbacks (``get()``) must lie within the readback tolerance of the setting before *and*
   after each reading (the machine's ``tolerance`` when it has one, else ``readback_tol`` of
   each range); a machine with ``setpoints()`` must show the same setpoints after the reading as
   before, and one with a ``disconnections`` counter must not have lost a connection during it.
   A reading that fails a check is discarded (a ``discarded`` record in the log, with the
   reason and the value) and taken again if the knobs are (still) at the setting, within the
   same ``read_retries``; if the knobs are no longer at the setting (an IOC reboot, another
   client) the run aborts with :class:`~pigp_torch.machine.errors.MachineError`. Freshness of
   the objective (timestamps that must advance) is the machine's check (``EpicsMachine``
   raises a ``StaleReadingError``, a ``ReadError``); what the machine reports about a reading
   (``last_reading``) is stored with the evaluation.
4. *Objective floor.* With ``objective_floor`` set, a valid reading below it is recorded, then the
   run aborts with :class:`RunAborted` (the beam may be gone or being lost).
5. *Restore.* The initial knobs — the SETPOINTS found at the start (rule 2), or on a resume
   those logged by the run's *first* start — are put back, by a ramp, when the run ends with
   any exception (a machine error, a refused setting, a bug, ``KeyboardInterrupt`` — Ctrl-C —
   SIGTERM or SIGHUP), and at the end of a completed run unless ``restore="best"`` or
   ``restore="none"``. A restoring ramp goes on through a readback that does not follow (the
   puts are still acknowledged one by one, each within the step limit), then the result is
   verified: the setpoints (where the machine has ``setpoints()``) equal to the target, and
   every readback within ``readback_tol`` of its range of the target — or of the readback
   found at the start, for a knob that already read off its setpoint then. When the ramp of
   every knob together fails (a put the machine refuses, e.g. outside control limits narrowed
   mid-run, or one never answered) each knob not yet at its target is ramped on its own, so one
   refused knob does not keep the others from their targets. A failed attempt is retried,
   ``restore_interval`` seconds apart (each ramps from the setpoints then held), until
   ``restore_attempts`` were made and ``restore_timeout`` seconds passed since the first; the
   end record says whether the knobs were restored, the target (``restore_target``), which
   knobs reached it (``knobs_at_target`` / ``knobs_not_at_target``), the setpoints and
   readbacks at the end, and the last setpoint the
   machine ACKNOWLEDGED (``last_setpoint``; ``last_intended`` the last one sent). While
   restoring, SIGINT/SIGTERM/SIGHUP are deferred (a second one abandons the restore: reported
   as not restored, with what is known).
   With ``restore="best"`` the knobs are first ramped to the first evaluation's point
   (normally the initial knobs) for a control reading that must reproduce its logged value
   (the machine or its instrument must not have changed), then to the best observed point,
   read again 3 times; it is confirmed if their mean agrees with the best of the run's
   :math:`N` readings within :math:`s(\sqrt{2\ln N} + 4\sqrt{1 + 1/3})` in either direction
   and, with the noise stated, the 3 agree with each other (:math:`s = \sigma`; without it a
   rough scale from the readings: see :mod:`pigp_torch.loop.readings`), and their mean is not
   worse than the control reading (never left below the start). If any check fails,
   or a point cannot be reached, the run says so (a warning and a ``notice`` record), restores
   the initial knobs instead (``restored_to = "initial (best not confirmed)"``) and reports no
   best (the end record's ``best`` is null, ``rejected_best`` names it).
6. *Signals.* With ``handle_signals`` (default) SIGTERM and SIGHUP (terminal closed, SSH
   dropped) raise :class:`Terminated`, a ``KeyboardInterrupt``, so they take the Ctrl-C path:
   restore, then re-raise; a SIGHUP that was ignored when the run started (``nohup``) stays
   ignored. The handlers are installed only in the main thread and the previous ones are always
   put back.
7. *Intent records.* With a log, every ``set`` the loop sends is preceded by an ``intent``
   record (the setting about to be written, the purpose, the step), written and fsynced before
   the write: after a crash (SIGKILL, power cut) the log holds the last commanded setting.

**Run log and resume.** With ``log`` every evaluation is appended (and fsynced) before the next
step, framed by a ``start`` and an ``end`` record (status, reason, where the knobs were put
back and their readback); see :mod:`pigp_torch.data.runlog`. ``resume=`` continues a logged run: the
optimizer is rebuilt with :func:`~pigp_torch.data.runlog.replay` and the run goes on at the next
step until ``budget`` evaluations in all; the knobs are restored to the initial knobs of the logged
run's first start (not to where a crash left them), and the new start record notes where the
knobs were found (``found_knobs``).
"""

from pigp_torch._utils.lazy import lazy_exports

#: public name -> the module that defines it (imported on first use: the ``pigp`` parser and the
#: run-file schema, :mod:`pigp_torch.loop.config`, are read without loading torch)
_EXPORTS = {
    "optimize": "core",
    "RAMP_FRACTION": "moves",
    "effective_max_step": "moves",
    "RESTORE_MODES": "options",
    "RunOptions": "options",
    "RunAborted": "signals",
    "Terminated": "signals",
    "track": "track_mode",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = [
    "RAMP_FRACTION",
    "RESTORE_MODES",
    "RunAborted",
    "RunOptions",
    "Terminated",
    "effective_max_step",
    "optimize",
    "track",
]
