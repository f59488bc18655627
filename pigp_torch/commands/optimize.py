r"""``pigp optimize``: an online run from a run file, with a run log, safe stops and resume.

``pigp optimize --config run.yaml`` validates the file (:mod:`pigp_torch.loop.config`), takes the
run's locks (the run log's, and on EPICS one per PV prefix: :mod:`pigp_torch.data.runlock`), builds
the optimizer and then the machine, writes the run log's header (configuration and its sha256,
prior provenance) and runs :func:`pigp_torch.optimize` with ramped moves, intent records, read
retries, checked readings, the objective floor and the restore of the initial knobs (or the best
point with ``restore: best``). One line per evaluation goes to stdout (step N of M counted from
1, the reading, the best so far, the largest knob move from the previous evaluation and the
seconds the step took: :class:`pigp_torch.loop.progress.ProgressLine`), then a summary: status, best
reading and where, and where the knobs were put back — or, if they could not be, the last
setpoint written.

``--resume LOG`` continues a logged run: the log's hash chain is verified (an edited log is
refused, exit 2, naming the first line that does not match; a torn last line is dropped with one
warning; a log of an older version without a chain resumes with a warning where that version
could have written it, and its restore target, when more than the step limit from the setpoints
now, only with ``--accept-restore-target``), the optimizer is
rebuilt from the logged evaluations (:func:`pigp_torch.data.runlog.replay`), the knobs are compared
with the initial knobs of the run's first start (the restore target) and the last commanded
setting, and the run goes on up to the budget (which may be raised in the run file; nothing else
may change). Without ``--config`` the configuration in the log header is used after its sha256 is
verified, and its safety limits are printed. ``--dry-run`` validates, checks the log path and the
locks, connects and prints the plan without moving anything or writing the log; an existing log
is named, with what a run would do, instead of being refused.

How the run ended is taken from the end record the loop handed to the run log
(:attr:`pigp_torch.data.runlog.RunLog.end_record`), written or not: a full log disk stops the run
(:class:`~pigp_torch.data.runlog.LogWriteError`, the knobs restored by the loop, one line, the
summary) and never hides that the knobs were not restored (exit 3). Python warnings, and
caproto's log records (a reconnection's traceback), are printed as one plain line each while the
command runs.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
from pathlib import Path

from pigp_torch.commands.optimize_log import (
    _check_arguments,
    _check_log_folder,
    _existing_log,
    _locks,
    _read_resumed,
    unverified_target,
)
from pigp_torch.commands.optimize_output import (
    caproto_one_line,
    print_plan,
    print_resume_state,
    print_summary,
    say,
)

#: Exit statuses of ``pigp optimize`` (also in ``--help`` and the README).
EXIT_OK = 0
EXIT_STOPPED = 1  # a safety rule, a machine error, a log write or another error; restored
EXIT_INPUT = 2  # invalid input (run file, log, its hash chain, arguments); nothing was moved
EXIT_NOT_RESTORED = 3  # the knobs were NOT restored (any cause): see the last setpoint
EXIT_LOCKED = 4  # another run holds the run log or the machine; nothing was moved

DESCRIPTION = (
    "Run an optimizer ({methods}) on the machine described by a "
    "YAML/JSON run file. Every evaluation is appended to a JSON-lines run log before the "
    "next step, and every setting is logged before it is written; the initial knobs are "
    "restored on Ctrl-C, SIGTERM, SIGHUP, errors and at the end (unless restore: best). "
    "One run per run log and per machine (lock files). --resume LOG continues a logged run "
    "and restores to the knobs of its first start; --dry-run only prints the plan. "
    "Ramps and restores work on the SETPOINTS (never from readbacks; no put above max_step). "
    "A reading counts only if finite, not in alarm (INVALID; MAJOR with machine: "
    "refuse_severity: MAJOR), inside objective_range (default: the objective PV's "
    "limits) and, with objective_noise (on EPICS without it: measured at the start from "
    "noise_reads readings), confirmed by a re-read when far from the run's own "
    "(the first reading always); with restore: best a control reading at the first "
    "evaluation's point and fresh readings at the best point must reproduce their logged "
    "values (either direction) and not read worse than the control reading, else the "
    "initial knobs are restored and no best is reported."
)

EXIT_HELP = """rules:
  run file  checked as a whole before anything connects; numbers must be numbers (true,
            false or a quoted "0.5" where a number belongs is refused, not converted);
            max_step is required: a fraction of each knob's half-range of at most 1, or
            {knob: value} of at most half that knob's range; anything larger is refused
            unless the file says max_step: unlimited
  run log   one JSON line per record, fsynced before the next step; every setting is
            logged before it is written; each record carries a sha256 chained to the
            previous one: --resume and pigp report refuse a log edited anywhere (exit 2,
            naming the first line that does not match); a last line cut short by a crash is
            dropped with one warning; a log of an older version (no chain) resumes, with a
            warning that it cannot be verified, only where that version could have written
            every record (else exit 2), and only with --accept-restore-target when its
            restore target is more than max_step from the setpoints now (else shown, exit 2)
  log disk  a log write that fails (disk full, I/O error) stops the run: the knobs are
            restored, one line says why, the summary is printed; a log whose header could
            not be written is removed (nothing moved)
  --dry-run writes nothing and moves nothing; an existing run log is not refused but named,
            with what a run would do (refuse it: continue it with --resume)

exit status:
  0    completed; the knobs restored (or set to the best point with restore: best)
  1    stopped by a safety rule, a machine error, a failed run-log write or another error;
       knobs restored (also: a PV that does not connect, or a run log that cannot be
       started — a full disk, a read-only log folder; nothing moved)
  2    invalid input (run file, a folder or unreadable file given as one, an existing run
       log, a run log that fails its hash chain, arguments); nothing moved
  3    the knobs were NOT restored (whatever ended the run, a full log disk included): the
       last setpoint the machine acknowledged is printed and logged when the log can be
       written (end record: restored false, last_setpoint)
  4    refused: another run holds the run log or the machine (lock file named); nothing
       moved
  129  stopped by SIGHUP, 130 by SIGINT (Ctrl-C), 143 by SIGTERM; knobs restored (mode:
       track: left where its restore says, by default the optimizer's estimate)
"""


def _list_methods_in_help(p: argparse.ArgumentParser) -> None:
    """Name the run-file methods of the registry in ``p``'s help, read when the help is shown
    (the registry imports torch; building the parser must not)."""
    format_help = p.format_help

    def with_methods() -> str:
        from pigp_torch.methods import run_file_methods

        p.description = DESCRIPTION.format(methods=", ".join(run_file_methods()))
        return format_help()

    p.format_help = with_methods


def register(sub, bench) -> None:
    """Add ``pigp optimize`` to the top-level sub-parsers ``sub`` (``bench`` is unused)."""
    p = sub.add_parser(
        "optimize",
        help="optimize a machine (simulated or EPICS) from a run file, with a run log",
        description=DESCRIPTION.format(methods="the methods of pigp_torch.methods"),
        epilog=EXIT_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _list_methods_in_help(p)
    p.add_argument(
        "--config",
        type=Path,
        help="run file (YAML or JSON); with --resume it must match the logged configuration "
        "except for the budget (default with --resume: the logged configuration)",
    )
    p.add_argument(
        "--resume", type=Path, metavar="LOG", help="continue the run recorded in this run log"
    )
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="validate, connect and print the plan; move nothing, write nothing (an existing "
        "run log is named with what a run would do, not refused)",
    )
    p.add_argument(
        "--accept-restore-target",
        action="store_true",
        help="with --resume of a log without a hash chain (an older version's): restore to its "
        "logged initial knobs even when they are more than max_step from the setpoints now "
        "(they cannot be verified; without this flag such a resume is refused, exit 2)",
    )
    p.add_argument("--quiet", action="store_true", help="no line per evaluation")
    p.add_argument(
        "--dashboard",
        action="store_true",
        help="serve a live page of the run on 127.0.0.1 (step, readings and best so far, knob "
        "settings, notices; read from the run log) while it runs; the URL is printed. At the "
        "end the final state is written to <log stem>_dashboard.html (path printed) and the "
        "server stops once an open page has it (at most 5 s)",
    )
    p.add_argument(
        "--dashboard-port",
        type=int,
        default=0,
        metavar="PORT",
        help="port of the dashboard (default 0: a free one)",
    )
    p.set_defaults(func=cmd_optimize)


@contextlib.contextmanager
def _plain_warnings():
    """Python warnings printed as one plain line (``warning: message``, no file name or source
    line) while the command runs; the run log's own warnings are printed by the command once."""
    import warnings

    from pigp_torch.data.runlog import RunLogWarning

    previous = warnings.formatwarning
    warnings.formatwarning = lambda message, *a, **k: f"warning: {message}\n"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RunLogWarning)
            yield
    finally:
        warnings.formatwarning = previous


def cmd_optimize(args) -> int:
    _check_arguments(args)
    with _plain_warnings(), caproto_one_line():
        return _optimize(args)


def _optimize(args) -> int:
    import torch

    from pigp_torch.data.runlock import LockHeld, holding
    from pigp_torch.loop.run import build_run, check_resume, load_config, logged_config
    from pigp_torch.machine.errors import MachineError

    torch.set_num_threads(1)  # an online run is measurement-bound; do not crowd the host
    out = sys.stdout
    from_header = False
    if args.resume is not None:
        if Path(args.resume).is_dir():
            raise ValueError(f"--resume {args.resume}: a folder, not a run log")
        records = _read_resumed(args.resume, warn_out=sys.stderr)  # read again under the lock
        config = load_config(args.config) if args.config is not None else logged_config(records)
        from_header = args.config is None
        log_path = Path(args.resume)
    else:
        config = load_config(args.config)
        try:
            _check_log_folder(config.log)
        except PermissionError as err:  # a read-only folder: exit 1, as a full disk
            say(sys.stderr, f"pigp optimize: could not start the run: {err.strerror}; nothing "
                             "was moved")  # fmt: skip
            return EXIT_STOPPED
        log_path = config.log
    locks = _locks(config, log_path)
    try:
        with holding(locks) as taken:  # the log's lock first: a log in use is refused (exit 4)
            for lock in taken:
                if lock.stale:
                    say(sys.stderr, f"note: took over the stale lock {lock.path} of PID "
                                     f"{lock.stale.get('pid')} on {lock.stale.get('host')} "
                                     "(no longer running)")  # fmt: skip
            if args.resume is None and config.log.exists():
                what = (
                    f"the run log {config.log} exists: continue it with --resume "
                    f"{config.log}, or set another log path ({_existing_log(config.log)})"
                )
                if not args.dry_run:
                    raise ValueError(what)
                say(sys.stderr, f"note: {what}; a run with this file would be refused (exit "
                                 f"{EXIT_INPUT})")  # fmt: skip
            if args.dry_run:  # the locks were free; a dry run does not keep them
                for lock in reversed(taken):
                    lock.release()
            records = None
            if args.resume is not None:
                records = _read_resumed(args.resume)  # what the log holds now that it is ours
                check_resume(config, records)
                if records.n_evaluations >= config.budget:
                    raise ValueError(
                        f"{args.resume} already holds {records.n_evaluations} evaluations and "
                        f"the budget is {config.budget}: raise the budget in the run file to "
                        "continue"
                    )
            if from_header:
                say(out, f"configuration from the log header of {args.resume} (sha256 "
                          "verified); safety limits used:")  # fmt: skip
                for line in config.safety_lines():
                    say(out, f"  {line}")
            for warning in config.warnings():
                say(sys.stderr, f"warning: {warning}")
            try:
                setup = build_run(config)  # the machine is constructed (connected) last
            except MachineError as err:
                say(sys.stderr, f"pigp optimize: could not connect to the machine: {err}")
                return EXIT_STOPPED
            try:
                refusal = None if records is None else unverified_target(setup, records)
                if refusal and not args.dry_run and not args.accept_restore_target:
                    print_resume_state(setup, records, out)  # the target shown, then refused
                    raise ValueError(refusal)
                log_lock = None if args.dry_run else taken[0]
                return _run(args, setup, records, log_lock)
            finally:
                close = getattr(setup.machine, "close", None)  # EPICS: release CA connections
                if callable(close):
                    close()
    except LockHeld as err:
        say(sys.stderr, f"pigp optimize: refused: {err}")
        return EXIT_LOCKED
    except OSError as err:  # a lock file or the log cannot be created: nothing was moved
        if isinstance(err, FileNotFoundError):
            raise
        say(sys.stderr, f"pigp optimize: could not start the run: {err}; nothing was moved")
        return EXIT_STOPPED


def _run(args, setup, records, log_lock) -> int:
    from pigp_torch.data.runlog import LogWriteError, RunLog
    from pigp_torch.loop import RunAborted, Terminated
    from pigp_torch.loop.run import advance_simulated_noise
    from pigp_torch.machine.errors import MachineError

    config = setup.config
    out = sys.stdout
    if args.dry_run:
        print_plan(setup, records, out)
        if records is not None:
            print_resume_state(setup, records, out)
        say(out, "dry run: nothing was moved or written")
        return EXIT_OK

    try:
        if records is not None:
            log = RunLog.append(args.resume, lock=log_lock, warn=False)
        else:
            log = RunLog.create(config.log, setup.header(), lock=log_lock)
    except LogWriteError as err:
        say(sys.stderr, f"pigp optimize: could not start the run: {err} (no run log was left "
                         "behind); nothing was moved")  # fmt: skip
        return EXIT_STOPPED
    if records is not None:
        advance_simulated_noise(
            setup.machine, sum(int(r.get("reads", 1)) for r in records.evaluations)
        )
    print_plan(setup, records, out)
    if records is not None:
        print_resume_state(setup, records, out)
    with contextlib.suppress(OSError, ValueError):
        out.flush()
    from pigp_torch.loop.progress import ProgressLine

    report = ProgressLine(
        config.budget,
        config.knob_names,
        maximize=config.objective.maximize,
        unit=getattr(setup.machine, "knob_units", None) or config.knob_unit,
        objective_unit=config.objective_unit,
        out=out,
    )
    if records is not None and records.evaluations:
        say(out, f"replaying {records.n_evaluations} logged evaluations (one ask each) ...")
        report.seed([r["x"] for r in records.evaluations], [r["y"] for r in records.evaluations])
    dashboard = None
    if getattr(args, "dashboard", False):
        from pigp_torch.reporting.dashboard import Dashboard, final_page_path

        dashboard = Dashboard(log.path, port=args.dashboard_port)
        say(out, f"dashboard: {dashboard.url} (while the run goes; the final page is then "
                  f"written to {final_page_path(log.path)})")  # fmt: skip
    code = EXIT_STOPPED
    try:
        setup.run(log=log, resume=records, callback=None if args.quiet else report)
        code = EXIT_OK
    except KeyboardInterrupt as err:
        signum = err.signum if isinstance(err, Terminated) else signal.SIGINT
        code = 128 + int(signum)
        say(sys.stderr, f"pigp optimize: interrupted ({type(err).__name__}: "
                         f"{signal.Signals(signum).name})")  # fmt: skip
    except LogWriteError as err:  # disk full, I/O error: the loop stopped and restored
        say(sys.stderr, f"pigp optimize: run stopped: {err}")
    except (MachineError, RunAborted) as err:
        say(sys.stderr, f"pigp optimize: run aborted: {type(err).__name__}: {err}")
    except Exception as err:  # a refused setting, a bug: the loop has restored the knobs
        say(sys.stderr, f"pigp optimize: run failed: {type(err).__name__}: {err}")
    finally:
        log.close()  # never raises: every record was fsynced when written
        with contextlib.suppress(Exception):  # the summary never hides the exit status
            print_summary(log.path, out, log=log)
        if dashboard is not None:
            try:
                say(out, f"dashboard: final page {dashboard.finish()}")
            except (OSError, ValueError) as err:
                say(sys.stderr, f"pigp optimize: dashboard final page not written: {err}")
        with contextlib.suppress(OSError, ValueError):
            out.flush()
    end = log.end_record  # this session's, written or not (never an earlier session's)
    if end is not None and end.get("restored") is False:
        say(sys.stderr, "pigp optimize: the knobs were NOT restored (exit status 3)"
                         + _which_knobs(end))  # fmt: skip
        return EXIT_NOT_RESTORED
    if end is None and log.moved:  # the run ended before its end record: the knobs are unknown
        say(sys.stderr, "pigp optimize: the run ended without an end record after moving the "
                         "knobs: they may NOT be restored (exit status 3)")  # fmt: skip
        return EXIT_NOT_RESTORED
    return code


def _which_knobs(end: dict) -> str:
    """``": at the target: A, B; NOT at the target: C"`` from an end record ("" without)."""
    at, off = end.get("knobs_at_target"), end.get("knobs_not_at_target")
    if not isinstance(at, list) or not isinstance(off, list):
        return ""
    return f": at the target: {', '.join(at) or 'none'}; NOT at the target: {', '.join(off)}"
