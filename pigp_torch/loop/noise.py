r"""The noise of one reading when the run states none: measured at the start, as a few repeated
readings at the initial setting (:func:`measure_noise`), or taken back from the run log on a
resume (:func:`logged_noise`).

**The estimate** (:func:`estimate_noise`). From :math:`n` readings :math:`y_1, \dots, y_n` taken
at one setting (objective units), with mean :math:`\bar y` and sample standard deviation
:math:`s = \sqrt{\sum (y_i - \bar y)^2 / (n - 1)}`, the noise in force is

.. math:: \sigma = \max\left(s,\ f\,|\bar y|,\ \sigma_0\right), \qquad
          f = 0.01\ (:data:`NOISE_FLOOR_REL`), \quad \sigma_0 = 10^{-12}\ (:data:`NOISE_FLOOR_ABS`),

a floor at a small fraction of the level, so that an instrument whose readings are quantized
(the same value :math:`n` times: :math:`s = 0`) does not give a zero noise that would make every
later reading an outlier. :math:`\sigma` is then the loop's stated noise: the outlier / glitch
rule and the best point's confirmation (:mod:`pigp_torch.loop.readings`) use it.

**In the run log** the start record of every session carries ``noise``:
``{"sigma", "source"}`` with ``source`` ``"stated"`` (the run's own), ``"measured"`` (this
session's start; with ``readings``, ``mean``, ``spread`` = :math:`s`, ``floor``) or ``"logged"``
(taken from the session that measured it; ``line``: its start record's line). A resume reuses a
measured noise and never measures again.
"""

from __future__ import annotations

import math

import torch

from pigp_torch._utils import utc_now as _utc_now
from pigp_torch.loop.moves import checked_read
from pigp_torch.loop.readings import ReadingJudge

#: Floor of the measured noise, as a fraction of the mean level :math:`|\bar y|`.
NOISE_FLOOR_REL = 0.01
#: Absolute floor of the measured noise (objective units): a level of exactly 0.
NOISE_FLOOR_ABS = 1e-12


def estimate_noise(readings) -> dict:
    r""":math:`\sigma = \max(s, f|\bar y|, \sigma_0)` of ``readings`` (``n >= 2`` finite values at
    one setting, objective units; the formula in the module docstring).

    Returns:
        ``{"sigma", "mean", "spread", "floor", "n", "readings"}``: the noise in force, the mean
        :math:`\bar y`, the sample standard deviation :math:`s`, the floor
        :math:`\max(f|\bar y|, \sigma_0)`, the count and the readings.

    Raises:
        ValueError: fewer than two readings, or one not finite.
    """
    ys = [float(y) for y in readings]
    if len(ys) < 2 or not all(math.isfinite(y) for y in ys):
        raise ValueError(f"the noise needs at least two finite readings, got {ys}")
    y = torch.tensor(ys, dtype=torch.float64)
    mean, spread = float(y.mean()), float(y.std())  # std: the n - 1 (unbiased variance) form
    floor = max(NOISE_FLOOR_REL * abs(mean), NOISE_FLOOR_ABS)
    return {"sigma": max(spread, floor), "mean": mean, "spread": spread, "floor": floor,
            "n": len(ys), "readings": ys}  # fmt: skip


def logged_noise(resume) -> dict | None:
    """The noise a logged run measured (its first start record whose ``noise`` was measured):
    ``{"sigma", "source": "logged", "line"}``, ``None`` when it measured none (its noise was
    stated, or the log predates the measurement)."""
    for start in resume.starts:
        noise = start.get("noise")
        if isinstance(noise, dict) and noise.get("source") == "measured":
            sigma = float(noise["sigma"])
            if not (0.0 < sigma < math.inf):
                raise ValueError(f"the run log's measured noise {sigma} is not positive")
            return {"sigma": sigma, "source": "logged", "line": start.get("_line")}
    return None


def measure_noise(run, n: int) -> dict:
    r"""Read the objective ``n`` times at the setting the run found (nothing moved; every reading
    checked against the machine's state, finite and inside the objective range, re-read within
    the run's ``read_retries``) and :func:`estimate_noise` of them; the run's judge then uses it.
    A reading discarded on the way is logged (``discarded``, step 0, ``noise measurement: ...``).

    Returns:
        the estimate with ``"source": "measured"``.

    Raises:
        ReadError, MachineError: a reading failed (the run stops; nothing was moved).
    """
    opts = run.opts

    def discard(reason: str, y: float) -> None:
        if run.log is not None:
            run.log.write("discarded", step=0, y=y, reason=f"noise measurement: {reason}",
                          time=_utc_now())  # fmt: skip

    plain = ReadingJudge(None, run.objective_range)
    readings = []
    for _ in range(n):
        y, _reads = checked_read(run.objective, run.rb_found, run.read_tol, opts.read_retries,
                                 opts.retry_interval, discard, plain)  # fmt: skip
        readings.append(y)
    info = estimate_noise(readings)
    info["source"] = "measured"
    run.judge.noise = info["sigma"]
    return info
