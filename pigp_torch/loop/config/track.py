r"""The run-file keys of track mode (``mode: track``), checked with the rest of a run file.

A track run keeps the machine tuned for a shift (:mod:`pigp_torch.loop.track_mode`)::

    mode: track                # optimize (default): a one-shot run of `budget` evaluations
    time_limit: 8 h            # required in a track run: the wall-clock limit, a number and a
                               # unit (s, min, h, d), at most 31 d; counted from the (re)start
    budget: 100000             # in a track run: the most readings (the run ends at the time
                               # limit, at this count or when stopped, whichever comes first)
    restore: estimate          # where a track run leaves the knobs when it ends or is stopped:
                               # estimate (default: the optimizer's current estimate of the
                               # optimum), best (the best of the last best_window readings),
                               # current (where they are), initial (as found at the start)
    best_window: 20            # readings among which restore: best picks (default 20)

After a failure (a machine error, a safety rule, a full disk) a track run sets the initial knobs
back, as a one-shot run does. A one-shot run (``mode: optimize``) takes ``restore: initial``
(default), ``best`` (the best observed point, confirmed by fresh readings) or ``current`` (the
knobs left where the last evaluation put them); ``estimate`` and ``time_limit`` are refused
there.
"""

from __future__ import annotations

import math
import re

#: Seconds per unit of a ``time_limit``.
DURATION_UNITS = {"s": 1.0, "min": 60.0, "h": 3600.0, "d": 86400.0}
#: The longest ``time_limit`` a run file may give (31 days, in s): a longer one is a typo.
MAX_TIME_LIMIT_S = 31 * 86400.0

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-z]+)\s*$")


def duration_s(text: str) -> float:
    """Seconds of a duration written with its unit: ``"8 h"`` -> 28800.0 (units
    :data:`DURATION_UNITS`; positive, at most :data:`MAX_TIME_LIMIT_S`).

    Raises:
        ValueError: no unit, an unknown unit, or a value out of range.
    """
    match = _DURATION.match(str(text)) if isinstance(text, str) else None
    if match is None or match.group(2) not in DURATION_UNITS:
        raise ValueError(
            f"{text!r} is not a duration: give a number and a unit "
            f"({', '.join(DURATION_UNITS)}), e.g. 8 h"
        )
    seconds = float(match.group(1)) * DURATION_UNITS[match.group(2)]
    if not (0.0 < seconds <= MAX_TIME_LIMIT_S) or not math.isfinite(seconds):
        raise ValueError(f"{text!r}: a time limit must be above 0 s and at most 31 d")
    return seconds


def check_mode(mode: str, time_limit: str | None, restore: str | None) -> str:
    """Check the track-mode keys of a run file; returns the ``restore`` in force (the mode's
    default when the file gives none: ``estimate`` in a track run, ``initial`` else).

    Raises:
        ValueError: a key the mode does not take, or a track run without a time limit.
    """
    if mode == "track":
        if time_limit is None:
            raise ValueError(
                "time_limit: a track run needs a wall-clock limit (a number and a unit, e.g. 8 h)"
            )
        duration_s(time_limit)
        return restore or "estimate"
    if time_limit is not None:
        raise ValueError("time_limit is for mode: track (a one-shot run is bounded by budget)")
    if restore == "estimate":
        raise ValueError(
            "restore: estimate is for mode: track; a one-shot run restores initial, best or current"
        )
    return restore or "initial"
