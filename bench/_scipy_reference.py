"""
The bench's adjustment problem for scipy.optimize.least_squares, with its analytic Jacobian.

The fair comparison with armcal's own solver (:func:`armcal_ros.core.adjustment.adjust`): the
same objective, the same start and the same stopping tolerance, so that the solvers differ only
in how they take their steps.  The objective is armcal's with the plain loss::

    F = sum_ij |pi(c_j, X_i) - uv_ij|^2 / s_px^2  [+ sum_i |X_i - X^_i|^2 / s_pt^2]

(the bracket for the ``independent`` prior; for ``fixed`` the points are X^ and not unknowns).
least_squares minimises 0.5 |f|^2 with f the whitened residuals, so F = |f|^2 = 2 * sol.cost.

Unknowns, per camera: fx, fy, cx, cy, k1, k2, p1, p2, a rotation increment w and the translation
t, with R = expm([w]x) R0 about the start rotation R0 (no rotation-vector singularity, since w
stays small); then, for ``independent``, the points (3 per point).  The Jacobian is assembled
from :func:`armcal_ros.core.camera.project_with_jacobians` - the derivatives armcal's solver
uses - with the left Jacobian of SO(3) mapping its left-increment derivative to w.
"""

import time

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

from armcal_ros.core.camera import Camera, project_with_jacobians
from armcal_ros.core.geometry import skew

#: Unknowns per camera: fx fy cx cy k1 k2 p1 p2 w(3) t(3).
PER_CAMERA = 14


def left_jacobian(w):
    """
    Return the left Jacobian of SO(3) at w.

    expm([w + dw]x) = expm([J_l(w) dw]x) expm([w]x) to first order, so a derivative taken with
    respect to a left increment (what project_with_jacobians returns) times J_l(w) is the
    derivative with respect to w itself.
    """
    th = float(np.linalg.norm(w))
    K = skew(np.asarray(w, float))
    if th < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (np.eye(3) + (1.0 - np.cos(th)) / th ** 2 * K +
            (th - np.sin(th)) / th ** 3 * K @ K)


class ReferenceProblem:
    """
    One adjustment problem (cameras, and points under ``independent``) as scipy sees it.

    ``model`` is 'fixed' or 'independent'; ``cams0`` the start cameras (armcal Camera objects);
    ``measured`` X^ (N, 3); ``obs`` armcal Observations.  :meth:`residuals` and
    :meth:`jacobian` are f and df/dx for least_squares; :meth:`cameras` and :meth:`points`
    unpack a solution.
    """

    def __init__(self, model, cams0, measured, obs, pixel_sigma, point_sigma=None):
        """Set up the unknowns' layout and the Jacobian's sparsity pattern."""
        if model not in ('fixed', 'independent'):
            raise ValueError(f'model must be fixed or independent, got {model!r}')
        self.model = model
        self.cams0 = [c.copy() for c in cams0]
        self.measured = np.asarray(measured, float)
        self.obs = obs
        self.s_px = float(pixel_sigma)
        self.s_pt = float(point_sigma) if model == 'independent' else None
        self.nc = len(cams0)
        self.n = self.measured.shape[0]
        self.m = len(obs)
        self.groups = [np.flatnonzero(obs.camera == j) for j in range(self.nc)]
        self.n_cam = self.nc * PER_CAMERA
        self.size = self.n_cam + (3 * self.n if model == 'independent' else 0)
        self._structure()

    def _structure(self):
        """
        Fix the CSR pattern once: each image row holds its camera's 14 columns, then its point's 3.

        Camera columns precede point columns, so every row's indices are sorted and the values
        can be written straight into ``data`` in row order; the prior rows (one entry each)
        follow the 2M image rows.
        """
        m = self.m
        per_row = PER_CAMERA + (3 if self.model == 'independent' else 0)
        cols = np.empty((m, 2, per_row), dtype=np.int64)
        cam_cols = self.obs.camera[:, None] * PER_CAMERA + np.arange(PER_CAMERA)
        cols[:, :, :PER_CAMERA] = cam_cols[:, None, :]
        if self.model == 'independent':
            pt_cols = self.n_cam + 3 * self.obs.point[:, None] + np.arange(3)
            cols[:, :, PER_CAMERA:] = pt_cols[:, None, :]
        indices = cols.reshape(-1)
        indptr = np.arange(2 * m + 1, dtype=np.int64) * per_row
        self.n_rows = 2 * m
        if self.model == 'independent':
            indices = np.concatenate([indices, self.n_cam + np.arange(3 * self.n)])
            indptr = np.concatenate([indptr, indptr[-1] + 1 + np.arange(3 * self.n)])
            self.n_rows += 3 * self.n
        self.indices, self.indptr, self.per_row = indices, indptr, per_row

    def x0(self):
        """Return the start vector: the start cameras with w = 0, then X^ (independent)."""
        parts = [np.concatenate([c.intrinsics(), c.dist[:4], np.zeros(3), c.translation])
                 for c in self.cams0]
        if self.model == 'independent':
            parts.append(self.measured.reshape(-1))
        return np.concatenate(parts)

    def cameras(self, x):
        """Return the armcal Camera objects that ``x`` encodes."""
        out = []
        for j, c0 in enumerate(self.cams0):
            v = x[j * PER_CAMERA:(j + 1) * PER_CAMERA]
            R = Rotation.from_rotvec(v[8:11]).as_matrix() @ c0.rotation
            out.append(Camera(c0.name, c0.width, c0.height, v[0], v[1], v[2], v[3],
                              np.array([v[4], v[5], v[6], v[7], 0.0]), R, v[11:14]))
        return out

    def points(self, x):
        """Return the points encoded in ``x`` (X^ for ``fixed``)."""
        if self.model == 'fixed':
            return self.measured
        return x[self.n_cam:].reshape(self.n, 3)

    def _linearise(self, x, with_jacobian):
        cams = self.cameras(x)
        X = self.points(x)
        r = np.empty((self.m, 2))
        blocks = np.empty((self.m, 2, self.per_row)) if with_jacobian else None
        for j, idx in enumerate(self.groups):
            c = cams[j]
            J = project_with_jacobians(c.intrinsics(), c.dist, c.rotation, c.translation,
                                       X[self.obs.point[idx]])
            r[idx] = (J.uv - self.obs.uv[idx]) / self.s_px
            if not with_jacobian:
                continue
            Jl = left_jacobian(x[j * PER_CAMERA + 8:j * PER_CAMERA + 11])
            b = blocks[idx]
            b[:, :, 0:4] = J.d_intr
            b[:, :, 4:8] = J.d_dist[:, :, :4]
            b[:, :, 8:11] = J.d_pose[:, :, :3] @ Jl
            b[:, :, 11:14] = J.d_pose[:, :, 3:]
            if self.model == 'independent':
                b[:, :, 14:17] = J.d_point
            blocks[idx] = b / self.s_px
        return r.reshape(-1), blocks, X

    def residuals(self, x):
        """Return the whitened residuals f(x): the image rows, then the prior rows."""
        r, _, X = self._linearise(x, False)
        if self.model == 'independent':
            r = np.concatenate([r, ((X - self.measured) / self.s_pt).reshape(-1)])
        return r

    def jacobian(self, x):
        """Return df/dx as a CSR matrix with the pattern of :meth:`_structure`."""
        _, blocks, _ = self._linearise(x, True)
        data = blocks.reshape(-1)
        if self.model == 'independent':
            data = np.concatenate([data, np.full(3 * self.n, 1.0 / self.s_pt)])
        return csr_matrix((data, self.indices, self.indptr), shape=(self.n_rows, self.size))

    def jacobian_dense(self, x):
        """Return df/dx as a dense array (the dense-solver reference)."""
        return self.jacobian(x).toarray()

    def objective(self, x):
        """Return F(x) = |f(x)|^2, armcal's cost."""
        r = self.residuals(x)
        return float(r @ r)


def solve(prob: ReferenceProblem, ftol, dense=False, tr_options=None):
    """
    Solve ``prob`` with least_squares from its start; return (seconds, result).

    Sparse: method 'trf' with the CSR Jacobian and tr_solver 'lsmr' (the only trust-region
    solver scipy has for a sparse Jacobian).  Dense: method 'lm' (MINPACK's lmder, a dense QR
    per iteration) on the same Jacobian as an array.  Both scale by the Jacobian's columns
    (x_scale='jac', Marquardt's scaling as in armcal) and stop on armcal's ftol; xtol and gtol
    are tight so that ftol is the test that ends the run, as it does armcal's.  ``tr_options``
    go to LSMR (its atol and btol: at scipy's default 1e-6 its inexact steps end trf early).
    """
    x0 = prob.x0()
    t0 = time.perf_counter()
    if dense:
        sol = least_squares(prob.residuals, x0, jac=prob.jacobian_dense, method='lm',
                            x_scale='jac', ftol=ftol, xtol=1e-12, gtol=1e-12,
                            max_nfev=100 * prob.size)
    else:
        sol = least_squares(prob.residuals, x0, jac=prob.jacobian, method='trf',
                            tr_solver='lsmr', tr_options=tr_options or {}, x_scale='jac',
                            ftol=ftol, xtol=1e-12, gtol=1e-12, max_nfev=2000)
    return time.perf_counter() - t0, sol
