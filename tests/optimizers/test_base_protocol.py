"""The shared defaults of the ask/tell protocol: ``recommend`` and ``tracked``."""

from __future__ import annotations

import pytest
import torch

from pigp_torch.optimizers.base import AskTellOptimizer

BOUNDS = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)


@pytest.mark.parametrize(("maximize", "expected"), [(True, [0.5, 0.0]), (False, [-0.5, 0.25])])
def test_recommend_defaults_to_the_best_reading(maximize, expected):
    opt = AskTellOptimizer(BOUNDS, maximize=maximize)
    opt.tell([0.0, 0.0], 1.0)
    opt.tell([0.5, 0.0], 3.0)
    opt.tell([-0.5, 0.25], -2.0)
    x = opt.recommend()
    assert x.dtype == torch.float64 and x.shape == (2,)
    assert x.tolist() == expected
    x[0] = 9.0  # a copy: changing it leaves the history alone
    assert opt.recommend().tolist() == expected


def test_recommend_before_any_tell_is_refused():
    with pytest.raises(RuntimeError, match="no measurements yet"):
        AskTellOptimizer(BOUNDS).recommend()


def test_tracked_defaults_to_nothing():
    opt = AskTellOptimizer(BOUNDS)
    assert opt.tracked() == {}
    opt.tell([0.0, 0.0], 1.0)
    assert opt.tracked() == {}
