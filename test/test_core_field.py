"""
The scalable correlated field against the exact prior.

Its products, its covariance, the reduced system, and agreement with the exact (dense)
correlated prior.
"""
import numpy as np
import pytest

from armcal_ros.core.adjustment import _Problem, adjust, SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.evaluation import triangulate
from armcal_ros.core.field import DenseDesign, LatticeField, StackedDesign
from armcal_ros.core.kernels import kernel_matrix
from armcal_ros.core.priors import PointPrior, PriorSettings
from armcal_ros.sim.robot_points import make_robot_problem
from armcal_ros.sim.synthetic import make_problem


def _dense(design, n):
    """Materialise A (N, 3, G) column by column through ``apply``."""
    A = np.zeros((n, 3, design.size))
    for k in range(design.size):
        e = np.zeros(design.size)
        e[k] = 1.0
        A[:, :, k] = design.apply(e)
    return A


@pytest.mark.parametrize('kernel', ['squared_exponential', 'matern32'])
def test_products_match_the_materialised_design(kernel):
    rng = np.random.default_rng(0)
    P = rng.uniform(-0.3, 0.3, (60, 3))
    parts = [DenseDesign(rng.normal(size=(60, 3, 5))),
             LatticeField(P, 1e-3, 0.3, kernel=kernel)]
    design = StackedDesign(parts)
    A = _dense(design, 60)
    Y = rng.normal(size=(60, 3))
    Yk = rng.normal(size=(60, 3, 4))
    B = rng.normal(size=(60, 3, 3))
    C = B @ B.transpose(0, 2, 1)
    assert np.allclose(design.apply_T(Y), np.einsum('nkg,nk->g', A, Y))
    assert np.allclose(design.cross(Yk), np.einsum('nkg,nkc->gc', A, Yk))
    assert np.allclose(design.gram(C), np.einsum('nka,nkl,nlb->ab', A, C, A))
    f = parts[1]
    g = rng.normal(size=f.size)
    assert np.allclose(f.evaluate(P, g), f.apply(g))


def test_field_covariance_approximates_the_kernel_and_keeps_the_marginals():
    rng = np.random.default_rng(1)
    P = rng.uniform(-0.3, 0.3, (300, 3))
    sb, L = 1e-3, 0.3
    f = LatticeField(P, sb, L)
    approx = f.features @ f.features.T
    exact = sb ** 2 * kernel_matrix(P, P, L)
    assert np.max(np.abs(approx - exact)) < 0.01 * sb ** 2
    assert np.allclose(np.sum(f.features ** 2, axis=1) + f.missing_variance, sb ** 2)
    assert f.rank <= 150 and f.spacing <= 0.5 * L + 1e-12


def test_reduced_system_equals_brute_force_elimination():
    """The Schur complement over (cameras, globals) and the step equal a dense solve."""
    prob = make_robot_problem('mixed', 40, 0, n_test=10)
    s = SolverSettings(pixel_sigma=0.3)
    fx = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    prior = PointPrior(prob.measured, PriorSettings('hybrid'), prob.kinematics)
    cams = fx.adjustment.camera_list()
    pb = _Problem(cams, prob.measured, prob.obs, prior, s, np.ones(len(prob.obs), bool))
    g = np.random.default_rng(1).normal(size=prior.n_global) * 0.3
    X = prob.measured + 1e-4
    U, g_c, Wt, Vb, g_x, g_g = pb.normal_equations(cams, X, g)
    lam = 1e-2
    S, rhs, _ = pb._global_system(U, g_c, Wt, Vb, g_x, g_g, lam)
    n, C, G = len(X), U.shape[0], prior.n_global
    A = _dense(prior.design, n)
    p = prior.precision
    H = np.zeros((C + G + 3 * n,) * 2)
    H[:C, :C] = U
    H[:C, C + G:] = Wt.reshape(3 * n, C).T       # Wt (n, 3, C) holds W_i^T per point
    H[C + G:, :C] = Wt.reshape(3 * n, C)
    H[C:C + G, C:C + G] = np.einsum('nka,n,nkb->ab', A, p, A) + np.eye(G)
    B = -(p[:, None, None] * A).reshape(3 * n, G)
    H[C + G:, C:C + G] = B
    H[C:C + G, C + G:] = B.T
    for i in range(n):
        H[C + G + 3 * i:C + G + 3 * i + 3, C + G + 3 * i:C + G + 3 * i + 3] = \
            Vb[i] + p[i] * np.eye(3)
    H[np.diag_indices_from(H)] *= 1.0 + lam
    d = np.linalg.solve(H, -np.concatenate([g_c, g_g, g_x.ravel()]))
    dc, dx, dg = pb.solve_step(U, g_c, Wt, Vb, g_x, lam, g_g)
    assert np.allclose(np.concatenate([dc, dg, dx.ravel()]), d, rtol=1e-7,
                       atol=1e-9 * np.abs(d).max())
    # cost gradient w.r.t. g against central differences
    k = 3
    e = np.zeros(G)
    e[k] = 1e-6
    num = (pb.cost(cams, X, g + e) - pb.cost(cams, X, g - e)) / 2e-6 / 2.0
    assert abs(num - g_g[k]) < 1e-5 * max(abs(g_g[k]), 1.0)


def test_lattice_form_agrees_with_the_exact_prior():
    """Lattice against exact: camera centres within half their std, points within 0.15 mm."""
    prob = make_problem(400, 3, bias_sigma=1e-3, coherence_length=0.3, pixel_sigma=0.3)
    s = SolverSettings(pixel_sigma=0.3)
    fx = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    c0, inl = fx.adjustment.camera_list(), fx.adjustment.inliers
    ex = adjust(c0, prob.measured, prob.obs, PriorSettings('correlated', field_form='exact'),
                s, inliers=inl)
    la = adjust(c0, prob.measured, prob.obs, PriorSettings('correlated', field_form='lattice'),
                s, inliers=inl)
    assert ex.prior.kind == 'dense' and la.prior.kind == 'global'
    for name, a in ex.cameras.items():
        b = la.cameras[name]
        assert np.linalg.norm(a.camera.center - b.camera.center) < 0.5 * a.std['center_x']
    uvs = [c.project(prob.test_points) for c in prob.cameras]
    Xe = triangulate(ex.camera_list(), uvs)
    Xl = triangulate(la.camera_list(), uvs)
    assert np.nanmax(np.linalg.norm(Xe - Xl, axis=1)) < 0.15e-3
    assert abs(ex.log_evidence - la.log_evidence) < 2.0


def test_auto_form_switches_to_the_lattice_above_the_threshold():
    P = np.random.default_rng(0).uniform(-0.3, 0.3, (50, 3))
    assert PointPrior(P, PriorSettings('correlated', exact_max_points=100)).kind == 'dense'
    assert PointPrior(P, PriorSettings('correlated', exact_max_points=40)).kind == 'global'
    with pytest.raises(ValueError, match='field_form'):
        PriorSettings('correlated', field_form='sparse').validate()
    with pytest.raises(ValueError, match='bias_sigma'):
        LatticeField(P, 0.0, 0.3)
