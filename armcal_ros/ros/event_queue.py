"""
A bounded, ordered queue between the ROS callbacks and the front-end worker.

The callbacks only append; one worker thread takes events out in arrival order.  Each kind of
event has its own lane and bound, so that a burst of images (large, costly to process) can only
push out older *images*: joint states (tiny, and needed to pair every image) are dropped only if
their own, much larger, bound is exceeded.  A global sequence number keeps the order between
lanes, which the time pairing relies on (a joint state must not overtake the images it brackets
any more than it would on the wire).  Nothing here imports ROS.

A full lane drops its oldest event, or, for a *thinned* lane (the images), the event whose
neighbours of the same stream are closest in time.  Dropping the oldest loses a contiguous
stretch: a worker starved for two seconds by a solve loses every frame of the dwells in that
stretch, and a worker slower than the input loses most dwells outright.  Thinning spreads the
loss evenly over the time the lane covers, so every dwell keeps frames at a lower rate (the
pooled centre's spread grows as 1/sqrt of the frames kept, and says so) while the memory
stays bounded.  Each stream (a camera) gives up frames in proportion to its share of the lane.
"""

import collections
import itertools
import threading
import time
from typing import Dict, Iterable, List, Optional, Tuple


class EventQueue:
    """
    FIFO of ``(kind, item)`` events with one bounded lane per kind.

    ``bounds`` maps each kind to its maximum length (``None``: unbounded, for rare control
    events).  :meth:`put` never blocks: when a lane is full one event is dropped and counted in
    ``dropped[kind]``: the oldest, or, in a lane named in ``thinned``, an interior event of the
    stream (``key``) holding most of the lane, the one whose removal leaves the smallest gap
    between its neighbours' ``stamp`` values.  :meth:`get_batch` returns events of all lanes
    merged back into arrival order.
    """

    def __init__(self, bounds: Dict[str, Optional[int]], thinned: Iterable[str] = ()):
        if not bounds:
            raise ValueError('bounds must name at least one kind of event')
        for kind, bound in bounds.items():
            if bound is not None and (int(bound) != bound or bound < 1):
                raise ValueError(f'bounds[{kind!r}] must be a positive integer or None, '
                                 f'got {bound!r}')
        self.thinned = frozenset(thinned)
        for kind in self.thinned:
            if kind not in bounds or bounds[kind] is None or bounds[kind] < 3:
                raise ValueError(f'thinned names {kind!r}: a thinned lane must be one of '
                                 f'bounds with a bound of at least 3')
        self.bounds = dict(bounds)
        self._lanes = {k: collections.deque() for k in bounds}
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = collections.Counter()
        self.accepted = collections.Counter()

    def put(self, kind, item, key=None, stamp=None) -> bool:
        """
        Append an event; return False if it pushed out an older one (or the queue is closed).

        ``key`` names the event's stream and ``stamp`` its time (any increasing number; the
        arrival order when None), used only by a thinned lane.
        """
        lane = self._lanes.get(kind)
        if lane is None:
            raise ValueError(f'kind must be one of {list(self._lanes)}, got {kind!r}')
        with self._cond:
            if self._closed:
                return False
            bound = self.bounds[kind]
            lost = bound is not None and len(lane) >= bound
            seq = next(self._seq)
            if lost:
                if kind in self.thinned:
                    _thin(lane)
                else:
                    lane.popleft()
                self.dropped[kind] += 1
            lane.append((seq, item, key, seq if stamp is None else stamp))
            self.accepted[kind] += 1
            self._cond.notify()
        return not lost

    def get_batch(self, timeout=None, max_items=256) -> List[Tuple[str, object]]:
        """
        Return up to ``max_items`` events in arrival order.

        Waits up to ``timeout`` seconds (``None``: forever) for the first one; returns an empty
        list on timeout or once the queue is closed and empty.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._closed and not any(self._lanes.values()):
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return []
                self._cond.wait(remaining)
            out = []
            while len(out) < max_items:
                heads = [(lane[0][0], kind) for kind, lane in self._lanes.items() if lane]
                if not heads:
                    break
                _, kind = min(heads)
                out.append((kind, self._lanes[kind].popleft()[1]))
            return out

    def __len__(self):
        with self._cond:
            return sum(len(lane) for lane in self._lanes.values())

    def depth(self) -> Dict[str, int]:
        """Return the number of waiting events per kind."""
        with self._cond:
            return {k: len(lane) for k, lane in self._lanes.items()}

    @property
    def closed(self):
        """Return True once :meth:`close` was called."""
        return self._closed

    def close(self):
        """Wake the worker and refuse further events (what is queued can still be taken)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


def _thin(lane):
    """
    Drop the event of ``lane`` whose loss spreads its stream's events most evenly.

    The stream is the ``key`` with most events in the lane; of its interior events (never its
    first or last) the one with the smallest gap between its neighbours' stamps goes.  Done
    repeatedly this keeps the stream's events about evenly spaced over the time the lane covers.
    A stream with fewer than three events cannot be thinned: the oldest event goes.
    """
    streams = collections.Counter(e[2] for e in lane)
    key, n = streams.most_common(1)[0]
    if n < 3:
        lane.popleft()
        return
    idx = [i for i, e in enumerate(lane) if e[2] == key]
    t = [lane[i][3] for i in idx]
    j = min(range(1, n - 1), key=lambda j: t[j + 1] - t[j - 1])
    del lane[idx[j]]
