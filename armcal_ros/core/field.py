"""
Global parameters of the point prior: X_i = X^_i + A_i g + e_i, g ~ N(0, I), e_i ~ N(0, s_i^2 I).

Two kinds of design A (each maps a few global parameters g to a 3-vector per point):

* :class:`DenseDesign` - A_i given per point as a (3, P) matrix; the ``kinematic`` prior uses it
  with A_i = J_p(q_i) diag(sigma_p) (the marker's derivative with respect to the kinematic error
  parameters, scaled by their prior standard deviations, so that g is whitened).
* :class:`LatticeField` - the scalable form of the paper's correlated prior.  The bias field
  b(X) ~ GP(0, s_b^2 k(.; L) I_3) is represented by its values f_U at inducing points U on a
  regular lattice over the points (spacing ``spacing_factor`` x L) and interpolated by kriging
  (the Nystrom / subset-of-regressors weights k(x, U) K_UU^-1, better than trilinear weights:
  a numpy prototype with trilinear weights needed spacing L/3 to stay within 0.1 mm of the
  exact prior, these reach it at L/2 with a quarter of the nodes).  K_UU is whitened, never
  inverted: with its eigenpairs (Q_r, Lambda_r) above ``eig_tol`` times the largest,
  f_U = s_b Q_r Lambda_r^(1/2) g with g ~ N(0, I), and the field at a point is
  b(x) = a(x) g with features a(x) = s_b k(x, U) Q_r Lambda_r^(-1/2) (r of them, r much smaller
  than the number of nodes: at spacing L/2 the squared-exponential K_UU is numerically
  singular, and its negligible directions are dropped).  The represented variance |a(x)|^2 is
  at most s_b^2; the missing part s_b^2 - |a(x_i)|^2 is added to the point's own independent
  term (as in FITC), so every point keeps the prior's marginal variance s_b^2 + s_n^2.  For the
  squared-exponential kernel K_UU is a Kronecker product over the three lattice axes and both
  its eigen-decomposition and k(x, U) Q_r factorise per axis.

Both designs offer the four products the solver needs (``apply``: A g; ``apply_T``:
sum_i A_i^T y_i; ``cross``: sum_i A_i^T Y_i for Y_i (3, K); ``gram``: sum_i A_i^T C_i A_i for
C_i (3, 3)), each O(N) (the field's gram is O(N r^2)).
:class:`StackedDesign` concatenates designs (``hybrid`` = kinematic + lattice).
"""

from typing import List, Sequence

import numpy as np

from armcal_ros.core.kernels import kernel_function, kernel_matrix


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

    def dense(self):
        """Return A (N, 3, P)."""
        return self.A

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
    The correlated prior's bias field through inducing points on a lattice (see the module doc).

    ``points`` (N, 3) are the measured points X^ the field is evaluated at.  Attributes:
    ``spacing`` (m), ``shape`` (nodes per axis), ``nodes`` (n_U, 3), ``features`` (N, r),
    ``missing_variance`` (N,) in m^2, ``rank`` r and ``size`` = 3 r (coefficients ordered
    coefficient-major, axis-minor).
    """

    def __init__(self, points, bias_sigma, coherence_length, kernel='squared_exponential',
                 spacing_factor=0.5, max_nodes=1200, eig_tol=1e-6, max_rank=150):
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
        self.axes = [self.origin[a] + h * np.arange(shape[a]) for a in range(3)]
        grid = np.meshgrid(*self.axes, indexing='ij')
        self.nodes = np.stack([g.ravel() for g in grid], axis=1)
        self.n_nodes = self.nodes.shape[0]
        self.n = P.shape[0]
        self._eigen(eig_tol, max_rank)
        self.rank = self._scale.size
        self.size = 3 * self.rank
        self.features = self.features_at(P)
        represented = np.sum(self.features ** 2, axis=1)
        self.missing_variance = np.maximum(self.bias_sigma ** 2 - represented, 0.0)

    def _eigen(self, eig_tol, max_rank):
        """Keep the significant eigenpairs of K_UU (Kronecker-factored for the SE kernel)."""
        if self.kernel == 'squared_exponential':
            # exp(-|d|^2 / 2L^2) factorises over the axes: K_UU = Kx (x) Ky (x) Kz.
            vals, self._vecs = [], []
            for a in self.axes:
                lam, V = np.linalg.eigh(kernel_function(np.abs(a[:, None] - a[None, :]),
                                                        self.coherence_length))
                vals.append(np.maximum(lam, 0.0))
                self._vecs.append(V)
            lam = np.einsum('i,j,k->ijk', *vals).ravel()
        else:
            K = kernel_matrix(self.nodes, self.nodes, self.coherence_length, self.kernel)
            lam, self._Q = np.linalg.eigh(K)
            lam = np.maximum(lam, 0.0)
        order = np.argsort(lam)[::-1]
        keep = order[lam[order] > eig_tol * lam[order[0]]][:max_rank]
        self._keep = keep
        self._scale = self.bias_sigma / np.sqrt(lam[keep])

    def features_at(self, points):
        """
        Return a(x) (M, r) with b(x) = sum_j a_j(x) g_j: s_b k(x, U) Q_r Lambda_r^(-1/2).

        a(x) a(x)^T is the Nystrom approximation of the prior variance s_b^2 at x; the field is
        the kriging interpolant of the lattice values f_U = s_b Q_r Lambda_r^(1/2) g.
        """
        P = np.asarray(points, float)
        out = np.empty((P.shape[0], self.rank))
        for start in range(0, P.shape[0], 4096):
            X = P[start:start + 4096]
            if self.kernel == 'squared_exponential':
                proj = [kernel_function(np.abs(X[:, a, None] - self.axes[a][None, :]),
                                        self.coherence_length) @ self._vecs[a]
                        for a in range(3)]
                ii, jj, kk = np.unravel_index(self._keep, self.shape)
                out[start:start + 4096] = proj[0][:, ii] * proj[1][:, jj] * proj[2][:, kk]
            else:
                K = kernel_matrix(X, self.nodes, self.coherence_length, self.kernel)
                out[start:start + 4096] = K @ self._Q[:, self._keep]
        return out * self._scale

    # ---- the four products ------------------------------------------------------------

    def apply(self, g):
        """Return the field at the points, (N, 3)."""
        return self.features @ g.reshape(self.rank, 3)

    def dense(self):
        """Return A (N, 3, 3 r): A_i[k, 3 m + k] = features[i, m], zero elsewhere."""
        out = np.zeros((self.n, 3, self.rank, 3))
        for k in range(3):
            out[:, k, :, k] = self.features
        return out.reshape(self.n, 3, self.size)

    def evaluate(self, points, g):
        """Return the field at arbitrary points (M, 3)."""
        return self.features_at(points) @ g.reshape(self.rank, 3)

    def apply_T(self, Y):
        """Return sum_i A_i^T y_i for Y (N, 3): (3 r,)."""
        return (self.features.T @ Y).reshape(-1)

    def cross(self, Y):
        """Return sum_i A_i^T Y_i for Y (N, 3, K): (3 r, K)."""
        K = Y.shape[2]
        return (self.features.T @ Y.reshape(self.n, 3 * K)).reshape(self.size, K)

    def gram(self, C):
        """Return sum_i A_i^T C_i A_i for C (N, 3, 3): (3 r, 3 r)."""
        r = self.rank
        F = self.features
        pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
        # One (r x N) @ (N x 6r) product instead of six: the same flops, better BLAS use.
        cF = np.empty((self.n, len(pairs), r))
        for k, (a, b) in enumerate(pairs):
            np.multiply(C[:, a, b, None], F, out=cF[:, k, :])
        M = (F.T @ cF.reshape(self.n, -1)).reshape(r, len(pairs), r)
        out = np.empty((r, 3, r, 3))
        for k, (a, b) in enumerate(pairs):
            out[:, a, :, b] = M[:, k, :]
            if b != a:
                out[:, b, :, a] = M[:, k, :]
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

    def dense(self):
        """Return A (N, 3, G), the parts side by side."""
        return np.concatenate([p.dense() for p in self.parts], axis=2)

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
