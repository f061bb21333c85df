"""The published pose covariance (T_base_camera) against the scatter of perturbed cameras."""
import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.core.uncertainty import pose_covariance
from armcal_ros.sim.synthetic import make_problem


def test_pose_covariance_matches_monte_carlo():
    prob = make_problem(10, 1)
    cam = prob.cameras[0]
    rng = np.random.default_rng(0)
    A = rng.normal(0, 1e-3, (6, 6))
    cov = A @ A.T
    draws = rng.multivariate_normal(np.zeros(6), cov, 20000)
    out = []
    R_wc = cam.rotation.T
    for d in draws:
        c = cam.copy()
        c.apply_pose_increment(d[:3], d[3:])
        dr = Rotation.from_matrix(c.rotation.T @ R_wc.T).as_rotvec()
        out.append(np.concatenate([c.center - cam.center, dr]))
    emp = np.cov(np.array(out).T)
    ref = pose_covariance(cam, cov)
    assert np.allclose(emp, ref, atol=0.05 * np.max(np.abs(ref)))
