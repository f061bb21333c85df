"""
Global parameters of the point prior: X_i = X^_i + A_i g + e_i, g ~ N(0, I), e_i ~ N(0, s_i^2 I).

Two kinds of design A (each maps a few global parameters g to a 3-vector per point):

* :class:`DenseDesign` - A_i given per point as a (3, P) matrix; the ``kinematic`` prior uses it
  with A_i = J_p(q_i) diag(sigma_p) (the marker's derivative with respect to the kinematic error
  parameters, scaled by their prior standard deviations, so that g is whitened).
* :class:`LatticeField` - the scalable form of the paper's correlated prior.  The bias field
  b(X) ~ GP(0, s_b^2 k(.; L) I_3) is represented by its values f_U at inducing points on a
  regular lattice over the points (spacing ``spacing_factor`` x L), interpolated trilinearly:
  b(X^_i) ~= sum_k w_ik f_U[k].  With K_UU = Phi Phi^T (Phi = s_b Q_r Lambda_r^(1/2), the
  eigenvectors of K_UU whose eigenvalues exceed ``eig_tol`` times the largest), f_U = Phi u
  with u ~ N(0, I): the lattice covariance is whitened, never inverted - at spacing L/2 the
  squared-exponential K_UU is numerically singular, and dropping its negligible directions also
  shrinks the number of coefficients.  The interpolated field has per-point variance
  w_i^T K_UU w_i <= s_b^2; the missing part s_b^2 - w_i^T K_UU w_i is added to the point's own
  independent term, so every point keeps the prior's marginal variance s_b^2 + s_n^2.  For the
  squared-exponential kernel K_UU is a Kronecker product over the three lattice axes and its
  eigen-decomposition costs next to nothing.

Both designs offer the four products the solver needs (``apply``: A g; ``apply_T``:
sum_i A_i^T y_i; ``cross``: sum_i A_i^T Y_i for Y_i (3, K); ``gram``: sum_i A_i^T C_i A_i for
C_i (3, 3)), at O(N) cost per call: the lattice products accumulate per-point terms on the
lattice nodes with a sparse interpolation matrix and only then transform with Phi, so their cost
grows with the number of points linearly and with the lattice size as n_U r^2.
:class:`StackedDesign` concatenates designs (``hybrid`` = kinematic + lattice).
"""

from typing import List, Sequence

import numpy as np
import scipy.sparse as sp

from armcal_ros.core.priors import kernel_function, kernel_matrix


class DenseDesign:
    """A_i stored densely: ``A`` (N, 3, P)."""

    def __init__(self, A):
        A = np.asarray(A, float)
        if A.ndim != 3 or A.shape[1] != 3:
            raise ValueError(f'design matrix must have shape (N, 3, P), got {A.shape}')
        self.A = A
        self.n = A.shape[0]
        self.size = A.shape[2]
        self._flat = A.reshape(3 * self.n, self.size)

    def apply(self, g):
        """Return A g as (N, 3)."""
        return self.A @ g

    def apply_T(self, Y):
        """Return sum_i A_i^T y_i for Y (N, 3): (P,)."""
        return self._flat.T @ Y.reshape(-1)

    def cross(self, Y):
        """Return sum_i A_i^T Y_i for Y (N, 3, K): (P, K)."""
        return self._flat.T @ Y.reshape(3 * self.n, -1)

    def gram(self, C):
        """Return sum_i A_i^T C_i A_i for C (N, 3, 3): (P, P)."""
        CA = np.einsum('nkl,nlp->nkp', C, self.A).reshape(3 * self.n, self.size)
        return self._flat.T @ CA


class LatticeField:
    """
    The correlated prior's bias field on a lattice of inducing points (see the module doc).

    ``points`` (N, 3) are the measured points X^ the field is evaluated at.  Attributes:
    ``spacing`` (m), ``shape`` (nodes per axis), ``nodes`` (n_U, 3), ``phi`` (n_U, r),
    ``missing_variance`` (N,) in m^2, ``size`` = 3 r (coefficients, ordered coefficient-major,
    axis-minor).
    """

    def __init__(self, points, bias_sigma, coherence_length, kernel='squared_exponential',
                 spacing_factor=0.5, max_nodes=1200, eig_tol=1e-9):
        P = np.asarray(points, float)
        if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] == 0:
            raise ValueError(f'points must have shape (N, 3) with N > 0, got {P.shape}')
        if not bias_sigma > 0:
            raise ValueError(f'bias_sigma must be > 0 for a lattice field, got {bias_sigma}')
        if not coherence_length > 0:
            raise ValueError(f'coherence_length must be > 0, got {coherence_length}')
        if not 0 < spacing_factor <= 2:
            raise ValueError(f'spacing_factor must be in (0, 2], got {spacing_factor}')
        self.bias_sigma = float(bias_sigma)
        self.coherence_length = float(coherence_length)
        self.kernel = kernel
        lo, hi = P.min(axis=0), P.max(axis=0)
        extent = np.maximum(hi - lo, 1e-9)
        h = spacing_factor * coherence_length
        shape = np.ceil(extent / h).astype(int) + 1
        # A lattice too large for the dense reduced system: widen the spacing (the missing
        # variance term keeps the marginals right; accuracy degrades gracefully).
        while np.prod(shape) > max_nodes:
            h *= 1.1
            shape = np.ceil(extent / h).astype(int) + 1
        shape = np.maximum(shape, 2)
        self.spacing = h
        self.shape = tuple(int(s) for s in shape)
        self.origin = 0.5 * (lo + hi) - 0.5 * h * (shape - 1)
        axes = [self.origin[a] + h * np.arange(shape[a]) for a in range(3)]
        grid = np.meshgrid(*axes, indexing='ij')
        self.nodes = np.stack([g.ravel() for g in grid], axis=1)
        self.n_nodes = self.nodes.shape[0]
        self.n = P.shape[0]
        idx, w = self._trilinear(P)
        self.W = sp.csr_matrix((w.ravel(), (np.repeat(np.arange(self.n), 8), idx.ravel())),
                               shape=(self.n, self.n_nodes))
        self.phi = self._whitening(axes, eig_tol)
        self.rank = self.phi.shape[1]
        self.size = 3 * self.rank
        Kq = self.phi @ self.phi.T
        represented = np.einsum('nk,nkl,nl->n', w, Kq[idx[:, :, None], idx[:, None, :]], w)
        self.missing_variance = np.maximum(self.bias_sigma ** 2 - represented, 0.0)

    def _trilinear(self, P):
        t = (P - self.origin) / self.spacing
        base = np.clip(np.floor(t).astype(int), 0, np.array(self.shape) - 2)
        f = np.clip(t - base, 0.0, 1.0)
        idx = np.empty((P.shape[0], 8), int)
        w = np.empty((P.shape[0], 8))
        ny, nz = self.shape[1], self.shape[2]
        k = 0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    i = base + np.array([dx, dy, dz])
                    idx[:, k] = (i[:, 0] * ny + i[:, 1]) * nz + i[:, 2]
                    w[:, k] = (np.where(dx, f[:, 0], 1 - f[:, 0]) *
                               np.where(dy, f[:, 1], 1 - f[:, 1]) *
                               np.where(dz, f[:, 2], 1 - f[:, 2]))
                    k += 1
        return idx, w

    def _whitening(self, axes, eig_tol):
        """Phi (n_U, r) with Phi Phi^T = s_b^2 K_UU restricted to its significant eigenspace."""
        s2 = self.bias_sigma ** 2
        if self.kernel == 'squared_exponential':
            # exp(-|d|^2 / 2L^2) factorises over the axes: K_UU = Kx (x) Ky (x) Kz.
            vals, vecs = [], []
            for a in axes:
                lam, V = np.linalg.eigh(kernel_function(np.abs(a[:, None] - a[None, :]),
                                                        self.coherence_length))
                vals.append(np.maximum(lam, 0.0))
                vecs.append(V)
            lam = np.einsum('i,j,k->ijk', *vals).ravel()
            keep = np.flatnonzero(lam > eig_tol * lam.max())
            ii, jj, kk = np.unravel_index(keep, [len(v) for v in vals])
            cols = (vecs[0][:, ii][:, None, None, :] * vecs[1][:, jj][None, :, None, :] *
                    vecs[2][:, kk][None, None, :, :]).reshape(self.n_nodes, keep.size)
            return cols * np.sqrt(s2 * lam[keep])
        K = kernel_matrix(self.nodes, self.nodes, self.coherence_length, self.kernel)
        lam, V = np.linalg.eigh(K)
        keep = lam > eig_tol * lam.max()
        return V[:, keep] * np.sqrt(s2 * lam[keep])

    # ---- the four products ------------------------------------------------------------

    def values_at_nodes(self, g):
        """Field values f_U (n_U, 3) for coefficients g (3 r,)."""
        return self.phi @ g.reshape(self.rank, 3)

    def apply(self, g):
        """Return the interpolated field at the points, (N, 3)."""
        return self.W @ self.values_at_nodes(g)

    def evaluate(self, points, g):
        """Interpolated field at arbitrary points (M, 3) inside or near the lattice."""
        idx, w = self._trilinear(np.asarray(points, float))
        F = self.values_at_nodes(g)
        return np.einsum('mk,mka->ma', w, F[idx])

    def apply_T(self, Y):
        """Return sum_i A_i^T y_i for Y (N, 3): (3 r,)."""
        return (self.phi.T @ (self.W.T @ Y)).reshape(-1)

    def cross(self, Y):
        """Return sum_i A_i^T Y_i for Y (N, 3, K): (3 r, K)."""
        K = Y.shape[2]
        Z = (self.W.T @ Y.reshape(self.n, 3 * K)).reshape(self.n_nodes, 3 * K)
        return (self.phi.T @ Z).reshape(self.size, K)

    def gram(self, C):
        """Return sum_i A_i^T C_i A_i for C (N, 3, 3): (3 r, 3 r)."""
        r = self.rank
        out = np.empty((r, 3, r, 3))
        Wt = self.W.T.tocsr()
        for a in range(3):
            for b in range(a, 3):
                Q = Wt @ sp.diags(C[:, a, b]) @ self.W          # sparse (n_U, n_U)
                M = self.phi.T @ (Q @ self.phi)
                out[:, a, :, b] = M
                if b != a:
                    out[:, b, :, a] = M.T
        return out.reshape(self.size, self.size)


class StackedDesign:
    """Several designs side by side: A_i = [A_i^(1), A_i^(2), ...], g = [g^(1); g^(2); ...]."""

    def __init__(self, parts: Sequence):
        self.parts: List = list(parts)
        if not self.parts:
            raise ValueError('StackedDesign needs at least one part')
        self.n = self.parts[0].n
        if any(p.n != self.n for p in self.parts):
            raise ValueError('all parts of a StackedDesign must cover the same points')
        sizes = [p.size for p in self.parts]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)])
        self.size = int(self.offsets[-1])

    def split(self, g):
        """Return g cut into the parts' coefficient vectors."""
        return [g[self.offsets[k]:self.offsets[k + 1]] for k in range(len(self.parts))]

    def apply(self, g):
        """Return A g, (N, 3)."""
        return sum(p.apply(x) for p, x in zip(self.parts, self.split(g)))

    def apply_T(self, Y):
        """Return sum_i A_i^T y_i: (G,)."""
        return np.concatenate([p.apply_T(Y) for p in self.parts])

    def cross(self, Y):
        """Return sum_i A_i^T Y_i: (G, K)."""
        return np.vstack([p.cross(Y) for p in self.parts])

    def gram(self, C):
        """Return sum_i A_i^T C_i A_i: (G, G); off-diagonal blocks go through a dense part."""
        G = np.zeros((self.size, self.size))
        o = self.offsets
        for k, p in enumerate(self.parts):
            G[o[k]:o[k + 1], o[k]:o[k + 1]] = p.gram(C)
            for m in range(k + 1, len(self.parts)):
                q = self.parts[m]
                if isinstance(p, DenseDesign):
                    B = q.cross(np.einsum('nkl,nlp->nkp', C, p.A)).T     # (size_p, size_q)
                elif isinstance(q, DenseDesign):
                    B = p.cross(np.einsum('nkl,nlp->nkp', C, q.A))       # (size_p, size_q)
                else:
                    raise ValueError('a StackedDesign may hold at most one non-dense part')
                G[o[k]:o[k + 1], o[m]:o[m + 1]] = B
                G[o[m]:o[m + 1], o[k]:o[k + 1]] = B.T
        return G
