"""``pigp report``: a figure of one run (its run log) or of a ``pigp compare`` folder."""

from __future__ import annotations

from pathlib import Path


def cmd_report(args) -> int:
    """Draw the report; a run log is first read with its hash chain verified (an edited log is
    refused, exit 2 naming the first line that does not match), and its warnings (a torn last
    line, a log without a chain) are printed once, one plain line each."""
    import sys
    import warnings

    from pigp_torch.data.runlog import RunLogWarning, read_log
    from pigp_torch.reporting.report import write_report

    target = Path(args.target)
    if target.is_file():
        for note in read_log(target, warn=False).warnings:  # ValueError: refused (exit 2)
            print(f"warning: {note}", file=sys.stderr)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RunLogWarning)  # printed above, once
        png, page = write_report(target, args.output, noise=args.noise, progress=_say)
    print(f"wrote {png} and {page}")
    return 0


def _say(text: str) -> None:
    """A line of progress on stdout, at once (the steps it announces take seconds)."""
    print(text, flush=True)


def register(sub, bench) -> None:
    """Add ``pigp report`` to the top-level sub-parsers ``sub`` (nothing under ``bench``)."""
    p = sub.add_parser(
        "report",
        help="figure (PNG and self-contained HTML) of a run log or a pigp compare folder",
        description="For a run log (pigp optimize): readings with the noise band, best so far "
        "(and on the simulated ring the noise-free value), knob trajectories within their "
        "limits, for pigp-physics the fitted optimum and its centre with 2-sigma bars, and the "
        "run's notices (resumes, discarded readings, knobs at a limit, how it ended). For a "
        "folder with runs.csv (pigp compare, pigp demo): the gain fraction per method (median, "
        "interquartile range) and the best noise-free value of every run. Writes OUT.png and "
        "OUT.html (the PNG embedded; no external files). A run log's hash chain is verified "
        "first: a log edited anywhere is refused (exit 2, naming the first line that does not "
        "match); a last line cut short by a crash is ignored with a warning; a log from an "
        "older version (no chain) is drawn with a warning that it cannot be verified.",
    )
    p.add_argument("target", type=Path, help="run log (.jsonl) or pigp compare folder")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="output path without suffix (default: LOG_report next to the log, FOLDER/report)",
    )
    p.add_argument(
        "--noise",
        type=float,
        default=None,
        help="noise sigma of the readings for the band when the run file gives none (EPICS "
        "without a prior)",
    )
    p.set_defaults(func=cmd_report)
