"""A reading refused for its alarm severity (SeverityError) in the loop's reading rule: a failed
attempt whose value is logged as discarded; a PV that stays in alarm is named with its
severity and the count of reads; other failures mixed in give the usual ReadError."""

from __future__ import annotations

import pytest

from pigp_torch.loop.readings import ReadingJudge, plausible_reading
from pigp_torch.machine.errors import ReadError, SeverityError


def reader(script):
    """``take()`` that returns or raises the items of ``script`` in order."""
    items = iter(script)

    def take():
        item = next(items)
        if isinstance(item, BaseException):
            raise item
        return item

    return take


def test_an_invalid_reading_is_retried_and_logged():
    discarded = []
    take = reader([SeverityError("P:LOSS", 3, 0.61), 0.5])
    note = lambda r, y: discarded.append((r, y))  # noqa: E731
    y, reads = plausible_reading(take, ReadingJudge(), 2, 0.0, note)
    assert (y, reads) == (0.5, 2)
    assert discarded == [("P:LOSS read with alarm severity INVALID (value 0.61)", 0.61)]


def test_a_pv_that_stays_invalid_is_named_with_its_severity():
    discarded = []
    take = reader([SeverityError("P:LOSS", 3, 0.6 + k / 100) for k in range(3)])
    with pytest.raises(SeverityError) as err:
        plausible_reading(take, ReadingJudge(), 2, 0.0, lambda r, y: discarded.append(y))
    message = "P:LOSS read with alarm severity INVALID on 3 reads in a row (value 0.62)"
    assert str(err.value) == message
    assert err.value.pv == "P:LOSS" and err.value.severity == "INVALID"
    assert discarded == [0.6, 0.61, 0.62]
    readback = reader([SeverityError("K:RB", "MAJOR")] * 2)  # not the objective: nothing logged
    with pytest.raises(SeverityError, match="K:RB read with alarm severity MAJOR on 2 reads"):
        plausible_reading(readback, ReadingJudge(), 1, 0.0, lambda r, y: discarded.append(y))
    assert len(discarded) == 3


def test_other_failures_mixed_in_give_a_read_error():
    take = reader([SeverityError("P:LOSS", 3, 0.6), ReadError("timeout"), float("nan")])
    with pytest.raises(ReadError, match="no valid reading in 3 attempts") as err:
        plausible_reading(take, ReadingJudge(), 2, 0.0, lambda r, y: None)
    assert not isinstance(err.value, SeverityError)
