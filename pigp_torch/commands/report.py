"""``pigp report``: a figure of one run (its run log) or of a ``pigp compare`` folder."""

from __future__ import annotations

from pathlib import Path


def cmd_report(args) -> int:
    from pigp_torch.report import write_report

    png, page = write_report(args.target, args.output, noise=args.noise)
    print(f"wrote {png} and {page}")
    return 0


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
        "OUT.html (the PNG embedded; no external files).",
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
