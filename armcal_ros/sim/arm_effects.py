"""
What a real arm does that its joint readings do not show: backlash, repeatability, settling.

All three move the marker away from where the joint states say it is, by amounts a calibration
cannot model per pose (they change from one stop to the next), so they act as noise on the
arm's points; the simulator adds them to the truth only (the published joint states stay the
motor-side readings).  Each is off at zero.

- **Backlash** (``backlash_deg``, total play per joint): the link lags the motor by half the play
  in the direction of the last motion, q_link = q_motor - b / 2 sign(last move).  Within a move
  the sign is the move's; during a dwell, the move's that ended in it (a joint that did not
  move keeps the sign of its own last move).  Typical harmonic-drive arms: 0.005-0.02 deg.
- **Repeatability** (``repeatability_mm``, per axis): each stop ends a little off the commanded
  place, N(0, s^2 I) in Cartesian space, from the move into the stop until the next move ends
  (ISO 9283 figures of 0.02-0.1 mm for industrial arms).
- **Settling** (``settle_mm`` at ``settle_hz``, decaying with ``settle_tau``): the structure
  rings down after each stop, a e^(-t / tau) sin(2 pi f t) along a random direction per stop,
  t from the start of the dwell (5-15 Hz, 0.05-0.2 mm for light arms; the joint encoders do
  not see it).

The random draws come from their own stream (``seed``), so a simulation's other draws are the
same with the effects on or off.
"""

from dataclasses import dataclass

import numpy as np


@dataclass
class ArmEffects:
    """The effects of one session; see the module docstring for the model of each."""

    backlash_rad: float
    dwell_start: np.ndarray          # (D,) s, start of each dwell segment
    direction: np.ndarray            # (K, n) sign of the last motion per segment and joint
    segment_times: np.ndarray        # (K + 1,) s, the trajectory's segment boundaries
    stop_of_segment: np.ndarray      # (K,) which stop (dwell index) a segment belongs to
    repeat_offset: np.ndarray        # (D, 3) m
    settle_direction: np.ndarray     # (D, 3) unit
    settle_m: float
    settle_hz: float
    settle_tau: float

    def _segment(self, t):
        t = np.asarray(t, float).reshape(-1)
        k = np.searchsorted(self.segment_times, t, side='right') - 1
        return np.clip(k, 0, len(self.direction) - 1)

    def link_joints(self, q, t):
        """Return the links' true angles (M, n) for the motor readings ``q`` at times ``t``."""
        if self.backlash_rad == 0.0:
            return q
        return q - 0.5 * self.backlash_rad * self.direction[self._segment(t)]

    def resting_offset(self, t):
        """Return where the stop in force at times ``t`` rests off its command (M, 3), m."""
        return self.repeat_offset[self.stop_of_segment[self._segment(t)]]

    def displacement(self, t):
        """Return how far (m) the marker is off its commanded place at times ``t``: (M, 3)."""
        k = self._segment(t)
        d = self.stop_of_segment[k]
        out = self.repeat_offset[d].copy()
        if self.settle_m > 0.0:
            dt = np.asarray(t, float).reshape(-1) - self.dwell_start[d]
            ring = np.where(dt >= 0.0, self.settle_m * np.exp(-np.maximum(dt, 0.0) /
                                                              self.settle_tau)
                            * np.sin(2.0 * np.pi * self.settle_hz * dt), 0.0)
            out += ring[:, None] * self.settle_direction[d]
        return out


def arm_effects(traj, backlash_deg=0.0, repeatability_mm=0.0, settle_mm=0.0, settle_hz=10.0,
                settle_tau=0.1, seed=0):
    """
    Return the :class:`ArmEffects` of trajectory ``traj``, or None when every effect is off.

    ``traj`` a :class:`~armcal_ros.sim.trajectory.Trajectory`; the amounts as in the module
    docstring (degrees, millimetres, hertz, seconds).
    """
    for name, v in (('backlash_deg', backlash_deg), ('repeatability_mm', repeatability_mm),
                    ('settle_mm', settle_mm)):
        if not (np.isfinite(v) and v >= 0.0):
            raise ValueError(f'{name} must be finite and >= 0, got {v}')
    if not (settle_hz > 0 and settle_tau > 0):
        raise ValueError(f'settle_hz and settle_tau must be > 0, got {settle_hz}, {settle_tau}')
    if backlash_deg == 0.0 and repeatability_mm == 0.0 and settle_mm == 0.0:
        return None
    rng = np.random.default_rng([int(seed), 4411])
    moving = np.asarray(traj.moving, bool)
    step = np.sign(np.diff(traj.knots, axis=0))           # (K, n), zero in dwells
    direction = np.zeros_like(step)
    last = np.zeros(step.shape[1])
    for k in range(len(step)):
        last = np.where(step[k] != 0.0, step[k], last)
        direction[k] = last
    dwell_idx = np.flatnonzero(~moving)
    # A segment belongs to the stop it leads into (a move) or is (a dwell); after the last
    # dwell, to the last one.
    stop = np.searchsorted(dwell_idx, np.arange(len(moving)), side='left')
    stop = np.clip(stop, 0, max(len(dwell_idx) - 1, 0))
    D = max(len(dwell_idx), 1)
    u = rng.normal(size=(D, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return ArmEffects(np.radians(backlash_deg),
                      traj.times[dwell_idx] if len(dwell_idx) else np.zeros(1),
                      direction, np.asarray(traj.times, float), stop,
                      rng.normal(0.0, 1e-3 * repeatability_mm, (D, 3)), u,
                      1e-3 * settle_mm, float(settle_hz), float(settle_tau))


__all__ = ['ArmEffects', 'arm_effects']
