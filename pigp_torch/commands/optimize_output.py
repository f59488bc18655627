r"""What ``pigp optimize`` prints: the plan of a run (``--dry-run``), where a resumed run stands,
and the summary of a run log."""

from __future__ import annotations

import contextlib
import math
import sys
from pathlib import Path

from pigp_torch._utils.units import display_unit
from pigp_torch.loop.config.schema import logged_units as log_units


def fmt_knobs(names, values, unit="") -> str:
    """``name=value, name=value (unit)``: the unit once, at the end; with one unit per knob (a
    list: knobs of different kinds) ``name=value unit, ...``."""
    if not isinstance(unit, str):
        return ", ".join(f"{n}={v:.6g} {u}" for n, v, u in zip(names, values, unit, strict=True))
    text = ", ".join(f"{n}={v:.6g}" for n, v in zip(names, values, strict=True))
    return f"{text} ({unit})" if unit else text


def print_plan(setup, records, out) -> None:
    c = setup.config
    names, bounds = c.knob_names, c.bounds()
    m = c.machine
    (k, yu), ku = display_unit(c.objective_unit), c.knob_unit  # readings as a person reads them
    machine = f"EPICS (objective PV {c.objective.pv})"
    if m.kind != "epics":  # a machine kind's simulated machine, in its kind's words
        from pigp_torch.machines import KINDS

        machine = KINDS.by_run_file_kind(m.kind).describe(c, setup.machine)
    from pigp_torch.loop import effective_max_step
    from pigp_torch.loop.moves import setpoints_of

    now = setpoints_of(setup.machine).tolist()  # setpoints: what a ramp starts from

    limit = effective_max_step(setup.machine, bounds, c.machine_max_step())
    print(f"plan: {c.method.name} on the {machine}", file=out)
    if c.mode == "track":  # until stopped, the time limit or the count, whichever first
        print(f"  track mode: until stopped, {c.time_limit} ({c.time_limit_s():g} s) or "
              f"{c.budget} readings; then the knobs at: {c.restore}", file=out)  # fmt: skip
    print(
        f"  budget {c.budget} evaluations, {'maximize' if c.objective.maximize else 'minimize'}"
        f" the objective ({yu}), options {c.method.options or '{}'}, seed {c.method.seed}",
        file=out,
    )
    units = setup.machine.knob_units  # one per knob (a column of its own), or None
    heads = ("lower", "upper", "now", "max step")
    head = "".join(f"{h if units else h + ' (' + ku + ')':>14}" for h in heads)
    print(f"  {'knob':<14}{head}{'  unit' if units else ''}", file=out)
    for i, n in enumerate(names):
        step = "none" if limit is None else f"{float(limit[i]):.4g}"
        print(
            f"  {n:<14}{float(bounds[0, i]):>14.4g}{float(bounds[1, i]):>14.4g}"
            f"{now[i]:>14.4g}{step:>14}{'  ' + units[i] if units else ''}",
            file=out,
        )
    floor = "none" if c.objective_floor is None else f"{k * c.objective_floor:g} {yu}"
    print(
        f"  at the end: restore {c.restore}; read retries {c.read_retries}; objective floor "
        f"{floor}",
        file=out,
    )
    opts = setup.options()
    rng = opts.objective_range or setup.machine.objective_limits
    rng_text = "none" if rng is None else f"[{k * rng[0]:g}, {k * rng[1]:g}] {yu}"
    noise = noise_in_force(setup, records)
    print(f"  readings: objective range {rng_text}; reading noise {noise}", file=out)
    if setup.prior_info:
        p = setup.prior_info
        print(f"  prior {p['path']} (sha256 {p['sha256'][:16]}…)", file=out)
    if records is not None:
        print(
            f"  resume {records.path}: {records.n_evaluations} logged evaluations, continue "
            f"at step {records.n_evaluations}",
            file=out,
        )
    else:
        print(f"  run log {c.log}", file=out)


def noise_in_force(setup, records) -> str:
    """The reading noise a run uses and where it comes from, with its unit (the plan's)."""
    from pigp_torch.loop.noise import NOISE_FLOOR_REL, logged_noise

    c, opts = setup.config, setup.options()
    k, yu = display_unit(c.objective_unit)
    if opts.noise is not None:
        from pigp_torch.machines import KINDS

        kind = KINDS.by_run_file_kind(c.machine.kind)  # None: the epics section
        simulator = kind is not None and kind.stated_noise(c.machine) is not None
        where = "objective_noise" if c.objective_noise is not None else (
            "the simulator's" if simulator else "the prior's")  # fmt: skip
        return f"{k * opts.noise:g} {yu} (stated: {where})"
    logged = logged_noise(records) if records is not None else None
    if logged is not None:
        return f"{k * logged['sigma']:.4g} {yu} (measured at the run's first start; from the log)"
    if opts.noise_reads:
        return (
            f"measured at the start: the standard deviation of {opts.noise_reads} readings at "
            f"the initial setting (at least {NOISE_FLOOR_REL:.0%} of their mean), in {yu}"
        )
    return "not stated: no re-read of outliers"


def say(out, text: str = "") -> None:
    """Print a line; a closed terminal (SIGHUP, SSH dropped) never stops the run or the restore."""
    with contextlib.suppress(OSError, ValueError):
        print(text, file=out, flush=True)


def print_summary(path: Path, out, log=None) -> dict | None:
    """Print how the run ended; returns the end record used.

    With a :class:`~pigp_torch.data.runlog.RunLog` (the session just run) the end record is
    ``log.end_record``, written to the file or not (a full disk never hides whether the knobs
    were restored); an earlier session's end record in the file is never taken for it. Without
    one, the log's last end record is used. The evaluations are counted from the file.
    """
    from pigp_torch.data.runlog import read_log

    records = None
    try:
        records = read_log(path, verify=False, warn=False)
    except (OSError, ValueError) as err:
        say(out, f"the run log could not be read back: {err}")
    if log is not None:
        end = log.end_record
    else:
        end = records.last_end if records is not None else None
    if end is None:
        if log is not None:
            failed = f"; a write failed: {log.write_error}" if log.write_error else ""
            say(out, f"run log: {path} (the session has no end record{failed})")
        return None
    header = records.header if records is not None else log.header
    names = list(header.get("knob_names"))
    yu, ku = log_units(header)
    k, yu = display_unit(yu)  # readings as a person reads them (a beam in µm)
    ku = header.get("knob_units") or ku  # one unit per knob where the machine has them
    say(out, f"status: {end['status']}" + (f" ({end['reason']})" if end.get("reason") else ""))
    if records is not None:
        start = records.starts[-1] if records.starts else {}
        session = records.n_evaluations - int(start.get("first_step", 0))
        say(out, f"evaluations: {records.n_evaluations} logged ({session} in this session)")
        noise = start.get("noise")
        if isinstance(noise, dict) and noise.get("source") == "measured":
            say(out, f"reading noise: {k * noise['sigma']:.4g} {yu}, measured at the start "
                     f"from {noise['n']} readings (mean {k * noise['mean']:.6g} {yu}, standard "
                     f"deviation {k * noise['spread']:.3g} {yu})")  # fmt: skip
    best = end.get("best")
    if best:
        say(
            out,
            f"best y = {k * best['y']:.6g} {yu} at evaluation {best['step'] + 1}: "
            f"{fmt_knobs(names, best['x'], ku)}",
        )
    rejected = end.get("rejected_best")
    if rejected:
        text = f"y = {k * rejected['y']:.6g} {yu} at evaluation {rejected['step'] + 1}"
        say(out, f"best: none (the best reading, {text}, was not confirmed: see the notice)")
    final = end.get("final_knobs")
    if end.get("restored") is False:
        last = end.get("last_setpoint")
        say(out, f"KNOBS NOT RESTORED ({end.get('restored_to')}, {end.get('restore_attempts')} "
                  "attempt(s)): " + "; ".join(end.get("restore_errors") or []))  # fmt: skip
        if isinstance(last, list):
            say(out, f"last setpoint acknowledged: {fmt_knobs(names, last, ku)}")
        intended = end.get("last_intended")
        if isinstance(intended, list) and intended != last:
            text = fmt_knobs(names, intended, ku)
            say(out, f"last setpoint intended (never acknowledged): {text}")
        if isinstance(final, list):
            say(out, f"readback now: {fmt_knobs(names, final, ku)}")
        elif final is not None:
            say(out, f"readback now: {final}")
        _against_target(names, end, out)
    elif isinstance(final, list):
        say(out, f"knobs restored to {end.get('restored_to')}, readback: "
                  f"{fmt_knobs(names, final, ku)}")  # fmt: skip
    elif final is not None:
        say(out, f"knobs: restore {end.get('restored_to')}; readback {final}")
    if log is not None and log.write_error:
        kept = "the end record is in it" if log.end_written else "the end record is NOT in it"
        say(out, f"run log: {path} (a write failed: {log.write_error}; {kept})")
    else:
        say(out, f"run log: {path}")
    return end


def _against_target(names, end: dict, out) -> None:
    """Per knob: the restore target, the setpoint and the readback at the end, and how far
    each is from the target (what is known when the restore did not finish)."""
    target, sp, rb = end.get("restore_target"), end.get("final_setpoints"), end.get("final_knobs")
    if not isinstance(target, list):
        return
    cols = [(k, v) for k, v in (("setpoint", sp), ("readback", rb)) if isinstance(v, list)]
    head = f"  {'knob':<14}{'target':>12}" + "".join(f"{k:>12}{k[:2] + '-target':>13}"
                                                     for k, _ in cols)  # fmt: skip
    say(out, "the knobs against the restore target:")
    say(out, head)
    for i, n in enumerate(names):
        line = f"  {n:<14}{target[i]:>12.6g}"
        for _, v in cols:
            line += f"{v[i]:>12.6g}{v[i] - target[i]:>13.3g}"
        say(out, line)


def print_resume_state(setup, records, out) -> None:
    """Where the knobs stand against the restore target (the first start's initial knobs) and
    the last commanded setting, and how many ramp steps away they are."""
    import torch

    from pigp_torch.loop import effective_max_step

    initial = records.initial_knobs
    if initial is None:
        return
    from pigp_torch.loop.moves import setpoints_of

    names = setup.config.knob_names
    now = setpoints_of(setup.machine).tolist()
    intent = records.last_intent
    last = intent["x"] if intent else None
    say(out, "resume: the knobs now against the initial knobs of the first start (the restore "
              "target) and the last setting commanded before the stop, in "
              f"{setup.config.knob_unit}:")  # fmt: skip
    head = f"  {'knob':<14}{'initial':>12}{'now':>12}{'now-initial':>13}"
    say(out, head + (f"{'last commanded':>16}" if last else ""))
    for i, n in enumerate(names):
        line = f"  {n:<14}{initial[i]:>12.6g}{now[i]:>12.6g}{now[i] - initial[i]:>13.4g}"
        say(out, line + (f"{last[i]:>16.6g}" if last else ""))
    bounds = setup.config.bounds()
    limit = effective_max_step(setup.machine, bounds, setup.config.machine_max_step())
    delta = torch.tensor(now, dtype=torch.float64) - torch.tensor(initial, dtype=torch.float64)
    if not bool(delta.abs().max() > 0):
        say(out, "  the knobs stand at the initial knobs")
    elif limit is not None:
        steps = math.ceil(float((delta.abs() / limit).max()))
        say(out, f"  the knobs are {steps} step limit(s) from the initial knobs; the restore "
                  "at the end ramps there within the step limit")  # fmt: skip
    if last is not None:
        at = max(abs(a - b) for a, b in zip(now, last, strict=True))
        where = "at" if at <= 1e-12 else f"{at:.3g} (largest knob difference) from"
        say(out, f"  the knobs stand {where} the last commanded setting ({intent['purpose']})")


#: Longest caproto log line printed (characters; a longer message is cut, with "...").
CAPROTO_LINE_CHARS = 300


@contextlib.contextmanager
def caproto_one_line(stream=None):
    """caproto's log records (WARNING and above) as one line each on ``stream`` (default: the
    ``sys.stderr`` of the moment) while the block runs, instead of Python's last-resort handler
    with full tracebacks (up to 38 lines for one reconnection): ``caproto <level>: <message>
    (<exception type>: <exception>)``, cut to :data:`CAPROTO_LINE_CHARS`. Nothing is silenced;
    the logger's own settings are put back afterwards."""
    import logging

    class OneLine(logging.Formatter):
        def format(self, record):
            text = " ".join(record.getMessage().split())
            if record.exc_info and record.exc_info[1] is not None:
                err = record.exc_info[1]
                text += f" ({type(err).__name__}: {' '.join(str(err).split())})"
            line = f"caproto {record.levelname.lower()}: {text}"
            if len(line) > CAPROTO_LINE_CHARS:
                line = line[: CAPROTO_LINE_CHARS - 3] + "..."
            return line

    logger = logging.getLogger("caproto")
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(OneLine())
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate
