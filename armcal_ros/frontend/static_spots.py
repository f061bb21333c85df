"""
A camera's view that stays put while the arm moves is not the marker.

Before a camera's static scene is learnt (the sphere detector's first seconds) or where it
cannot be (a spot that flickers), a detector can lock on to a fixed bright spot - a lamp, a
polished bolt head - and every dwell then pools the same pixel.  The detector alone cannot tell
such a spot from a marker that dwells; the samples can: the arm moved between them.

A camera's point observation is dropped when it lies within :data:`STATIC_PX` of one of the
same camera's last :data:`RECENT_VIEWS` views while the arm's point moved by more than
:data:`STATIC_MOVE_M` since that one (the marker's true views in between do not hide a spot the
detector keeps coming back to).  A marker keeps its pixel over such a move only if the move
runs along the camera's ray to within a pixel's width (about 2 mm at 1.5 m for a move of
several centimetres: a chance of a few in ten thousand per pair of dwells, about 1e-3 against
the last five), while a fixed spot repeats its pooled pixel to a few hundredths.  The first
view of a spot cannot be told and stays (the adjustment's gate meets a lone one); each later
one is dropped.
"""

from collections import deque
from typing import Dict, List, Tuple

import numpy as np

#: Pixels within which a camera's pooled view counts as the same place in the image: 10 to 100
#: times a pooled detection's noise, far below the image motion of any real move.
STATIC_PX = 1.0
#: Metres the arm's point must have moved for an unmoved view to be a fixed spot: several
#: times the distance two samples are merged at (the store's same-place tolerance), so a
#: re-visited place is never mistaken for one.
STATIC_MOVE_M = 0.01
#: A camera's previous views a new one is compared with.
RECENT_VIEWS = 5


class StaticSpotFilter:
    """
    Drop point observations that stay put while the arm moves (module docstring).

    ``counts['observations_static']`` counts the dropped observations, and
    ``counts['samples_static']`` the samples left with no observation at all (dropped too).
    """

    def __init__(self):
        self._last: Dict[str, deque] = {}
        self.counts = {'observations_static': 0, 'samples_static': 0}

    def reset(self):
        """Forget the previous views (a new recording, a new session)."""
        self._last.clear()

    def filter(self, samples) -> Tuple[List, List[str]]:
        """Return (the samples kept, the cameras whose views were dropped) in order."""
        kept, dropped = [], []
        for s in samples:
            X = np.asarray(s.point_nominal, float).reshape(3)
            for cam, obs in list(s.observations.items()):
                if obs.uv.shape[0] != 1:
                    continue
                recent = self._last.setdefault(cam, deque(maxlen=RECENT_VIEWS))
                static = any(np.hypot(*(obs.uv[0] - uv)) <= STATIC_PX and
                             np.linalg.norm(X - X0) > STATIC_MOVE_M for uv, X0 in recent)
                recent.append((obs.uv[0].copy(), X))
                if static:
                    del s.observations[cam]
                    self.counts['observations_static'] += 1
                    dropped.append(cam)
            if s.observations:
                kept.append(s)
            else:
                self.counts['samples_static'] += 1
        return kept, dropped


__all__ = ['RECENT_VIEWS', 'STATIC_MOVE_M', 'STATIC_PX', 'StaticSpotFilter']
