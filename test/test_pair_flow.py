"""Stereo pairs between the callbacks and the worker (pair_flow.py): the newest pair is
taken, every other one is counted, and the diagnostics say so."""

from __future__ import annotations

import threading
import time

from inhand_common.health import OK, WARN, Problems
from inhand_stereo.pair_flow import NewestPair, flow_report


def test_a_busy_worker_takes_the_newest_pair_and_every_other_is_counted_as_skipped():
    slot: NewestPair[int] = NewestPair()
    taken: list[int] = []

    def worker():
        while not slot.closed:
            pair = slot.take(timeout=0.05)
            if pair is not None:
                taken.append(pair)
                time.sleep(0.03)                 # the work takes longer than the camera

    thread = threading.Thread(target=worker)
    thread.start()
    for pair in range(40):                       # 100 pairs/s
        slot.offer(pair)
        time.sleep(0.01)
    time.sleep(0.1)
    slot.close()
    thread.join(timeout=5)
    assert not thread.is_alive()
    assert slot.received == 40
    assert len(taken) + slot.skipped == 40       # none lost without a count
    assert 5 <= len(taken) < 40 and slot.skipped > 0
    assert taken == sorted(taken) and taken[-1] == 39   # the newest, and the last one too


def test_an_idle_worker_takes_every_pair_and_take_returns_none_when_nothing_comes():
    slot: NewestPair[str] = NewestPair()
    assert slot.take(timeout=0.01) is None
    for pair in ('a', 'b'):
        slot.offer(pair)
        assert slot.take(timeout=0.01) == pair
    assert (slot.received, slot.skipped) == (2, 0)
    slot.close()
    assert slot.take(timeout=1.0) is None        # closed: no wait


def test_the_report_warns_when_pairs_were_skipped_or_images_went_unpaired():
    counts = {'pairs received': 30, 'pairs processed': 20, 'pairs skipped': 10,
              'pairs refused': 0, 'images unpaired': 0}
    problems = Problems()
    message, values = flow_report(counts, {'pairs received': 15, 'pairs skipped': 5}, 1.0,
                                  problems)
    health = problems.health(message, values)
    assert health.level == WARN and '5 of 15 stereo pairs' in health.message
    assert values['pairs skipped'] == 10 and values['pairs per second'] == '15.0'
    quiet = Problems()
    message, values = flow_report(counts, {'pairs received': 15}, 1.0, quiet)
    assert quiet.health(message, values).level == OK
    assert message.startswith('15.0 pairs/s, 20 processed, 10 skipped')
    unpaired = Problems()
    flow_report(counts, {'images unpaired': 3}, 1.0, unpaired)
    assert 'no partner' in unpaired.health('', {}).message
