"""The bounded keep-newest queue between live stages (livebridge.capture.queue)."""

from __future__ import annotations

import threading

from livebridge.capture.queue import NewestQueue


def test_newest_queue_keeps_the_newest_and_never_blocks():
    q = NewestQueue(2)
    for k in range(10):
        q.put(k)
    assert (q.get(0), q.get(0), q.get(0)) == (8, 9, None) and q.dropped == 8


def test_put_waiting_waits_for_room_and_drops_nothing():
    q = NewestQueue(1)
    q.put("first")
    taken = []
    consumer = threading.Timer(0.1, lambda: taken.append(q.get(0)))
    consumer.start()
    assert q.put_waiting("second", lambda: True, poll_s=0.01)
    consumer.join()
    assert taken == ["first"] and q.get(0) == "second" and q.dropped == 0


def test_put_waiting_gives_up_when_told_and_keeps_what_is_queued():
    q = NewestQueue(1)
    q.put("first")
    asked = []

    def keep_waiting():
        asked.append(True)
        return len(asked) < 3

    assert not q.put_waiting("second", keep_waiting, poll_s=0.01)
    assert q.get(0) == "first" and q.get(0) is None and q.dropped == 0
