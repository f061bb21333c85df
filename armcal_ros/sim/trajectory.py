"""
Teleoperation-like joint trajectories: minimum-jerk moves between targets, with dwells.

An operator jogs the arm to a place, holds it there for a moment, and moves on.  Each move from
q_a to q_b over T seconds follows the minimum-jerk profile (Flash and Hogan, 1985)::

    q(t) = q_a + (q_b - q_a) s(t / T),   s(x) = 10 x^3 - 15 x^4 + 6 x^5

whose velocity and acceleration are zero at both ends, so the arm comes to rest smoothly.
Its peak speed is 1.875 |q_b - q_a| / T; T is chosen so that no joint exceeds its speed limit,
then stretched by a random factor (operators are not time-optimal).  Dwells of random length
follow every move.
"""

from dataclasses import dataclass

import numpy as np


def min_jerk(x):
    """Minimum-jerk profile s(x) and its derivative ds/dx for x in [0, 1] (clipped)."""
    x = np.clip(x, 0.0, 1.0)
    s = x ** 3 * (10.0 + x * (-15.0 + 6.0 * x))
    ds = 30.0 * x ** 2 * (1.0 - x) ** 2
    return s, ds


@dataclass
class Trajectory:
    """
    Piecewise trajectory of moves and dwells.

    Segment k runs from ``times[k]`` to ``times[k+1]`` (seconds) and goes
    from ``knots[k]`` to ``knots[k+1]`` (joint vectors) by minimum jerk if ``moving[k]``, else
    it is a dwell (``knots[k] == knots[k+1]``).
    """

    times: np.ndarray
    knots: np.ndarray
    moving: np.ndarray

    @property
    def duration(self):
        """End time of the last segment."""
        return float(self.times[-1])

    def _locate(self, t):
        t = np.asarray(t, float).reshape(-1)
        k = np.clip(np.searchsorted(self.times, t, side='right') - 1, 0, len(self.moving) - 1)
        T = self.times[k + 1] - self.times[k]
        x = (t - self.times[k]) / T
        return k, x, T

    def positions(self, t):
        """Evaluate q(t): an (M, n) array for times t (M,) in seconds."""
        k, x, _ = self._locate(t)
        s, _ = min_jerk(x)
        return self.knots[k] + (self.knots[k + 1] - self.knots[k]) * s[:, None]

    def velocities(self, t):
        """Evaluate dq/dt: an (M, n) array for times t (M,) in seconds."""
        k, x, T = self._locate(t)
        _, ds = min_jerk(x)
        inside = (x >= 0.0) & (x <= 1.0)
        return (self.knots[k + 1] - self.knots[k]) * (ds * inside / T)[:, None]

    def dwells(self):
        """(D, 2) start and end times of the dwell segments."""
        idx = np.flatnonzero(~self.moving)
        return np.column_stack([self.times[idx], self.times[idx + 1]])

    def dwell_knots(self):
        """(D, n) joint positions held during each dwell."""
        return self.knots[np.flatnonzero(~self.moving)]


def teleop_trajectory(sample_target, q_start, duration, rng, speed_limits, dwell=(0.4, 2.0),
                      min_move_time=0.5, slowdown=(1.0, 1.6)):
    """
    Generate a trajectory of at least ``duration`` seconds starting with a dwell at ``q_start``.

    ``sample_target(rng, q_current) -> q`` proposes the next target (the caller decides what is
    reachable and visible); ``speed_limits`` (n,) rad/s bound each joint's peak speed.
    """
    q = np.asarray(q_start, float)
    speed_limits = np.asarray(speed_limits, float)
    times, knots, moving = [0.0], [q], []
    t = 0.0
    while True:
        t += rng.uniform(*dwell)
        times.append(t)
        knots.append(q)
        moving.append(False)
        if t >= duration:
            break
        q_next = np.asarray(sample_target(rng, q), float)
        T = max(min_move_time, float(np.max(1.875 * np.abs(q_next - q) / speed_limits)))
        t += T * rng.uniform(*slowdown)
        times.append(t)
        knots.append(q_next)
        moving.append(True)
        q = q_next
    return Trajectory(np.array(times), np.array(knots), np.array(moving, bool))
