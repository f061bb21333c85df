"""
Leverages and redundancy of the adjustment: each camera's degrees of freedom left in its residuals.

The Schur-complement formulas of ``_Problem.leverages`` are checked against the whole normal
matrix assembled densely and inverted (independent prior, exact correlated prior, and a global
prior: the kinematic model), and against the parameter count where it is exact (points known).
"""

import numpy as np
import pytest

from armcal_ros.core import adjustment as adj
from armcal_ros.core.adjustment import adjust, SolverSettings
from armcal_ros.core.camera import project_with_jacobians
from armcal_ros.core.intrinsics_prior import IntrinsicsPrior
from armcal_ros.core.priors import PointPrior, PriorSettings
from armcal_ros.sim.robot_points import make_robot_problem

SETTINGS = SolverSettings(pixel_sigma=0.3, max_gate_rounds=0, gate_min_px=1e9,
                          distortion_sigma=None)


@pytest.fixture(scope='module')
def prob():
    return make_robot_problem('geometric', 25, 4, pixel_sigma=0.3, n_test=10)


def _dense_leverages(problem, res):
    """h_k from the whole normal matrix N = [[U, W], [W^T, V]], inverted densely."""
    cams = [e.camera for e in res.cameras.values()]
    U, _, Wt, Vb, _, _ = problem.normal_equations(cams, res.points)
    C, n = problem.layout.size, problem.n
    V = np.zeros((3 * n, 3 * n))
    for i in range(n):
        V[3 * i:3 * i + 3, 3 * i:3 * i + 3] = Vb[i]
    V += (np.kron(np.eye(n), np.eye(3)) / problem.prior.settings.point_sigma ** 2
          if problem.prior.kind == 'block' else problem.P_dense)
    Wm = Wt.reshape(3 * n, C).T                    # W (C, 3n) from its per-point transposes
    N = np.block([[U, Wm], [Wm.T, V]])
    Sigma = np.linalg.inv(N)
    pc = problem.layout.per_camera
    h = np.zeros(len(problem.obs))
    for j, idx in enumerate(problem.by_camera):
        c = cams[j]
        for k in idx:
            i = problem.obs.point[k]
            J = project_with_jacobians(c.intrinsics(), c.dist, c.rotation, c.translation,
                                       res.points[i][None])
            Jk = np.zeros((2, C + 3 * n))
            Jk[:, j * pc:(j + 1) * pc] = problem.layout.camera_jacobian(J)[0]
            Jk[:, C + 3 * i:C + 3 * i + 3] = J.d_point[0]
            h[k] = np.trace(Jk @ Sigma @ Jk.T) / SETTINGS.pixel_sigma ** 2
    return h


@pytest.mark.parametrize('model', ['independent', 'correlated'])
def test_leverages_match_the_whole_normal_matrix(prob, model):
    ps = PriorSettings(model)
    res = adjust(prob.cameras, prob.measured, prob.obs, ps, SETTINGS)
    assert res.status == 'converged'
    cams = [e.camera for e in res.cameras.values()]
    problem = adj._Problem(cams, prob.measured, prob.obs, PointPrior(prob.measured, ps),
                           SETTINGS, res.inliers)
    h = problem.leverages(cams, res.points, None, res.covariance)
    np.testing.assert_allclose(h, _dense_leverages(problem, res), rtol=1e-6, atol=1e-9)
    assert np.all((h > 0) & (h < 2))
    red = sum(e.redundancy for e in res.cameras.values())
    assert red == pytest.approx(2 * res.inliers.sum() - h.sum())


def test_with_known_points_the_leverages_count_the_free_parameters(prob):
    # fixed: the points are the robot's; each camera pays for its 14 parameters exactly, and
    # for 6 when its intrinsics and distortion are held.
    given = {'cam2': IntrinsicsPrior.from_camera(prob.cameras[1])}
    res = adjust(prob.cameras, prob.measured, prob.obs, PriorSettings('fixed'),
                 SolverSettings(pixel_sigma=0.3, max_gate_rounds=0, gate_min_px=1e9,
                                distortion_sigma=None,
                                intrinsics=given))
    for name, free in (('cam1', 14), ('cam2', 6), ('cam3', 14)):
        e = res.cameras[name]
        assert 2 * e.n_inliers - e.redundancy == pytest.approx(free, abs=1e-6), name


def test_kinematic_leverages_match_the_whole_normal_matrix(prob):
    # A global prior (the kinematic model's error parameters g): N gains the rows of g,
    # H_gg = sum_i p_i A_i^T A_i + I and H_gx_i = -p_i A_i^T, and V_i = Vb_i + p_i I.
    from armcal_ros.core.kinematic_prior import KinematicData
    chain = prob.robot.chain
    kin = KinematicData(chain.jacobian_errors(prob.q, prob.robot.point), chain.error_names)
    ps = PriorSettings('kinematic')
    res = adjust(prob.cameras, prob.measured, prob.obs, ps, SETTINGS, kinematics=kin)
    cams = [e.camera for e in res.cameras.values()]
    prior = PointPrior(prob.measured, ps, kin)
    problem = adj._Problem(cams, prob.measured, prob.obs, prior, SETTINGS, res.inliers)
    g = res.global_parameters
    cov = np.linalg.inv(problem.reduced_matrix(cams, res.points, g))
    h = problem.leverages(cams, res.points, g, cov)
    U, _, Wt, Vb, _, _ = problem.normal_equations(cams, res.points, g)
    C, n, G = problem.layout.size, problem.n, len(g)
    p = prior.precision
    A = np.stack([prior.design.apply(e) for e in np.eye(G)], axis=2)       # (n, 3, G)
    V = np.zeros((3 * n, 3 * n))
    Hgx = np.zeros((G, 3 * n))
    for i in range(n):
        V[3 * i:3 * i + 3, 3 * i:3 * i + 3] = Vb[i] + p[i] * np.eye(3)
        Hgx[:, 3 * i:3 * i + 3] = -p[i] * A[i].T
    Hgg = np.einsum('n,nkg,nkh->gh', p, A, A) + np.eye(G)
    Wm = Wt.reshape(3 * n, C).T
    N = np.block([[U, np.zeros((C, G)), Wm], [np.zeros((G, C)), Hgg, Hgx], [Wm.T, Hgx.T, V]])
    Sigma = np.linalg.inv(N)
    pc = problem.layout.per_camera
    for j, idx in enumerate(problem.by_camera):
        c = cams[j]
        for k in idx[:5]:
            i = problem.obs.point[k]
            J = project_with_jacobians(c.intrinsics(), c.dist, c.rotation, c.translation,
                                       res.points[i][None])
            Jk = np.zeros((2, C + G + 3 * n))
            Jk[:, j * pc:(j + 1) * pc] = problem.layout.camera_jacobian(J)[0]
            Jk[:, C + G + 3 * i:C + G + 3 * i + 3] = J.d_point[0]
            want = np.trace(Jk @ Sigma @ Jk.T) / SETTINGS.pixel_sigma ** 2
            assert h[k] == pytest.approx(want, rel=1e-6, abs=1e-9), k


@pytest.mark.parametrize('model', ['fixed', 'independent', 'correlated', 'kinematic'])
def test_camera_sensitivity_is_the_estimates_derivative(model):
    # Noise-free images of the true points and the robot's points at the truth: perturb the
    # robot's points along a random direction, solve again, and the cameras move by D dX^.
    from armcal_ros.core.kinematic_prior import KinematicData
    p = make_robot_problem('geometric', 25, 4, pixel_sigma=0.0, n_test=10)
    uv = np.zeros_like(p.obs.uv)
    for j, c in enumerate(p.truth.values() if isinstance(p.truth, dict) else p.truth):
        m = p.obs.camera == j
        uv[m] = c.project(p.true_points[p.obs.point[m]])
    obs = adj.Observations(p.obs.camera, p.obs.point, uv)
    chain = p.robot.chain
    kin = KinematicData(chain.jacobian_errors(p.q, p.robot.point), chain.error_names)
    kw = dict(kinematics=kin) if model == 'kinematic' else {}
    ps = PriorSettings(model)
    tight = SolverSettings(pixel_sigma=0.3, max_gate_rounds=0, gate_min_px=1e9, ftol=1e-15,
                           xtol=1e-15, gtol=1e-20, max_iterations=200)
    base = adjust(p.cameras, p.true_points, obs, ps, tight, **kw)
    cams = base.camera_list()
    prior = PointPrior(p.true_points, ps, kin if model == 'kinematic' else None)
    problem = adj._Problem(cams, p.true_points, obs, prior, tight, base.inliers)
    g = base.global_parameters
    cov = np.linalg.inv(problem.reduced_matrix(cams, base.points, g))
    D = problem.camera_sensitivity(cams, base.points, g, cov)
    rng = np.random.default_rng(0)
    dX = rng.normal(0, 1e-6, p.true_points.shape)
    moved = []
    for sign in (1, -1):
        r = adjust(cams, p.true_points + sign * dX, obs, ps, tight,
                   points_init=None if model == 'fixed' else base.points, globals_init=g, **kw)
        moved.append(np.concatenate([np.concatenate([
            c.intrinsics(), c.dist[problem.layout.dist_idx]]) for c in r.camera_list()]))
    fd = (moved[0] - moved[1]) / 2
    pred = np.einsum('cnk,nk->c', D, dX)
    pc = problem.layout.per_camera
    intr = np.concatenate([np.arange(j * pc, j * pc + pc - 6) for j in range(len(cams))])
    np.testing.assert_allclose(pred[intr], fd, rtol=2e-2, atol=1e-3 * np.max(np.abs(fd)))


def test_a_subsample_of_leverages_estimates_each_cameras_sum():
    # Above max_per_camera observations an even subsample stands for the rest: each camera's
    # redundancy (2 n less the leverage sum) from 1 in 4 of them is within 3 % of the exact
    # one (the sum itself, over some 45 sampled leverages between 0.2 and 1.9, to about 10 %).
    p = make_robot_problem('geometric', 200, 1, pixel_sigma=0.3, n_test=10)
    from armcal_ros.core.kinematic_prior import KinematicData
    chain = p.robot.chain
    kin = KinematicData(chain.jacobian_errors(p.q, p.robot.point), chain.error_names)
    ps = PriorSettings('hybrid')
    res = adjust(p.cameras, p.measured, p.obs, ps, SETTINGS, kinematics=kin)
    cams = res.camera_list()
    problem = adj._Problem(cams, p.measured, p.obs, PointPrior(p.measured, ps, kin), SETTINGS,
                           res.inliers)
    g = res.global_parameters
    cov = np.linalg.inv(problem.reduced_matrix(cams, res.points, g))
    exact = problem.leverages(cams, res.points, g, cov)
    m = max(idx.size for idx in problem.by_camera)
    part = problem.leverages(cams, res.points, g, cov, max_per_camera=m // 4)
    for idx in problem.by_camera:
        sampled = np.isfinite(part[idx])
        assert 0.2 < sampled.mean() < 0.4
        np.testing.assert_allclose(part[idx][sampled], exact[idx][sampled], rtol=1e-9)
        estimate = idx.size * (2.0 - np.mean(part[idx][sampled]))
        assert estimate == pytest.approx(2 * idx.size - exact[idx].sum(), rel=0.03)
