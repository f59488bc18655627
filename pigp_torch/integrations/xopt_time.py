r"""Xopt's time-dependent Bayesian optimization on a clock of readings.

Needs the optional extra ``xopt``.

Xopt 3's :class:`~xopt.generators.bayesian.upper_confidence_bound.TDUpperConfidenceBoundGenerator`
(Kuklev et al., "Online accelerator tuning with adaptive Bayesian optimization", NAPAC 2022)
models the objective as a GP over the knobs AND time: its
:class:`~xopt.generators.bayesian.models.time_dependent.TimeDependentModelConstructor` builds the
product kernel :math:`k_{\mathrm{SM}}(t, t')\,k_{\mathrm{Mat\acute ern\,5/2}}(x, x')` (a spectral
mixture of 3 components on time, an ARD Matérn on the knobs, all trained at every step), and the
UCB acquisition :math:`\mu + \sqrt\beta\,\sigma` is maximised over the knobs with time fixed at the
target time :math:`t_{\mathrm{now}} + \Delta t` (``added_time``). Stock Xopt reads the wall clock
(``time.time()``), sleeps until the target time and expects the evaluator to write a ``time``
column.

:class:`ReadingClockTDUCB` is the same generator on a deterministic clock: time is the reading
index. Row :math:`n` of the generator's data (the :math:`n`-th reading told, from 0) gets
``time = n``; the target time of a proposal is :math:`t_{\mathrm{now}} + \Delta t` with
:math:`t_{\mathrm{now}}` the index of the last reading and ``added_time`` :math:`\Delta t = 1`
(the reading about to be taken); ``forgetting_time`` (readings) keeps the readings with
:math:`t > t_{\mathrm{now}} - ` ``forgetting_time``. Nothing sleeps and nothing depends on the
load of the computer, so a seeded run repeats exactly. The time bounds of the model's input
normalisation stay Xopt's (first reading to last + 15).
"""

from __future__ import annotations

from copy import copy

import numpy as np
import pandas as pd
from pydantic import Field, PositiveFloat

try:
    from xopt.generators.bayesian.time_dependent import TimeDependentBayesianGenerator
    from xopt.generators.bayesian.upper_confidence_bound import TDUpperConfidenceBoundGenerator
except ImportError as err:  # pragma: no cover - depends on the environment
    raise ImportError(
        "pigp_torch.integrations.xopt_time needs Xopt; install the extra: "
        "pip install 'pigp-torch[xopt]'"
    ) from err

#: Name of Xopt's time column.
TIME = "time"


class ReadingClockTDUCB(TDUpperConfidenceBoundGenerator):
    r"""Xopt's time-dependent UCB with time = the reading index (module docstring).

    Fields as :class:`~xopt.generators.bayesian.upper_confidence_bound.\
TDUpperConfidenceBoundGenerator`; ``added_time`` (default 1) and ``forgetting_time`` (default
    ``None``: keep every reading) are in readings.
    """

    name = "time_dependent_upper_confidence_bound_readings"
    added_time: PositiveFloat = Field(1.0, description="readings from the last to the target")

    def add_data(self, new_data: pd.DataFrame) -> None:
        """Append the rows with ``time`` = their reading indices (continuing the count)."""
        start = 0 if self.data is None else len(self.data)
        rows = new_data.copy()
        rows[TIME] = np.arange(start, start + len(rows), dtype=float)
        super().add_data(rows)

    def now(self) -> float:
        """Index of the last reading told (``-1`` before any)."""
        return -1.0 if self.data is None else float(len(self.data) - 1)

    def get_training_data(self, data: pd.DataFrame) -> pd.DataFrame:
        """The readings within ``forgetting_time`` of the last one (all if ``None``)."""
        if self.forgetting_time is None:
            return copy(data)
        return data[data[TIME] > self.now() - float(self.forgetting_time)]

    def generate(self, n_candidates: int) -> list[dict]:
        """Candidates for the target time ``now() + added_time``, without waiting."""
        self.target_prediction_time = self.now() + float(self.added_time)
        return super(TimeDependentBayesianGenerator, self).generate(n_candidates)
