"""
The centre of a ball's image from a photometric model: a shaded sphere, whatever the light.

Why.  An intensity centroid is the centre's image only when the ball is equally bright all
over.  A matte ball under a lamp is brighter towards the lamp, and the centroid moves that way
by a fraction of the image radius - differently in every camera, since each sees the lit side
at another angle (core/marker_light.py has the exact offset; docs/BENCHMARKS.md, *realism*,
measures 0.4-0.7 px for a 5 mm ball at 1.5-2 m under a lamp above the cell).  Pooling a
dwell's frames does not average it out.  The outline of the ball does not move with the
light; a model of the whole blob - outline and shading together - separates the two.

Model.  In units of the image radius r about the centre (cx, cy), a disc point (x, y) sees the
surface normal n = (x, y, -z), z = sqrt(1 - x^2 - y^2) (camera looking along +z).  A
Lambertian ball with ambient light has brightness

    I(x, y) = p0 + max(0, p1 x + p2 y + p3 z)                                         (1)

(p0 the ambient level; (p1, p2, -p3) the lamp's direction times its strength: any one distant
lamp, from the front, the side or behind; p = 0 is a ball that glows alike from every side).
The image is

    m(u, v) = B + G_sigma * [ cov(u, v) I ]                                             (2)

with cov the pixel's covered fraction (S x S sub-pixels, the outline anti-aliased over one
sub-pixel), G_sigma a Gaussian point spread (defocus and optics), B the background.  The
perspective makes the outline an ellipse whose centre is off the centre's projection by
f a^2 tan t / cos^2 t (a the ball's angular radius, t its field angle): under 0.005 px for a
ball of a few pixels (sim/render.py), so the circle of (2) is the centre's image.

Fit.  Levenberg-Marquardt on all nine parameters (cx, cy, r, sigma, B, p0..p3), Marquardt's
diagonal scaling.  The model is linear in B, p0 and - on a fixed lit side - in p1..p3, so
those Jacobian columns are the basis images themselves (d max(0, p . n) / dp = n where lit);
the four geometric columns are forward differences.  The blur and the pixel integration are a
pair of small matrices (rows and columns), so a model image is two matrix products.  Written
here rather than with scipy.optimize.least_squares (the same minimum, 30 ms a fit) because the
exact linear columns and the warm start from the previous frame (two or three iterations in a
dwell) make it cheap enough for every still frame.
"""

from dataclasses import dataclass
import math

import numpy as np

#: Sub-pixels per pixel and axis: the outline is anti-aliased over one sub-pixel, so the model
#: image is smooth in the centre and radius and 4 x 4 is within 0.002 px of 8 x 8 on the
#: simulator's balls.
SUPERSAMPLE = 3


#: The ambient level and the lamp's term are bounded by this many times the patch's brightest
#: pixel (above its border).
SHADING_BOUND = 4.0
#: Bounds on the point spread (px): below 0.3 the pixel integration dominates anyway.
SIGMA_MIN, SIGMA_MAX = 0.3, 6.0


@dataclass(frozen=True)
class ShadedFit:
    """
    The fitted ball.

    ``uv`` (2,) centre, ``radius`` and ``sigma`` (px), ``shading`` (p0..p3
    of the module's (1), image units), ``background``, ``rms`` of the residual (image units),
    ``iterations``, ``status`` ('ok' or why the fit is not to be used) and ``message``.
    """

    uv: np.ndarray
    radius: float
    sigma: float
    shading: np.ndarray
    background: float
    rms: float
    iterations: int
    status: str
    message: str = ''

    @property
    def ok(self):
        """Return True when the fit converged inside its bounds."""
        return self.status == 'ok'


def _blur_matrix(d, sigma):
    """Blur matrix over pixel offsets ``d`` (n, n): a Gaussian truncated at 4 sigma, normalised."""
    half = math.ceil(4.0 * sigma)
    k = np.exp((-0.5 / (sigma * sigma)) * d * d)
    k[np.abs(d) > half] = 0.0
    norm = 1.0 + 2.0 * sum(math.exp(-0.5 * (j / sigma) ** 2) for j in range(1, half + 1))
    return k / norm


class _Model:
    """The model images of one patch: the bases of (2) for a geometry, and the linear solve."""

    def __init__(self, patch, u0, v0, scene=None):
        self.y = patch.astype(float).ravel()
        # The scene behind the ball, which it hides: its pixels' share in the blurred
        # outline is taken off (the last basis, its coefficient ~1).
        self.scene = None if scene is None else np.asarray(scene, float).ravel()
        self.n_linear = 5 if scene is None else 6
        self.h, self.w = patch.shape
        S = SUPERSAMPLE
        a = (np.arange(S) + 0.5) / S - 0.5
        self.us = ((u0 + np.arange(self.w))[:, None] + a[None, :]).ravel()
        self.vs = ((v0 + np.arange(self.h))[:, None] + a[None, :]).ravel()
        # Pixel integration as a matrix: row i averages the S sub-pixels of pixel i.
        self._pool_y = np.kron(np.eye(self.h), np.full((1, S), 1.0 / S))
        self._pool_x = np.kron(np.eye(self.w), np.full((1, S), 1.0 / S))
        self._ones = np.ones(self.h * self.w)
        self._dy = (np.arange(self.h)[:, None] - np.arange(self.h)[None, :]).astype(float)
        self._dx = (np.arange(self.w)[:, None] - np.arange(self.w)[None, :]).astype(float)
        self._sigma = None

    def _operators(self, sigma):
        """Return (Ly, Lx): pixel integration then blur, along rows and columns."""
        if sigma != self._sigma:
            self._ly = _blur_matrix(self._dy, sigma) @ self._pool_y
            self._lxt = (_blur_matrix(self._dx, sigma) @ self._pool_x).T
            self._sigma = sigma
        return self._ly, self._lxt

    def bases(self, g, p):
        """Return the (N, 5 or 6) basis images for geometry ``g``, the lit side from ``p``."""
        cx, cy, r, sigma = g
        # Only the sub-pixels of the disc's bounding box can be covered (the outline is
        # anti-aliased over half a sub-pixel outside the circle): the four fine images are
        # computed there and blurred by those columns of the operators - about a seventh of
        # the detector's patch (the radius plus 3 px each side) for a ball of 2 px radius.
        reach = r + 1.0 / SUPERSAMPLE
        iy = np.searchsorted(self.vs, (cy - reach, cy + reach))
        ix = np.searchsorted(self.us, (cx - reach, cx + reach))
        sy, sx = slice(*iy), slice(*ix)
        dx = (self.us[sx] - cx) / r
        dy = (self.vs[sy] - cy) / r
        rho2 = dy[:, None] ** 2 + dx[None, :] ** 2
        rho = np.sqrt(rho2)
        cov = np.minimum(np.maximum((1.0 - rho) * (r * SUPERSAMPLE) + 0.5, 0.0), 1.0)
        z = np.sqrt(np.maximum(1.0 - rho2, 0.0))
        lit = cov if p is None else cov * (p[0] * dx[None, :] + p[1] * dy[:, None]
                                           + p[2] * z > 0)
        ly, lxt = self._operators(sigma)
        fine = np.empty((4,) + cov.shape)
        fine[0] = cov
        np.multiply(lit, dx[None, :], out=fine[1])
        np.multiply(lit, dy[:, None], out=fine[2])
        np.multiply(lit, z, out=fine[3])
        # One stacked product for the four images (the same products as one at a time).
        blurred = ly[:, sy] @ fine @ lxt[sx]
        A = np.empty((self.h * self.w, self.n_linear))
        A[:, 0] = self._ones
        A[:, 1:5] = blurred.reshape(4, -1).T
        if self.scene is not None:
            A[:, 5] = -A[:, 1] * self.scene
        return A

    def image(self, theta):
        """Return the modelled pixels (N,) and the bases (N, 5) at the parameter vector."""
        A = self.bases(theta[:4], theta[6:9])
        return A @ theta[4:], A


#: A fit whose radius ends within this fraction of its upper bound (twice the start) is
#: pinned there (:func:`fit_shaded_sphere`).
RADIUS_PINNED = 0.99


#: Directions of light the cold starts try, as (p1, p2, p3) of the module's (1) (x right, y
#: down, z towards the camera): from the camera's side, from each side, and from behind.  A
#: ball lit from behind shows a bright rim on a dark disc, which a start lit from the front
#: may explain as a shifted, smaller ball (a local minimum measured on the simulator's
#: back-lit frames: 0.5-0.9 px off).
COLD_STARTS = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.3), (-1.0, 0.0, 0.3), (0.0, 1.0, 0.3),
               (0.0, -1.0, 0.3), (0.0, 0.0, -1.0))
#: The cold starts race: each runs this many iterations, then only the ``COLD_FINALISTS``
#: lowest in cost go on to convergence.  A start in a wrong basin (a back-lit ball taken for
#: a shifted front-lit one) is already worse after a few iterations: on 900 simulated frames
#: under four lamps and two LEDs the race found the six full fits' centre to 0.02 px in all
#: but 7 frames and matched their 99th-percentile error (0.132 px), in three quarters of the
#: time.  (Ranking the starts by a linear solve at the start's geometry, cheaper still,
#: chose the wrong basin in one frame in ten.)
COLD_RACE_ITERATIONS = 6
#: Four of the six go on, not two: on the simulator's lamp-lit cluttered cell, a start that
#: ended in the right basin was still behind after six iterations in some frames (cold fits
#: more than 0.5 px off: 261 of 1355 against 292), for about a third more time a cold fit;
#: on 900 lit balls over a dark ground nothing changed (99th percentile 0.127 px).
COLD_FINALISTS = 4
#: The largest concentration of the light-direction prior (:func:`fit_shaded_sphere`
#: ``light_prior``).  A lamp 1.5 m above a workspace of +-0.4 m is seen from one camera in
#: directions some +-15 degrees apart, a von Mises-Fisher concentration of about 1 / 0.26^2 ~ 15;
#: at 20 the prior can tip a near tie between two minima (log-odds up to 2 x 20) but not outweigh
#: an image that clearly shows the light elsewhere (a lamp moved or switched).
LIGHT_KAPPA_MAX = 20.0


#: The least spread (natural log of the radius) of the radius prior: the fits' own scatter
#: where the distance does not change (one camera's fits within a dwell, measured on the
#: simulator's lamp-lit textured UR5 cell: 1.49-1.80 px about 1.7, some 8 %).
RADIUS_SPREAD_MIN = 0.1


def fit_shaded_sphere(patch, u0, v0, uv0, radius0, sigma0=1.0, shading0=None,
                      max_iterations=30, tolerance=3e-3, scene=None, light_prior=None,
                      radius_prior=None, look=None):
    """
    Fit the shaded-sphere model (module doc) to ``patch`` and return a :class:`ShadedFit`.

    ``patch`` (h, w) background-level image around the ball, its top-left pixel at (u0, v0)
    (OpenCV convention: integer coordinates are pixel centres); ``uv0`` (2,), ``radius0`` and
    ``sigma0`` the start.  ``shading0`` (p0..p3) is a warm start (the previous frame's); without
    it the :data:`COLD_STARTS` race and the best finish (:data:`COLD_RACE_ITERATIONS`,
    :data:`COLD_FINALISTS`).  The
    radius is bounded to [radius0 / 2, 2 radius0]; a fit that ends at the upper bound
    (:data:`RADIUS_PINNED`) goes on once from there with the bounds doubled.  Converged when a
    step moves the centre and radius by less than ``tolerance`` px.

    ``scene`` (h, w), the static scene behind the ball where it is known (the detector's
    median of earlier frames), makes ``patch`` the frame minus that scene - unclipped - and
    the model the ball drawn over it: ``m = B + ball - k c S`` with c the ball's blurred
    coverage (the second basis) and k ~ 1 a linear parameter.  Fitting the ball alone to a
    frame minus its scene, clipped at zero, shaded the disc with the scene it hides (a ball
    over clutter 0.15-0.3 px off on the simulator's cluttered cell).

    ``light_prior`` (direction (3,), kappa): where the light came from in the camera's recent
    fits, a unit vector of (p1, p2, p3) and the concentration of a von Mises-Fisher density
    about it.  A cold fit then takes, of the race's finalists, the one of least

        cost / (2 s^2) - kappa d . l,     s^2 = least cost / (pixels - 10),

    (d its own light's direction, l the prior's; 10 bounds the fit's parameters): the
    posterior's mode when the image's noise is white, rather than the least cost.  The race is
    ranked the same way, and the prior's direction is one more start.  Why: a ball over a
    textured scene can fit nearly as well lit from the opposite side and shifted towards where
    its lit part is (measured on the simulator's lamp-lit textured UR5 cell: whole dwells
    1.1-1.8 px off, their residual RMS 1.5-3.5 % below the right minimum's), and what tells the
    two apart is that a lamp fixed in the cell lights the ball from nearly the same side at
    every place.  An LED that turns with the tool gives fits whose directions spread, hence a
    small kappa and a prior that decides little.

    ``radius_prior`` (radius, spread): the ball's size at the camera's recent places, a
    log-normal density of that median and log-spread (:func:`radius_prior_of`).  A cold fit's
    key then has ``(ln(r / radius))^2 / (2 spread^2)`` added.  Why: the other wrong minimum
    is a smaller ball shifted towards the lit side, lit from nearly the right direction
    (measured on the same cell: radius 1.1-1.2 px where the camera's fits at other places are
    1.6-2.0, 0.3-0.7 px off), which the light prior cannot tell apart; the ball's distance,
    hence its image's size, changes little from place to place.

    ``look`` (uv (2,), radius, sigma, shading (4,)): the camera's last fit moved to this blob
    (its centre at the same offset from the blob's centroid), one more start of the race.
    Where the light is much the same from place to place it starts in the right basin where
    none of the fixed starts does (measured on the same cell: every start from the blob's
    moments ended in the flipped or the smaller ball, 1.5 and 0.4 px off, the last fit's look
    0.17 px off).
    """
    patch = np.asarray(patch)
    if patch.ndim != 2 or min(patch.shape) < 5:
        raise ValueError(f'patch must be a 2-D array of at least 5 x 5, got shape {patch.shape}')
    uv0 = np.asarray(uv0, float).reshape(2)
    if not (radius0 > 0 and sigma0 > 0):
        raise ValueError(f'radius0 and sigma0 must be > 0, got {radius0}, {sigma0}')
    if scene is not None and np.shape(scene) != patch.shape:
        raise ValueError(f'scene must have the patch\'s shape {patch.shape}, got '
                         f'{np.shape(scene)}')
    model = _Model(patch, u0, v0, scene)
    occlusion = [] if scene is None else [1.0]
    level = float(np.median(np.concatenate([patch[0], patch[-1], patch[:, 0], patch[:, -1]])))
    top = float(patch.max()) - level
    geometry = [uv0[0], uv0[1], float(radius0), min(max(sigma0, SIGMA_MIN), SIGMA_MAX), level]
    if shading0 is not None:
        # A warm start is usually within the quadratic region: a small damping to begin with.
        shading0 = np.asarray(shading0, float).reshape(4)
        best = _levenberg_marquardt(model, np.r_[geometry, shading0, occlusion], radius0, top,
                                    1e-6,
                                    max_iterations, tolerance)
    else:
        race = max(1, min(COLD_RACE_ITERATIONS, max_iterations))
        prior = light_prior is not None and light_prior[1] > 0
        starts = COLD_STARTS + ((tuple(light_prior[0]),) if prior else ())
        thetas = [np.r_[geometry, 0.4 * top, 0.6 * top * np.asarray(light), occlusion]
                  for light in starts]
        if look is not None:
            uv, radius, sigma, shading = look
            thetas.append(np.r_[np.asarray(uv, float).reshape(2),
                                min(max(float(radius), 0.5 * radius0), 2.0 * radius0),
                                min(max(float(sigma), SIGMA_MIN), SIGMA_MAX), level,
                                np.asarray(shading, float).reshape(4), occlusion])
        runs = [_levenberg_marquardt(model, theta, radius0, top, 1e-3, race, tolerance)
                for theta in thetas]
        key = (light_prior if prior else None, radius_prior)
        runs.sort(key=_score(runs, model.y.size, *key))
        finals = []
        for theta, cost, it, converged, lam in runs[:COLD_FINALISTS]:
            if not converged and it < max_iterations:
                theta, cost, more, converged, lam = _levenberg_marquardt(
                    model, theta, radius0, top, lam, max_iterations - it, tolerance)
                it += more
            finals.append((theta, cost, it, converged, lam))
        best = min(finals, key=_score(finals, model.y.size, *key))
    theta, cost, it, converged, lam = best
    if theta[2] >= RADIUS_PINNED * 2.0 * radius0:
        # Pinned at the largest radius the start allows: the start under-stated the ball (the
        # moments of a crescent, the lit part of a ball over a brighter scene).  Once more
        # from there, the bounds about the pinned radius.
        radius0 = 2.0 * radius0
        theta, cost, more, converged, _ = _levenberg_marquardt(
            model, theta, radius0, top, lam, max_iterations, tolerance)
        it += more
    g, coef = theta[:4], theta[4:]
    rms = math.sqrt(cost / model.y.size)
    status, message = 'ok', ''
    if not converged:
        status, message = 'not_converged', f'no convergence in {max_iterations} iterations'
    elif coef[1] + np.linalg.norm(coef[2:5]) <= 0:
        status, message = 'no_ball', 'the fitted ball is not brighter than its background'
    elif not 0.5 * radius0 < g[2] < 2.0 * radius0:
        status, message = 'radius', (f'fitted radius {g[2]:.2f} px at a bound (start '
                                     f'{radius0:.2f})')
    return ShadedFit(uv=g[:2].copy(), radius=float(g[2]), sigma=float(g[3]),
                     shading=coef[1:5].copy(), background=float(coef[0]), rms=rms,
                     iterations=it, status=status, message=message)


def _score(runs, pixels, light_prior, radius_prior=None):
    """
    Return the key that ranks ``runs`` (:func:`fit_shaded_sphere`).

    Without priors their cost; with them the negative log posterior

        cost / (2 s^2) - kappa d . l + (ln(r / r_p))^2 / (2 spread^2),

    s^2 from the least cost of ``runs``, each prior's term only where it is given.
    """
    if light_prior is None and radius_prior is None:
        return lambda run: run[1]
    if light_prior is None:
        direction, kappa = np.zeros(3), 0.0
    else:
        direction = np.asarray(light_prior[0], float).reshape(3)
        kappa = min(float(light_prior[1]), LIGHT_KAPPA_MAX)
    if radius_prior is None:
        log_r, weight = 0.0, 0.0
    else:
        log_r = math.log(radius_prior[0])
        weight = 0.5 / max(float(radius_prior[1]), RADIUS_SPREAD_MIN) ** 2
    s2 = max(min(r[1] for r in runs), 1e-12) / max(pixels - 10, 1)

    def score(run):
        light = run[0][6:9]
        norm = np.linalg.norm(light)
        agree = float(light @ direction) / norm if norm > 0 else 0.0
        size = weight * (math.log(max(run[0][2], 1e-9)) - log_r) ** 2
        return run[1] / (2.0 * s2) - kappa * agree + size
    return score


def light_prior_of(directions):
    """
    Return (direction (3,), kappa) of a von Mises-Fisher density fitted to unit ``directions``.

    kappa by Banerjee et al.'s (2005) approximation R (3 - R^2) / (1 - R^2), R the mean
    resultant length; (zeros, 0) for an empty or balanced set.
    """
    d = np.asarray(directions, float).reshape(-1, 3)
    if len(d) == 0:
        return np.zeros(3), 0.0
    mean = d.mean(axis=0)
    r = float(np.linalg.norm(mean))
    if r < 1e-9:
        return np.zeros(3), 0.0
    r_ = min(r, 1.0 - 1e-9)
    return mean / r, min(r_ * (3.0 - r_ * r_) / (1.0 - r_ * r_), LIGHT_KAPPA_MAX)


def radius_prior_of(radii):
    """
    Return (radius, spread) of a log-normal density fitted to ``radii`` (px), or None.

    The median and 1.4826 times the median absolute deviation of their logarithms (robust to
    a fit or two on something else), the spread at least :data:`RADIUS_SPREAD_MIN`; None for
    an empty set or one with a radius that is not positive.
    """
    r = np.asarray(radii, float).ravel()
    if len(r) == 0 or not np.all(r > 0):
        return None
    logs = np.log(r)
    centre = float(np.median(logs))
    spread = 1.4826 * float(np.median(np.abs(logs - centre)))
    return math.exp(centre), max(spread, RADIUS_SPREAD_MIN)


def _levenberg_marquardt(model, theta, radius0, top, lam, max_iterations, tolerance):
    """
    Return (theta, cost, iterations, converged, damping) from ``theta`` (module doc, Fit).

    ``top`` is the patch's brightest pixel above its border: the shading cannot be brighter
    than a few times that (blur lowers the peak, not by more), and a bound keeps a shading
    lit only at an invisible rim - whose columns vanish, so nothing would pull it back - out.
    """
    bright = SHADING_BOUND * max(top, 1e-9)
    theta = theta.copy()
    theta[5] = min(max(theta[5], 0.0), bright)
    norm = np.linalg.norm(theta[6:9])
    if norm > bright:
        theta[6:9] *= bright / norm
    y = model.y
    m, A = model.image(theta)
    res = y - m
    cost = res @ res
    h = 1e-3
    it = 0
    converged = False
    J = np.empty((y.size, theta.size))
    for it in range(1, max_iterations + 1):
        # Geometry by forward differences, the linear parameters exactly: their columns are
        # the bases themselves (d max(0, p.n) / dp = n on the lit side).
        for k in range(4):
            tk = theta.copy()
            tk[k] += h
            J[:, k] = (model.image(tk)[0] - m) / h
        J[:, 4:] = A
        JtJ, Jtr = J.T @ J, J.T @ res
        d = np.diag(JtJ).copy() + 1e-12
        improved = False
        while lam < 1e10:
            delta = np.linalg.solve(JtJ + lam * np.diag(d), Jtr)
            trial = theta + delta
            # Bounds: a radius within a factor of two of the start (the blob's own size), a
            # plausible blur, and no negative ambient light (which would let a dark ball with
            # a bright rim pose as a shifted one).
            trial[2] = min(max(trial[2], 0.5 * radius0, 0.5), 2.0 * radius0)
            trial[3] = min(max(trial[3], SIGMA_MIN), SIGMA_MAX)
            trial[5] = min(max(trial[5], 0.0), bright)
            norm = np.linalg.norm(trial[6:9])
            if norm > bright:
                trial[6:9] *= bright / norm
            if trial.size > 9:
                trial[9] = min(max(trial[9], 0.0), 2.0)      # the hidden scene's share
            m_t, A_t = model.image(trial)
            res_t = y - m_t
            cost_t = res_t @ res_t
            if cost_t < cost:
                # The step taken, not the one proposed: a radius held at its bound proposes
                # the same step again and again.
                step = trial - theta
                theta, m, A, res, cost = trial, m_t, A_t, res_t, cost_t
                lam = max(lam / 10.0, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or np.max(np.abs(step[:3])) < tolerance:
            converged = True
            break
    return theta, cost, it, converged, lam
