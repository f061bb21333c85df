"""
Point-level calibration problems from a simulated arm: joint angles, true and nominal markers.

The cell simulator (:mod:`armcal_ros.sim.cell`) renders images and writes bags; this module keeps
only its geometry, for the estimator's tests and benchmarks: the same cameras ring, the same true
robot (:mod:`armcal_ros.sim.true_robot`, scenarios of :data:`armcal_ros.sim.cell.SCENARIOS` with
the same error magnitudes), configurations drawn uniformly over the joint ranges a teleoperated
arm uses, kept when the nominal marker lies in the workspace box and projects inside every image
(with a margin), and observations where the arm's links do not hide the marker.  The robot's
measurement of a point is the nominal forward kinematics, X^ = FK_nominal(q); the cameras see the
true marker plus pixel noise.  Test points for scoring are fresh true markers from fresh
configurations.
"""

from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from armcal_ros.core.adjustment import Observations
from armcal_ros.core.kinematic_prior import KinematicData
from armcal_ros.sim.cell import (build_true_robot, joint_ranges, link_occluded, load_chain,
                                 place_cameras, SimSettings)
from armcal_ros.sim.synthetic import SyntheticProblem
from armcal_ros.sim.true_robot import TrueRobot


@dataclass
class RobotProblem(SyntheticProblem):
    """A :class:`SyntheticProblem` with the arm behind it: joint readings and the Jacobian."""

    q: Optional[np.ndarray] = None
    kinematics: Optional[KinematicData] = None
    robot: Optional[TrueRobot] = None
    scenario: str = ''
    test_q: Optional[np.ndarray] = None


def make_robot_problem(scenario='geometric', n_points=300, seed=0, n_test=500,
                       pixel_sigma=0.3, settings: SimSettings = None, chain=None,
                       occlusion=True, field=None) -> RobotProblem:
    """
    Draw a point-level problem of ``scenario`` with ``n_points`` robot points.

    ``occlusion`` drops observations the arm's links hide (slower for very large N).
    ``field`` overrides the scenario's bias field, (sigma, coherence length) in metres.
    """
    s = settings or SimSettings()
    rng = np.random.default_rng(seed)
    chain = chain or load_chain(s)
    n = chain.n_joints
    lo, hi = joint_ranges(chain, s)
    wmin, wmax = np.asarray(s.workspace_min, float), np.asarray(s.workspace_max, float)
    point = np.asarray(s.marker_offset, float)
    cams = place_cameras(s, rng)
    q_sample = rng.uniform(lo, hi, (500, n))
    robot = build_true_robot(chain, scenario, rng, s, q_sample, field)

    def draw(count):
        qs: List[np.ndarray] = []
        got = 0
        while got < count:
            cand = rng.uniform(lo, hi, (max(4 * (count - got), 200), n))
            x = chain.fk(cand, point)
            ok = np.all((x >= wmin) & (x <= wmax), axis=1)
            for cam in cams:
                uv = cam.project(x)
                ok &= cam.in_front(x) & (uv[:, 0] >= s.image_margin) & \
                    (uv[:, 0] <= cam.width - 1 - s.image_margin) & \
                    (uv[:, 1] >= s.image_margin) & (uv[:, 1] <= cam.height - 1 - s.image_margin)
            good = cand[ok][:count - got]
            qs.append(good)
            got += len(good)
        return np.vstack(qs)

    q = draw(n_points)
    X = robot.marker(q)
    measured = robot.nominal_marker(q)
    ci, pi, uvs = [], [], []
    for j, c in enumerate(cams):
        uv = c.project(X)
        vis = np.ones(n_points, bool)
        if occlusion:
            vis = ~link_occluded(chain, q, measured, c.center, s.link_radius,
                                 s.occlusion_clearance)
        idx = np.flatnonzero(vis)
        ci.append(np.full(idx.size, j))
        pi.append(idx)
        uvs.append(uv[idx] + rng.normal(0.0, pixel_sigma, (idx.size, 2)))
    obs = Observations(np.concatenate(ci), np.concatenate(pi), np.vstack(uvs))
    test_q = draw(n_test)
    test = robot.marker(test_q)
    kin = KinematicData(chain.jacobian_errors(q, point), chain.error_names)
    meta = dict(n_points=n_points, seed=seed, scenario=scenario, pixel_sigma=pixel_sigma)
    return RobotProblem(cams, X, measured, measured - X, obs, test, meta, q=q, kinematics=kin,
                        robot=robot, scenario=scenario, test_q=test_q)
