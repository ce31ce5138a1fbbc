"""The one renderer of the events not estimated (core.windows.describe_events): the end-of-run
EventsDroppedWarning and the summary line of ``cmax-taichi estimate`` say the same counts by reason."""

from __future__ import annotations

import json

from cmax_taichi.core.windows import (
    PARTIAL_TAIL,
    TOO_FEW_EVENTS,
    EventLedger,
    Span,
    describe_events,
    min_tail_events,
)


def _ledger() -> EventLedger:
    """Two windows of 10 events (one with 2 off the sensor), one of a single event, a partial tail of 3."""
    ledger = EventLedger(24)
    inside = [True] * 8 + [False] * 2
    ledger.add(Span(0, 0, 10), "estimated", inside=inside)
    ledger.add(Span(1, 10, 20), "estimated")
    ledger.add(Span(2, 20, 21), TOO_FEW_EVENTS)
    ledger.add(Span(3, 21, 24, tail=True, keep=False), PARTIAL_TAIL)
    ledger.finish()
    return ledger


def test_the_ledger_and_its_saved_counts_render_alike():
    ledger = _ledger()
    text = describe_events(ledger.as_dict(), n_events=10)
    assert text == ledger.describe(10)
    least = min_tail_events(10)
    assert text == (
        f"3 in the partial last window (shorter than the {least} that keep_tail=True / --keep-tail keeps), "
        "2 outside the sensor, 1 in 1 window(s) of fewer than 2 events"
    )
    # the counts as a results.json holds them (SequenceResult.events) say the same
    assert describe_events(json.loads(json.dumps(ledger.as_dict())), n_events=10) == text


def test_missing_categories_count_zero():
    assert describe_events({"total": 5, "estimated": 5}) == ""
    assert describe_events({"total": 5, "estimated": 3, "after_max_windows": 2}, max_windows=1) == (
        "2 after the last window of max_windows=1"
    )
