"""The node's event queue: bounded lanes that drop their oldest, one worker woken in order."""
import threading

import pytest

from armcal_ros.ros.event_queue import EventQueue

pytestmark = pytest.mark.timeout(60)


def test_event_queue_keeps_order_and_drops_oldest_per_lane():
    q = EventQueue({'joint': 5, 'image': 2, 'control': None})
    assert q.put('joint', 'j0') and q.put('image', 'i0') and q.put('joint', 'j1')
    assert q.put('image', 'i1')
    assert not q.put('image', 'i2'), 'the image lane is full: i0 is pushed out'
    q.put('control', 'c0')
    assert q.dropped['image'] == 1 and q.dropped['joint'] == 0
    assert q.depth() == {'joint': 2, 'image': 2, 'control': 1}
    got = q.get_batch(timeout=0.1)
    assert [item for _, item in got] == ['j0', 'j1', 'i1', 'i2', 'c0']
    assert q.get_batch(timeout=0.01) == []
    with pytest.raises(ValueError, match='kind'):
        q.put('bogus', 1)
    with pytest.raises(ValueError, match='bounds'):
        EventQueue({'joint': 0})


def test_event_queue_wakes_the_worker_and_closes():
    q = EventQueue({'joint': 10})
    got = []

    def worker():
        while True:
            batch = q.get_batch(timeout=5.0)
            if not batch and q.closed:
                return
            got.extend(batch)
    t = threading.Thread(target=worker)
    t.start()
    for i in range(5):
        q.put('joint', i)
    q.close()
    t.join(5.0)
    assert not t.is_alive() and [i for _, i in got] == list(range(5))
    assert not q.put('joint', 99)
