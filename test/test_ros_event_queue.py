"""The node's event queue: bounded lanes that drop their oldest or thin, one worker in order."""
import threading

import numpy as np

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


def test_a_thinned_lane_keeps_every_stretch_of_time_of_every_stream():
    """
    A worker starved for three seconds in four keeps frames of every second of the input.

    Two 15 Hz cameras and a 5 Hz one into a lane of 60 (1.7 s of them); the worker takes nothing
    for three seconds (a solve holds it up), then three events per event put.  Dropping the
    oldest loses the first second of every stall outright (as the drop-oldest lane shows); the
    thinned lane keeps frames of every camera in every second, in arrival order.
    """
    rates = {'a': 15, 'b': 15, 'c': 5}
    events = sorted((k / r, cam) for cam, r in rates.items() for k in range(r * 20))

    def run(thinned):
        q = EventQueue({'image': 60, 'joint': 100}, thinned=thinned)
        taken = []
        for t, cam in events:
            q.put('image', (cam, t), key=cam, stamp=t)
            if t % 4 >= 3:
                taken.extend(item for _, item in q.get_batch(timeout=0.0, max_items=3))
        taken.extend(item for _, item in q.get_batch(timeout=0.0, max_items=1000))
        assert q.dropped['image'] == len(events) - len(taken) > len(events) / 5
        assert [t for _, t in taken] == sorted(t for _, t in taken), 'arrival order kept'
        return {cam: np.bincount(np.array([t for c, t in taken if c == cam]).astype(int),
                                 minlength=20) for cam in rates}

    for cam, per_second in run(()).items():
        assert per_second.min() == 0, (cam, per_second)
    for cam, per_second in run(('image',)).items():
        assert per_second.min() >= min(rates[cam], 5), (cam, per_second)


def test_a_lane_with_streams_too_short_to_thin_drops_its_oldest():
    q = EventQueue({'image': 3}, thinned=('image',))
    for i, cam in enumerate('xyzw'):
        q.put('image', i, key=cam)
    assert [i for _, i in q.get_batch(timeout=0.0)] == [1, 2, 3]
    with pytest.raises(ValueError, match='thinned'):
        EventQueue({'image': 2}, thinned=('image',))
    with pytest.raises(ValueError, match='thinned'):
        EventQueue({'image': 5}, thinned=('joint',))


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
