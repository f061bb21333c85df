"""
The base-motion gauge: error directions that only move the whole arm rigidly, and the rest.

PUMA 560 of the simulator; U is built from configurations over the URDF limits and checked on
fresh ones.  Errors in U must change every marker position by one rigid motion, so moving the
cameras by the inverse motion reproduces the images exactly (the data are identical); the
canonical (observable) part must not depend on which member of the class the truth was.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.core.camera import Camera
from armcal_ros.core.evaluation import similarity_fit
from armcal_ros.core.kinematic_prior import (base_motion_gauge, kinematic_sigmas,
                                             rigid_motion_jacobian)
from armcal_ros.sim.cameras import ring_of_cameras
from armcal_ros.sim.cell import load_chain, SimSettings

DEG = np.pi / 180.0


@pytest.fixture(scope='module')
def arm():
    s = SimSettings()
    chain = load_chain(s)
    point = np.asarray(s.marker_offset, float)
    q = chain.sample_configurations(300, np.random.default_rng(0))
    sigma = kinematic_sigmas(chain.error_names)
    gauge = base_motion_gauge(chain.jacobian_errors(q, point), chain.fk(q, point), sigma)
    fresh = chain.sample_configurations(200, np.random.default_rng(1))
    return chain, point, gauge, fresh


def _rigid_residual(a, b):
    """RMS residual (m) of the best rigid fit of a onto b, and the fit."""
    fit = similarity_fit(a, b, with_scale=False)
    return float(np.sqrt(np.mean(np.sum((fit.apply(a) - b) ** 2, axis=1)))), fit


def _draw(gauge, rng, in_u):
    """Error vector of about the simulator's size, inside U or with its U part removed."""
    z = gauge.basis @ rng.standard_normal(gauge.basis.shape[1]) if in_u else \
        rng.standard_normal(gauge.sigma.size)
    e = 0.5 * gauge.sigma * z
    return e if in_u else gauge.canonical(e)


def test_rigid_motion_jacobian_matches_a_small_motion():
    x = np.random.default_rng(2).normal(size=(5, 3))
    v = np.array([1e-6, -2e-6, 3e-6, 1e-5, 2e-5, -1e-5])
    moved = Rotation.from_rotvec(v[:3]).apply(x) + v[3:]
    np.testing.assert_allclose(moved - x, rigid_motion_jacobian(x) @ v, atol=1e-10)


def test_errors_in_u_move_every_marker_by_one_rigid_motion(arm):
    chain, point, gauge, fresh = arm
    x0 = chain.fk(fresh, point)
    rng = np.random.default_rng(3)
    for _ in range(3):
        u = _draw(gauge, rng, in_u=True)
        xu = chain.fk(fresh, point, u)
        shift = np.sqrt(np.mean(np.sum((xu - x0) ** 2, axis=1)))
        res, _ = _rigid_residual(x0, xu)
        assert shift > 1e-4                   # a real, sub-millimetre-sized motion ...
        assert res < 2e-6                     # ... that is rigid to second order in |u|


def test_cameras_moved_by_the_inverse_motion_see_identical_images(arm):
    chain, point, gauge, fresh = arm
    u = _draw(gauge, np.random.default_rng(4), in_u=True)
    x0 = chain.fk(fresh, point)
    xu = chain.fk(fresh, point, u)
    _, fit = _rigid_residual(x0, xu)          # xu = R x0 + t
    for cam in ring_of_cameras(3, x0.mean(axis=0), np.random.default_rng(5)):
        moved = Camera(cam.name, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                       cam.dist, cam.rotation @ fit.rotation.T,
                       cam.translation - cam.rotation @ fit.rotation.T @ fit.translation)
        ok = cam.in_front(x0)
        diff = moved.project(xu[ok]) - cam.project(x0[ok])
        assert np.max(np.abs(diff)) < 2e-3    # pixels: identical data up to the base frame


def test_observable_part_is_unchanged_and_is_not_a_rigid_motion(arm):
    chain, point, gauge, fresh = arm
    rng = np.random.default_rng(6)
    e = 0.5 * gauge.sigma * rng.standard_normal(gauge.sigma.size)
    u = _draw(gauge, rng, in_u=True)
    c = gauge.canonical(e)
    np.testing.assert_allclose(gauge.canonical(e + u), c, atol=1e-12)
    np.testing.assert_allclose(gauge.canonical(c), c, atol=1e-12)
    # minimum prior norm: what is removed is prior-orthogonal to what is kept
    assert abs(np.dot(c / gauge.sigma, gauge.unobservable_part(e) / gauge.sigma)) < 1e-9
    # the canonical truth differs from the raw one by one rigid motion only ...
    res, _ = _rigid_residual(chain.fk(fresh, point, e), chain.fk(fresh, point, c))
    assert res < 2e-6
    # ... while the observable part itself is not a rigid motion
    obs = _draw(gauge, rng, in_u=False)
    res, _ = _rigid_residual(chain.fk(fresh, point), chain.fk(fresh, point, obs))
    assert res > 2e-5


def test_base_joint_errors_lie_in_u_and_a_link_length_does_not(arm):
    chain, _, gauge, _ = arm
    names = chain.error_names
    for k, name in enumerate(names):
        e = np.zeros(len(names))
        e[k] = gauge.sigma[k]
        kept = np.linalg.norm(gauge.canonical(e) / gauge.sigma)
        if name.startswith('joint_1/'):
            assert kept < 1e-9, name          # the mount: wholly a rigid motion
        if name in ('joint_3/tx', 'tip/tx'):
            assert kept > 0.99, name          # a link length, the marker mount: observable
    assert 6 <= gauge.basis.shape[1] < len(names)
    assert gauge.n_observable + gauge.basis.shape[1] == len(names)


def test_gauge_validates_its_arguments():
    J = np.zeros((4, 3, 2))
    with pytest.raises(ValueError, match='points'):
        base_motion_gauge(J, np.zeros((3, 3)), np.ones(2))
    with pytest.raises(ValueError, match='sigma'):
        base_motion_gauge(J, np.zeros((4, 3)), np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match='jacobian'):
        base_motion_gauge(np.zeros((4, 2)), np.zeros((4, 3)), np.ones(2))


def test_sample_configurations_cover_the_urdf_limits(arm):
    chain = arm[0]
    q = chain.sample_configurations(2000, np.random.default_rng(7))
    assert q.shape == (2000, chain.n_joints)
    assert np.all(q >= chain.lower) and np.all(q <= chain.upper)
    span = (q.max(axis=0) - q.min(axis=0)) / (chain.upper - chain.lower)
    assert np.all(span > 0.95)
    with pytest.raises(ValueError, match='m must be'):
        chain.sample_configurations(0)
