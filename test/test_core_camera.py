"""Camera model: projection equals cv2.projectPoints; Jacobians equal finite differences."""
import cv2
import numpy as np
import pytest

from armcal_ros.core.camera import Camera, project, project_with_jacobians, undistort_normalized


def _camera(rng):
    return Camera.look_at('cam', 640, 480, 800 + rng.normal(0, 20), 805 + rng.normal(0, 20),
                          320 + rng.normal(0, 5), 240 + rng.normal(0, 5),
                          [-0.15, 0.05, 1e-3, -2e-3, 0.01], eye=[1.6, 0.4, 1.0],
                          target=[0.5, 0.0, 0.4])


def _points(rng, n=40):
    return np.array([0.5, 0.0, 0.4]) + rng.uniform(-0.3, 0.3, (n, 3))


def test_projection_matches_opencv():
    rng = np.random.default_rng(0)
    for _ in range(5):
        cam = _camera(rng)
        X = _points(rng, 200)
        ref, _ = cv2.projectPoints(X, cam.rvec, cam.translation, cam.K, cam.dist)
        assert np.max(np.abs(cam.project(X) - ref.reshape(-1, 2))) < 1e-9


def _rel_err(a, b):
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12)


def test_jacobians_match_central_differences():
    rng = np.random.default_rng(1)
    cam = _camera(rng)
    X = _points(rng)
    intr, dist, R, t = cam.intrinsics(), cam.dist, cam.rotation, cam.translation
    J = project_with_jacobians(intr, dist, R, t, X)
    assert np.allclose(J.uv, cam.project(X), atol=1e-12)

    def fd(f, x0, h):
        cols = []
        for k in range(len(x0)):
            e = np.zeros_like(x0)
            e[k] = h[k]
            cols.append((f(x0 + e) - f(x0 - e)) / (2 * h[k]))
        return np.stack(cols, axis=-1)

    num = fd(lambda p: project(p, dist, R, t, X), intr, np.full(4, 1e-3))
    assert _rel_err(J.d_intr, num) < 1e-6
    num = fd(lambda d: project(intr, d, R, t, X), dist, np.full(5, 1e-6))
    assert _rel_err(J.d_dist, num) < 1e-6

    def pose(v):
        c = cam.copy()
        c.apply_pose_increment(v[:3], v[3:])
        return c.project(X)
    num = fd(pose, np.zeros(6), np.full(6, 1e-6))
    assert _rel_err(J.d_pose, num) < 1e-6
    cols = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        cols.append((project(intr, dist, R, t, X + e) - project(intr, dist, R, t, X - e)) / 2e-6)
    assert _rel_err(J.d_point, np.stack(cols, axis=-1)) < 1e-6


def test_undistort_inverts_distortion():
    rng = np.random.default_rng(2)
    cam = _camera(rng)
    X = _points(rng)
    xc = cam.to_camera(X)
    rays = undistort_normalized(cam, cam.project(X))
    assert np.max(np.abs(rays - xc[:, :2] / xc[:, 2:])) < 1e-9


def test_pose_round_trip_and_validation():
    rng = np.random.default_rng(3)
    cam = _camera(rng)
    t, q = cam.pose_in_world()
    back = Camera.from_pose_in_world('cam', 640, 480, cam.K, cam.dist, t, q)
    assert np.allclose(back.rotation, cam.rotation) and np.allclose(back.translation,
                                                                    cam.translation)
    with pytest.raises(ValueError, match='dist'):
        Camera('c', 640, 480, 1, 1, 0, 0, dist=[0, 0, 0])
    with pytest.raises(ValueError, match=r'\(N, 3\)'):
        cam.project(np.zeros((4, 2)))
