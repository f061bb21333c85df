"""
Given intrinsics: held fixed, or a Gaussian prior around them, through the adjustment.

A simulated cell (three cameras, robot points with a 1 mm correlated bias, 0.3 px image noise)
is calibrated with each camera's true intrinsics given.  Fixed: the intrinsics come back exactly
and the reported standard deviations are about zero.  Prior: a loose prior gives the estimate of
the free camera, a tight one the given values, and a wrong mean is pulled towards the data by
an amount the two information terms set.  A camera whose points are coplanar, which the DLT
refuses, is initialised by PnP when its intrinsics are given.
"""

from dataclasses import replace

import numpy as np
import pytest

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.initialisation import initialise_camera, initialise_with_intrinsics
from armcal_ros.core.intrinsics_prior import IntrinsicsPrior
from armcal_ros.core.priors import PriorSettings
from armcal_ros.sim.synthetic import make_problem


@pytest.fixture(scope='module')
def prob():
    return make_problem(60, 3)


def _solve(prob, **given):
    # Without the weak distortion prior: the limits compare the given cameras' prior alone.
    s = SolverSettings(pixel_sigma=0.3, intrinsics=given, distortion_sigma=None)
    return calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)


def test_fixed_intrinsics_come_back_exactly_with_zero_std(prob):
    given = {c.name: IntrinsicsPrior.from_camera(c) for c in prob.cameras}
    res = _solve(prob, **given)
    assert res.success, res.message
    for c in prob.cameras:
        est = res.adjustment.cameras[c.name]
        np.testing.assert_allclose(est.camera.intrinsics(), c.intrinsics(), atol=1e-4)
        np.testing.assert_allclose(est.camera.dist, c.dist, atol=1e-7)
        assert est.std['fx'] < 1e-4 and est.std['k1'] < 1e-6
        # The pose is estimated: within the bias's reach of the truth (1 mm bias, 1.5-2 m).
        assert np.linalg.norm(est.camera.center - c.center) < 0.01
        assert 'PnP' in res.init[c.name].message


def test_prior_limits_loose_tight_and_pulled(prob):
    free = _solve(prob)
    c0 = prob.cameras[0]
    est_free = free.adjustment.cameras[c0.name]
    wrong = c0.intrinsics() + np.array([6.0, -6.0, 4.0, 4.0])

    def given(sigma):
        return IntrinsicsPrior(tuple(wrong), tuple(c0.dist), (sigma,) * 4, (1e3,) * 5)
    loose = _solve(prob, **{c0.name: given(1e4)}).adjustment.cameras[c0.name]
    np.testing.assert_allclose(loose.camera.intrinsics(), est_free.camera.intrinsics(),
                               atol=0.05)
    tight = _solve(prob, **{c0.name: given(1e-4)}).adjustment.cameras[c0.name]
    np.testing.assert_allclose(tight.camera.intrinsics(), wrong, atol=0.01)
    # A prior as informative as the data: the estimate lies strictly between the two.
    sig = float(est_free.std['fx'])
    mid = _solve(prob, **{c0.name: given(sig)}).adjustment.cameras[c0.name].camera.fx
    lo, hi = sorted((est_free.camera.fx, wrong[0]))
    assert lo + 0.1 * (hi - lo) < mid < hi - 0.1 * (hi - lo)


def test_coplanar_points_need_given_intrinsics():
    prob = make_problem(40, 5)
    cam = prob.cameras[0]
    rng = np.random.default_rng(1)
    # Ten points on one plane in front of the camera (a board-like set of views).
    X = prob.true_points[:10].copy()
    X[:, 2] = X[:, 2].mean()
    uv = cam.project(X) + rng.normal(0, 0.3, (10, 2))
    refused = initialise_camera(cam.name, cam.width, cam.height, X, uv)
    assert not refused.success and 'coplanar' in refused.message
    res = initialise_with_intrinsics(cam.name, cam.width, cam.height, X, uv,
                                     IntrinsicsPrior.from_camera(cam))
    assert res.success, res.message
    assert np.linalg.norm(res.camera.center - cam.center) < 0.02


def test_bad_given_intrinsics_are_refused_naming_the_field():
    with pytest.raises(ValueError, match='intrinsics must be finite'):
        IntrinsicsPrior((800.0, -1.0, 320.0, 240.0))
    with pytest.raises(ValueError, match='sigma must be 4 finite numbers > 0'):
        IntrinsicsPrior((800.0, 800.0, 320.0, 240.0), sigma=(1.0, 1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match='intrinsics of'):
        replace(SolverSettings(), intrinsics={'cam1': (800, 800, 320, 240)}).validate()


def test_images_of_another_size_are_refused_for_the_given_values(prob):
    c0 = prob.cameras[0]
    wrong = IntrinsicsPrior(tuple(c0.intrinsics()), tuple(c0.dist), width=1280, height=720)
    res = _solve(prob, **{c0.name: wrong})
    assert res.status == 'partial' and c0.name not in res.cameras
    assert 'images are 640x480 but the given intrinsics are for 1280x720' in \
        res.init[c0.name].message
    assert sorted(res.cameras) == sorted(c.name for c in prob.cameras[1:])


def test_a_camera_with_given_intrinsics_needs_equations_for_its_pose_only(prob):
    # 5 points: 10 equations, too few for 14 free parameters, enough for a pose of 6.
    from armcal_ros.core.adjustment import adjust, Observations
    obs = prob.obs
    keep = np.ones(len(obs.camera), bool)
    keep[np.flatnonzero(obs.camera == 2)[5:]] = False
    sub = Observations(obs.camera[keep], obs.point[keep], obs.uv[keep])
    cam3 = prob.cameras[2]
    free = adjust(prob.cameras, prob.measured, sub, PriorSettings('fixed'),
                  SolverSettings(pixel_sigma=0.3))
    given = adjust(prob.cameras, prob.measured, sub, PriorSettings('fixed'),
                   SolverSettings(pixel_sigma=0.3,
                                  intrinsics={cam3.name: IntrinsicsPrior.from_camera(cam3)}))
    assert free.cameras[cam3.name].status == 'degenerate'
    assert given.cameras[cam3.name].status == 'ok', given.cameras[cam3.name].message
