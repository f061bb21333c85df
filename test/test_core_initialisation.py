"""DLT initialisation: exact cameras from noise-free points, clear refusals when degenerate."""
import numpy as np

from armcal_ros.core.camera import Camera
from armcal_ros.core.initialisation import decompose, dlt, initialise_camera
from armcal_ros.sim.synthetic import make_problem


def _undistorted(cam):
    c = cam.copy()
    c.dist = np.zeros(5)
    return c


def test_dlt_recovers_exact_camera_from_noise_free_points():
    rng = np.random.default_rng(0)
    for seed in range(3):
        prob = make_problem(60, seed, bias_sigma=0.0, pixel_sigma=0.0)
        for cam in prob.cameras:
            cam = _undistorted(cam)
            X = prob.true_points[cam.in_front(prob.true_points)]
            uv = cam.project(X)
            K, R, t = decompose(dlt(X, uv))
            assert np.allclose(K, cam.K, rtol=1e-7, atol=1e-6)
            assert np.allclose(R, cam.rotation, atol=1e-9)
            assert np.allclose(t, cam.translation, atol=1e-9)
            res = initialise_camera(cam.name, 640, 480, X, uv, rng=rng)
            assert res.success, res.message
            assert np.allclose(res.camera.center, cam.center, atol=1e-9)


def test_ransac_survives_gross_outliers():
    prob = make_problem(200, 4, bias_sigma=0.0, pixel_sigma=0.3)
    cam = prob.cameras[0]
    X = prob.true_points
    uv = cam.project(X) + np.random.default_rng(1).normal(0, 0.3, (len(X), 2))
    uv[::10] += 80.0
    res = initialise_camera(cam.name, 640, 480, X, uv)
    assert res.success, res.message
    assert not res.inliers[::10].any()
    assert np.linalg.norm(res.camera.center - cam.center) < 0.05


def test_too_few_and_coplanar_points_are_refused_with_a_reason():
    cam = Camera.look_at('c', 640, 480, 800, 800, 320, 240, np.zeros(5), [1.5, 0, 1], [0, 0, 0])
    rng = np.random.default_rng(2)
    X = rng.uniform(-0.3, 0.3, (5, 3))
    res = initialise_camera('c', 640, 480, X, cam.project(X))
    assert not res.success and res.status == 'insufficient_points' and '5 points' in res.message
    X = rng.uniform(-0.3, 0.3, (50, 3))
    X[:, 2] = 0.1
    res = initialise_camera('c', 640, 480, X, cam.project(X))
    assert not res.success and res.status == 'degenerate' and 'coplanar' in res.message
