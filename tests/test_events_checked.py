"""Events marked checked by their producer: the estimators' input check trusts them (no host sync)
only for the batch and sensor they were marked for."""

from __future__ import annotations

import pytest
import torch

from dvsland.bench.syncs import SyncCounter
from dvsland.events import Events, EventEmulator
from dvsland.events.validate import EventDataError, checked_for_estimator


def _events(b=(0, 0, 1), x=(1, 2, 3), t=(10, 20, 5)):
    n = len(b)
    return Events(torch.tensor(b), torch.tensor(x), torch.zeros(n, dtype=torch.int64), torch.tensor(t),
                  torch.ones(n, dtype=torch.int8))


def test_a_new_or_sliced_event_list_is_unmarked():
    ev = _events().marked_checked(2, 8, 8)
    assert ev.checked == (2, 8, 8)
    assert _events().checked is None and ev[ev.b == 0].checked is None


def test_marked_events_pass_without_a_sync_only_for_their_shape():
    ev = _events().marked_checked(2, 8, 8)
    with SyncCounter() as c:
        assert checked_for_estimator(ev, 2, 8, 8) is ev
    assert c.total == 0
    with SyncCounter() as c:  # another sensor: read and checked
        checked_for_estimator(ev, 2, 16, 16)
    assert c.total > 0
    with pytest.raises(EventDataError, match="field 'x' must be in"):
        checked_for_estimator(ev, 2, 3, 8)


def test_unmarked_bad_events_are_still_refused():
    with pytest.raises(EventDataError, match="field 'b' must be in"):
        checked_for_estimator(_events(b=(0, 0, 5)), 2, 8, 8)


def test_the_emulator_marks_what_it_emits():
    emu = EventEmulator(threshold=0.1, refractory_us=0.0)
    g = torch.Generator().manual_seed(0)
    f0 = torch.rand(3, 6, 5, generator=g) + 0.1
    emu.reset(f0, 0)
    ev = emu.step(f0 * (1.5 + torch.rand(3, 6, 5, generator=g)), 100_000)
    assert len(ev) > 0 and ev.checked == (3, 5, 6)  # (B, W, H)
    assert ev.is_sorted()
    assert int(ev.x.max()) < 5 and int(ev.y.max()) < 6 and int(ev.b.max()) < 3


def test_dropping_finished_descents_keeps_the_mark():
    from dvsland.sim.step import active_events

    ev = _events().marked_checked(2, 8, 8)
    sub = active_events(ev, torch.tensor([True, False]))
    assert len(sub) == 2 and sub.checked == (2, 8, 8)
    assert active_events(_events(), torch.tensor([True, False])).checked is None
