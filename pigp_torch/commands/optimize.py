r"""``pigp optimize``: an online run from a run file, with a run log, safe stops and resume.

``pigp optimize --config run.yaml`` validates the file (:mod:`pigp_torch.config`), builds the
optimizer and then the machine, writes the run log's header (configuration, prior provenance) and
runs :func:`pigp_torch.optimize` with ramped moves, read retries, the objective floor and the
restore of the initial knobs (or the best point with ``restore: best``). One line per evaluation
goes to stdout, then a summary: status, best reading and where, and where the knobs were put back.

``--resume LOG`` continues a logged run: the optimizer is rebuilt from the logged evaluations
(:func:`pigp_torch.runlog.replay`) and the run goes on up to the budget (which may be raised in
the run file; nothing else may change). ``--dry-run`` validates, connects and prints the plan
without moving anything or writing the log.

Exit status: 0 completed, 1 aborted by a safety rule or a machine error, 2 invalid input,
130 interrupted by Ctrl-C (SIGINT), 143 by SIGTERM — in every case after the knobs were restored.
"""

from __future__ import annotations

import sys
from pathlib import Path


def register(sub, bench) -> None:
    """Add ``pigp optimize`` to the top-level sub-parsers ``sub`` (``bench`` is unused)."""
    p = sub.add_parser(
        "optimize",
        help="optimize a machine (simulated or EPICS) from a run file, with a run log",
        description="Run an optimizer (pigp, ml2, nelder-mead, rcds) on the machine described by "
        "a YAML/JSON run file. Every evaluation is appended to a JSON-lines run log before the "
        "next step; the initial knobs are restored on Ctrl-C, SIGTERM, errors and at the end "
        "(unless restore: best). --resume LOG continues a logged run; --dry-run only prints the "
        "plan.",
    )
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
        help="validate, connect and print the plan; move nothing, write nothing",
    )
    p.add_argument("--quiet", action="store_true", help="no line per evaluation")
    p.set_defaults(func=cmd_optimize)


def _fmt_knobs(names, values) -> str:
    return ", ".join(f"{n}={v:.6g}" for n, v in zip(names, values, strict=True))


def _print_plan(setup, records, out) -> None:
    c = setup.config
    names, bounds = c.knob_names, c.bounds()
    m = c.machine
    if m.kind == "sim":
        machine = f"simulated ring (error seed {m.error_seed}, noise {m.noise:g}, seed {m.seed})"
    else:
        machine = f"EPICS (objective PV {c.objective.pv})"
    now = setup.machine.get().tolist()
    from pigp_torch.loop import effective_max_step

    limit = effective_max_step(setup.machine, bounds, c.machine_max_step())
    print(f"plan: {c.method.name} on the {machine}", file=out)
    print(
        f"  budget {c.budget} evaluations, {'maximize' if c.objective.maximize else 'minimize'}"
        f" the objective, options {c.method.options or '{}'}, seed {c.method.seed}",
        file=out,
    )
    print(f"  {'knob':<14}{'lower':>12}{'upper':>12}{'now':>12}{'max step':>12}", file=out)
    for i, n in enumerate(names):
        step = "none" if limit is None else f"{float(limit[i]):.4g}"
        print(
            f"  {n:<14}{float(bounds[0, i]):>12.4g}{float(bounds[1, i]):>12.4g}"
            f"{now[i]:>12.4g}{step:>12}",
            file=out,
        )
    floor = "none" if c.objective_floor is None else f"{c.objective_floor:g}"
    print(
        f"  at the end: restore {c.restore}; read retries {c.read_retries}; objective floor "
        f"{floor}",
        file=out,
    )
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


def _print_summary(path: Path, out) -> None:
    from pigp_torch.runlog import read_log

    records = read_log(path)
    end = records.last_end
    if end is None:
        return
    names = records.knob_names
    print(
        f"status: {end['status']}" + (f" ({end['reason']})" if end.get("reason") else ""), file=out
    )
    start = records.starts[-1] if records.starts else {}
    session = records.n_evaluations - int(start.get("first_step", 0))
    print(f"evaluations: {records.n_evaluations} logged ({session} in this session)", file=out)
    best = end.get("best")
    if best:
        print(
            f"best y = {best['y']:.6g} at step {best['step']}: {_fmt_knobs(names, best['x'])}",
            file=out,
        )
    final = end.get("final_knobs")
    if isinstance(final, list):
        print(
            f"knobs restored to {end.get('restored_to')}, readback: {_fmt_knobs(names, final)}",
            file=out,
        )
    elif final is not None:
        print(f"knobs: restore {end.get('restored_to')}; readback {final}", file=out)
    print(f"run log: {path}", file=out)


def cmd_optimize(args) -> int:
    import torch

    from pigp_torch.config import build_run, check_resume, load_config, logged_config
    from pigp_torch.runlog import read_log

    torch.set_num_threads(1)  # an online run is measurement-bound; do not crowd the host
    if args.config is None and args.resume is None:
        raise ValueError("give a run file with --config RUN.yaml (or --resume LOG)")
    records = None
    if args.resume is not None:
        records = read_log(args.resume)
        config = load_config(args.config) if args.config is not None else logged_config(records)
        check_resume(config, records)
        if records.n_evaluations >= config.budget:
            raise ValueError(
                f"{args.resume} already holds {records.n_evaluations} evaluations and the "
                f"budget is {config.budget}: raise the budget in the run file to continue"
            )
    else:
        config = load_config(args.config)
        if config.log.exists() and not args.dry_run:
            raise ValueError(
                f"the run log {config.log} exists: continue it with --resume {config.log}, or "
                "set another log path"
            )
    setup = build_run(config)  # the machine is constructed (connected) last
    try:
        return _run(args, setup, records)
    finally:
        close = getattr(setup.machine, "close", None)  # EPICS: release the CA connections
        if callable(close):
            close()


def _run(args, setup, records) -> int:
    from pigp_torch.config import advance_simulated_noise
    from pigp_torch.loop import RunAborted, Terminated
    from pigp_torch.machine.errors import MachineError
    from pigp_torch.runlog import RunLog

    config = setup.config
    out = sys.stdout
    if args.dry_run:
        _print_plan(setup, records, out)
        print("dry run: nothing was moved or written", file=out)
        return 0

    if records is not None:
        log = RunLog.append(args.resume)
        advance_simulated_noise(
            setup.machine, sum(int(r.get("reads", 1)) for r in records.evaluations)
        )
    else:
        log = RunLog.create(config.log, setup.header())
    _print_plan(setup, records, out)
    out.flush()
    budget = config.budget
    maximize = config.objective.maximize
    state = {"best": None}

    def report(row: dict) -> None:
        y = row["y"]
        b = state["best"]
        if b is None or (y > b if maximize else y < b):
            state["best"] = y
        print(
            f"step {row['step']:>4}/{budget}  y = {y:.6g}  best = {state['best']:.6g}",
            file=out,
            flush=True,
        )

    if records is not None and records.evaluations:
        print(
            f"replaying {records.n_evaluations} logged evaluations (one ask each) ...",
            file=out,
            flush=True,
        )
        ys = [r["y"] for r in records.evaluations]
        state["best"] = max(ys) if maximize else min(ys)
    code = 2
    try:
        setup.run(log=log, resume=records, callback=None if args.quiet else report)
        code = 0
    except KeyboardInterrupt as err:
        code = 143 if isinstance(err, Terminated) else 130
        print(f"pigp optimize: interrupted ({type(err).__name__})", file=sys.stderr)
    except (MachineError, RunAborted) as err:
        code = 1
        print(f"pigp optimize: run aborted: {type(err).__name__}: {err}", file=sys.stderr)
    finally:
        log.close()
        _print_summary(log.path, out)
        out.flush()
    return code
