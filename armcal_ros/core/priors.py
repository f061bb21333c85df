"""
Priors on the true 3-D points X given the robot's measured points X^ (the noise models).

Thompson, Daniel and Murray (2004) treat the arm's forward-kinematics positions as measurements
whose errors are smooth biases correlated over a coherence length L.  With N measured points
stacked point-major (x0, y0, z0, x1, ...)::

    fixed        X = X^ exactly (test-field calibration, the classic baseline)
    independent  X ~ N(X^, s_n^2 I)                       (Lavest et al.)
    correlated   X ~ N(X^, (s_b^2 K_L + s_n^2 I_N) (x) I_3),
                 K_L[i, k] = k(|X^_i - X^_k| / L)

with a stationary kernel k (squared exponential, exponential or Matern-3/2:
:mod:`armcal_ros.core.kernels`).  Each coordinate axis carries an independent copy of the same
scalar process.  The small independent term s_n keeps the matrix positive definite (0.02 mm is
enough in double precision).

A prior enters the objective as the quadratic (X - X^)^T P (X - X^) with precision P = Cov^-1;
the solver needs only P, either as N 3x3 blocks (``block_precision``) or dense
(``scalar_precision``, the N x N factor of the Kronecker product).

Beyond the paper (docs/NOISE_MODELS.md), priors with global parameters g ~ N(0, I)::

    X_i = X^_i + A_i g + e_i,   e_i ~ N(0, s_i^2 I)

(kind ``global``; :mod:`armcal_ros.core.field`, :mod:`armcal_ros.core.kinematic_prior`):

    kinematic    A_i = J_p(q_i) diag(sigma_p): the arm's kinematic error parameters
    correlated   (scalable form, ``field_form`` 'lattice', or 'auto' above
                 ``exact_max_points``) A_i = trilinear weights x whitened lattice covariance,
                 s_i^2 = s_n^2 + the variance the lattice misses at X^_i
    hybrid       both designs side by side

The solver keeps g next to the cameras in the reduced system; the points stay 3x3 blocks.
``auto`` is not a prior but a request to choose one (:mod:`armcal_ros.core.model_selection`).
"""

from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from armcal_ros.core.field import DenseDesign, LatticeField, StackedDesign
from armcal_ros.core.kernels import kernel_matrix, KERNELS
from armcal_ros.core.kinematic_prior import rigid_motion_jacobian

NOISE_MODELS = ('fixed', 'independent', 'correlated', 'kinematic', 'hybrid', 'auto')
FIELD_FORMS = ('auto', 'exact', 'lattice')
#: Models that need joint angles (the kinematic Jacobian).
KINEMATIC_MODELS = ('kinematic', 'hybrid')


@dataclass
class PriorSettings:
    """
    Hyperparameters of the point prior.

    point_sigma is s_n (metres), bias_sigma s_b (metres), coherence_length L (metres).
    field_form chooses the exact (dense, O(N^3)) or lattice (O(N)) form of the correlated
    field; 'auto' takes the exact one up to ``exact_max_points`` points (the lattice is always
    used by ``hybrid``).  lattice_spacing is the lattice spacing as a fraction of L,
    lattice_max_nodes caps the lattice (the spacing widens beyond it) and
    lattice_max_rank the number of field coefficients per axis (the leading eigenvectors of the
    lattice covariance are kept; the rest is restored as per-point variance).  kinematic_scale
    multiplies every kinematic prior sigma (``KinematicData.sigma``).
    """

    model: str = 'correlated'
    point_sigma: float = 0.0002
    bias_sigma: float = 0.001
    coherence_length: float = 0.3
    kernel: str = 'squared_exponential'
    field_form: str = 'auto'
    exact_max_points: int = 600
    lattice_spacing: float = 0.5
    lattice_max_nodes: int = 1200
    lattice_max_rank: int = 150
    kinematic_scale: float = 1.0

    def validate(self):
        """Raise ValueError naming the first bad field."""
        if self.model not in NOISE_MODELS:
            raise ValueError(f'noise_model must be one of {NOISE_MODELS}, got {self.model!r}')
        if self.kernel not in KERNELS:
            raise ValueError(f'kernel must be one of {KERNELS}, got {self.kernel!r}')
        if self.model != 'fixed' and not self.point_sigma > 0:
            raise ValueError(f'point_sigma must be > 0 for the {self.model} model, '
                             f'got {self.point_sigma}')
        if self.field_form not in FIELD_FORMS:
            raise ValueError(f'field_form must be one of {FIELD_FORMS}, got {self.field_form!r}')
        if not self.kinematic_scale >= 0:
            raise ValueError(f'kinematic_scale must be >= 0, got {self.kinematic_scale}')
        if self.lattice_max_rank < 1 or self.lattice_max_nodes < 8:
            raise ValueError(f'lattice_max_rank must be >= 1 and lattice_max_nodes >= 8, got '
                             f'{self.lattice_max_rank}, {self.lattice_max_nodes}')
        if not 0 < self.lattice_spacing <= 2:
            raise ValueError(f'lattice_spacing must be in (0, 2], got {self.lattice_spacing}')
        if self.model in ('correlated', 'hybrid'):
            if not self.bias_sigma >= 0:
                raise ValueError(f'bias_sigma must be >= 0, got {self.bias_sigma}')
            if not self.coherence_length > 0:
                raise ValueError(f'coherence_length must be > 0, got {self.coherence_length}')
        return self


def canonical_settings(ps):
    """Return ``ps``, or for a hybrid with one part switched off the settings of that model."""
    if ps.model == 'hybrid' and ps.kinematic_scale == 0:
        return replace(ps, model='correlated')
    if ps.model == 'hybrid' and ps.bias_sigma == 0:
        return replace(ps, model='kinematic')
    return ps


def prior_key(ps):
    """Return a key of the prior ``ps`` solves (a hybrid with one part off is that model)."""
    model = canonical_settings(ps).model
    field_part = (ps.bias_sigma, ps.coherence_length) if model in (
        'correlated', 'hybrid') else None
    kin = ps.kinematic_scale if model in KINEMATIC_MODELS else None
    return (model, field_part, kin, ps.point_sigma if model != 'fixed' else None)


class PointPrior:
    """
    Gaussian prior on the points: cost (X - X^)^T P (X - X^).

    ``kind`` is 'fixed' (points are not unknowns), 'block' (P is N 3x3 blocks), 'dense', or
    'global' (X = X^ + A g + e with ``design`` A, g ~ N(0, I), e_i ~ N(0, I / precision_i);
    cost sum_i precision_i |X_i - X^_i - A_i g|^2 + |g|^2).  ``kinematics`` is a
    :class:`~armcal_ros.core.kinematic_prior.KinematicData`, needed by 'kinematic' and 'hybrid'.
    """

    def __init__(self, measured, settings: PriorSettings, kinematics=None):
        settings.validate()
        if settings.model == 'auto':
            raise ValueError("noise_model 'auto' is a model choice, not a prior: use "
                             'calibrate() or model_selection.select_model()')
        self.settings = settings
        self.measured = np.asarray(measured, float)
        if self.measured.ndim != 2 or self.measured.shape[1] != 3:
            raise ValueError(f'measured points must have shape (N, 3), got {self.measured.shape}')
        n = self.measured.shape[0]
        self.n = n
        model = settings.model
        self.design = None
        self.field = None
        self.kinematics = None
        self.lattice = (model == 'hybrid' or (model == 'correlated' and (
            settings.field_form == 'lattice' or
            (settings.field_form == 'auto' and n > settings.exact_max_points))))
        if model in KINEMATIC_MODELS:
            if kinematics is None:
                raise ValueError(f'the {model} model needs kinematics (the per-point kinematic '
                                 'Jacobian from joint angles); pose input cannot use it')
            if kinematics.n != n:
                raise ValueError(f'kinematics.jacobian has {kinematics.n} points, measured '
                                 f'has {n}')
            self.kinematics = kinematics
        if model == 'fixed':
            self.kind = 'fixed'
        elif model in KINEMATIC_MODELS or (self.lattice and settings.bias_sigma > 0):
            self._init_global(settings, self.kinematics)
        elif model == 'independent' or (model == 'correlated' and settings.bias_sigma == 0):
            self.kind = 'block'
            self._blocks = np.broadcast_to(np.eye(3) / settings.point_sigma ** 2, (n, 3, 3))
        else:
            self.kind = 'dense'
            K = settings.bias_sigma ** 2 * kernel_matrix(
                self.measured, self.measured, settings.coherence_length, settings.kernel)
            K[np.diag_indices(n)] += settings.point_sigma ** 2
            self._chol = cho_factor(K, lower=True)
            # K^-1 (N x N); the 3N x 3N precision is K^-1 (x) I_3.
            self._kinv = cho_solve(self._chol, np.eye(n))

    def _init_global(self, settings, kinematics):
        self.kind = 'global'
        parts = []
        if kinematics is not None:
            parts.append(DenseDesign(kinematics.whitened_design(settings.kinematic_scale)))
        var = np.full(self.n, settings.point_sigma ** 2)
        if self.lattice and settings.bias_sigma > 0:
            self.field = LatticeField(self.measured, settings.bias_sigma,
                                      settings.coherence_length, settings.kernel,
                                      settings.lattice_spacing, settings.lattice_max_nodes,
                                      max_rank=settings.lattice_max_rank)
            parts.append(self.field)
            var = var + self.field.missing_variance
        self.design = StackedDesign(parts) if parts else None
        self.n_global = self.design.size if parts else 0
        self.precision = 1.0 / var
        # Which slice of g is what (for reporting).
        self.global_slices = {}
        if self.design is not None:
            names = (['kinematic'] if kinematics is not None else []) + \
                (['field'] if self.field is not None else [])
            for k, nm in enumerate(names):
                self.global_slices[nm] = slice(int(self.design.offsets[k]),
                                               int(self.design.offsets[k + 1]))

    def global_offsets(self, g):
        """Return A g (N, 3): the prior's predicted correction of the measured points."""
        if self.kind != 'global' or self.design is None:
            return np.zeros_like(self.measured)
        return self.design.apply(g)

    def global_cost(self, X, g):
        """Return sum_i precision_i |X_i - X^_i - A_i g|^2 + |g|^2 (kind 'global')."""
        D = np.asarray(X, float) - self.measured - self.global_offsets(g)
        return float(np.sum(self.precision * np.sum(D * D, axis=1)) + g @ g)

    def design_matrix(self):
        """Return the global design A (N, 3, G), densely (kind 'global'; cached)."""
        if self.kind != 'global':
            raise ValueError(f'design_matrix needs a global prior, this one is {self.kind}')
        if getattr(self, '_A', None) is None:
            self._A = (self.design.dense() if self.n_global else np.zeros((self.n, 3, 0)))
        return self._A

    def error_covariance(self):
        """
        Return the covariance this prior gives the point errors X^ - X, in a compact form.

        ('none', None) for ``fixed`` (the points are exact); ('blocks', (N, 3, 3)) for
        ``independent``; ('kron', K (N, N)), the covariance being K (x) I_3, for the exact
        correlated prior; ('lowrank', (var (N,), A (N, 3, G))), the covariance being
        diag(var) (x) I_3 + A A^T, for the global priors (kinematic, hybrid, the lattice
        field: their design is whitened, g ~ N(0, I)).
        """
        if self.kind == 'fixed':
            return 'none', None
        if self.kind == 'block':
            return 'blocks', np.linalg.inv(self._blocks)
        if self.kind == 'dense':
            L = np.tril(self._chol[0])
            return 'kron', L @ L.T
        return 'lowrank', (1.0 / self.precision, self.design_matrix())

    def relative_sigma(self, limit=300) -> float:
        """
        Return the per-axis error this prior gives a point, less what a rigid motion takes (m).

        Cameras fitted to the points move with any rigid motion common to all of them, so that
        part of the points' errors never shows at a new view.  With C the prior covariance of
        the errors of ``limit`` points spread evenly over the N (3m x 3m, from
        :meth:`error_covariance`), R (3m x 6) their rigid motions and P = I - R R^+,

            sigma^2 = tr(P C P) / 3m = (tr C - tr(R^+ C R)) / 3m,

        (P is a symmetric projection), so C is applied to R's six columns only.  A new view's
        point is drawn from the same prior, so this is the size of the arm's error to expect
        there; the adjustment's corrections at its own points, posterior means shrunk towards
        zero by the cameras' pull, say less.  0 for ``fixed``.
        """
        kind, C = self.error_covariance()
        if kind == 'none' or self.n == 0:
            return 0.0
        keep = np.unique(np.linspace(0, self.n - 1, min(self.n, int(limit))).round().astype(int))
        m = len(keep)
        R = rigid_motion_jacobian(self.measured[keep])                 # (m, 3, 6)
        if kind == 'blocks':
            B = C[keep]
            trace, CR = float(np.einsum('iaa->', B)), np.einsum('iab,ibk->iak', B, R)
        elif kind == 'kron':
            K = C[np.ix_(keep, keep)]
            trace, CR = 3.0 * float(np.trace(K)), np.einsum('ij,jak->iak', K, R)
        else:
            var, A = C
            A = A[keep]                                                # (m, 3, G)
            trace = float(np.sum(A * A) + 3.0 * np.sum(var[keep]))
            CR = A @ np.einsum('jbg,jbk->gk', A, R) + var[keep][:, None, None] * R
        R, CR = R.reshape(3 * m, 6), CR.reshape(3 * m, 6)
        absorbed = float(np.trace(np.linalg.pinv(R) @ CR))
        return float(np.sqrt(max(trace - absorbed, 0.0) / (3 * m)))

    def block_precision(self):
        """Precision as (N, 3, 3) blocks (kind 'block' only)."""
        if self.kind != 'block':
            raise ValueError(f'block_precision needs a block prior, this one is {self.kind}')
        return self._blocks

    def scalar_precision(self):
        """Return the N x N matrix K^-1 whose Kronecker product with I_3 is the precision."""
        if self.kind != 'dense':
            raise ValueError(f'scalar_precision needs a dense prior, this one is {self.kind}')
        return self._kinv

    def residual(self, X):
        """Whitened residual vector r with |r|^2 = (X - X^)^T P (X - X^), shape (3N,)."""
        D = np.asarray(X, float) - self.measured
        if self.kind == 'fixed':
            return np.zeros(0)
        if self.kind == 'block':
            return (D / self.settings.point_sigma).reshape(-1)
        # Whitening with the Cholesky factor: r = L^-1 D per axis.
        return solve_triangular(self._chol[0], D, lower=True).reshape(-1)

    def cost(self, X):
        """Return (X - X^)^T P (X - X^)."""
        r = self.residual(X)
        return float(r @ r)

    def gradient_half(self, X):
        """Return P (X - X^) as (N, 3), half the gradient of :meth:`cost`."""
        D = np.asarray(X, float) - self.measured
        if self.kind == 'fixed':
            return np.zeros_like(D)
        if self.kind == 'block':
            return D / self.settings.point_sigma ** 2
        return self._kinv @ D
