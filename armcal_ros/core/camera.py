"""
Pinhole camera with OpenCV/ROS ``plumb_bob`` distortion, and its analytic Jacobians.

Projection of a world point X (metres, robot base frame) by a camera with world-to-camera pose
(R, t), exactly as ``cv2.projectPoints`` computes it with five distortion coefficients::

    [x, y, z] = R X + t,          x' = x / z,  y' = y / z,  r^2 = x'^2 + y'^2
    radial    = 1 + k1 r^2 + k2 r^4 + k3 r^6
    x''       = x' radial + 2 p1 x' y' + p2 (r^2 + 2 x'^2)
    y''       = y' radial + p1 (r^2 + 2 y'^2) + 2 p2 x' y'
    u = fx x'' + cx,              v = fy y'' + cy

Rotation is perturbed on the left, R <- expm([w]x) R, so the minimal pose increment is
(w, dt) in R^6 and d(RX + t)/dw = -[RX]x at w = 0.  That is the parameterisation the solver
updates and the one the Jacobians below are taken with respect to.
"""

from dataclasses import dataclass, field
from typing import Tuple

import numpy as np
from scipy.spatial.transform import Rotation


DISTORTION_NAMES = ('k1', 'k2', 'p1', 'p2', 'k3')
INTRINSIC_NAMES = ('fx', 'fy', 'cx', 'cy')
POSE_NAMES = ('wx', 'wy', 'wz', 'tx', 'ty', 'tz')


def _as_points(X, name='X'):
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f'{name} must have shape (N, 3), got {X.shape}')
    return X


@dataclass
class Camera:
    """
    One camera: image size, intrinsics, plumb_bob distortion and world-to-camera pose.

    ``rotation`` and ``translation`` map world (robot base) points into the optical frame
    (REP 103: x right, y down, z forward): x_cam = rotation @ X + translation.
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        self.dist = np.asarray(self.dist, dtype=float).reshape(-1)
        if self.dist.shape != (5,):
            raise ValueError(f'dist must have 5 plumb_bob coefficients, got {self.dist.shape}')
        self.rotation = np.asarray(self.rotation, dtype=float)
        if self.rotation.shape != (3, 3):
            raise ValueError(f'rotation must be 3x3, got {self.rotation.shape}')
        self.translation = np.asarray(self.translation, dtype=float).reshape(3)
        self.width = int(self.width)
        self.height = int(self.height)

    # --- conversions -------------------------------------------------------------------
    @property
    def K(self):
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def rvec(self):
        """Rodrigues vector of ``rotation`` (world-to-camera), as OpenCV uses it."""
        return Rotation.from_matrix(self.rotation).as_rotvec()

    @property
    def center(self):
        """Optical centre in the world frame, C = -R^T t."""
        return -self.rotation.T @ self.translation

    def pose_in_world(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return T_base_camera as (translation (3,), quaternion [qx, qy, qz, qw])."""
        q = Rotation.from_matrix(self.rotation.T).as_quat()
        return self.center, q

    @classmethod
    def from_pose_in_world(cls, name, width, height, K, dist, translation, quat_xyzw):
        """Build a camera from K, distortion and its pose in the world (TF convention)."""
        K = np.asarray(K, dtype=float).reshape(3, 3)
        R_wc = Rotation.from_quat(np.asarray(quat_xyzw, dtype=float)).as_matrix()
        R = R_wc.T
        t = -R @ np.asarray(translation, dtype=float).reshape(3)
        return cls(name, width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist, R, t)

    @classmethod
    def look_at(cls, name, width, height, fx, fy, cx, cy, dist, eye, target, up=(0, 0, 1)):
        """Build a camera at ``eye`` whose optical axis points at ``target`` (z up world)."""
        eye = np.asarray(eye, float)
        z = np.asarray(target, float) - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, np.asarray(up, float))
        if np.linalg.norm(x) < 1e-9:
            x = np.cross(z, [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.vstack([x, y, z])
        return cls(name, width, height, fx, fy, cx, cy, dist, R, -R @ eye)

    def copy(self):
        """Deep copy."""
        return Camera(self.name, self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                      self.dist.copy(), self.rotation.copy(), self.translation.copy())

    def intrinsics(self):
        """Return [fx, fy, cx, cy]."""
        return np.array([self.fx, self.fy, self.cx, self.cy])

    def set_intrinsics(self, values):
        """Set fx, fy, cx, cy from a 4-vector."""
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in values)

    def apply_pose_increment(self, w, dt):
        """
        Update the pose by R <- expm([w]x) R and t <- t + dt.

        This is the increment the Jacobians are taken with respect to:
        d(RX + t)/dw = -[RX]x and d(RX + t)/d(dt) = I at w = 0, dt = 0.
        """
        dR = Rotation.from_rotvec(np.asarray(w, float)).as_matrix()
        self.rotation = dR @ self.rotation
        self.translation = self.translation + np.asarray(dt, float)

    # --- projection --------------------------------------------------------------------
    def to_camera(self, X):
        """World points (N, 3) -> camera-frame points (N, 3)."""
        X = _as_points(X)
        return X @ self.rotation.T + self.translation

    def project(self, X):
        """Project world points (N, 3) to pixels (N, 2); identical to cv2.projectPoints."""
        return project(self.intrinsics(), self.dist, self.rotation, self.translation, X)

    def in_front(self, X):
        """Boolean mask of points with positive depth."""
        return self.to_camera(X)[:, 2] > 0


def _distort(xn, yn, dist):
    k1, k2, p1, p2, k3 = dist
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return xd, yd, r2, radial


def project(intr, dist, R, t, X):
    """
    Project world points with intrinsics [fx, fy, cx, cy], plumb_bob ``dist``, pose (R, t).

    Returns (N, 2) pixels.  Points behind the camera are projected as the formula says
    (callers mask them with :meth:`Camera.in_front`).
    """
    X = _as_points(X)
    fx, fy, cx, cy = intr
    Xc = X @ np.asarray(R).T + np.asarray(t)
    xn = Xc[:, 0] / Xc[:, 2]
    yn = Xc[:, 1] / Xc[:, 2]
    xd, yd, _, _ = _distort(xn, yn, np.asarray(dist, float))
    return np.column_stack([fx * xd + cx, fy * yd + cy])


@dataclass
class ProjectionJacobians:
    """
    Pixels and their derivatives for N points.

    Shapes: ``uv`` (N, 2); ``d_intr`` (N, 2, 4) w.r.t. [fx, fy, cx, cy]; ``d_dist`` (N, 2, 5)
    w.r.t. [k1, k2, p1, p2, k3]; ``d_pose`` (N, 2, 6) w.r.t. the left rotation increment w and
    the translation increment dt; ``d_point`` (N, 2, 3) w.r.t. the world point; ``depth`` (N,).
    """

    uv: np.ndarray
    d_intr: np.ndarray
    d_dist: np.ndarray
    d_pose: np.ndarray
    d_point: np.ndarray
    depth: np.ndarray


def project_with_jacobians(intr, dist, R, t, X) -> ProjectionJacobians:
    """Project and differentiate analytically (see the module docstring for the model)."""
    X = _as_points(X)
    fx, fy, cx, cy = intr
    k1, k2, p1, p2, k3 = dist
    R = np.asarray(R, float)
    RX = X @ R.T
    Xc = RX + np.asarray(t, float)
    z = Xc[:, 2]
    iz = 1.0 / z
    xn = Xc[:, 0] * iz
    yn = Xc[:, 1] * iz
    xd, yd, r2, radial = _distort(xn, yn, np.asarray(dist, float))
    n = X.shape[0]

    uv = np.column_stack([fx * xd + cx, fy * yd + cy])

    d_intr = np.zeros((n, 2, 4))
    d_intr[:, 0, 0] = xd
    d_intr[:, 1, 1] = yd
    d_intr[:, 0, 2] = 1.0
    d_intr[:, 1, 3] = 1.0

    d_dist = np.empty((n, 2, 5))
    d_dist[:, 0, 0] = fx * xn * r2
    d_dist[:, 1, 0] = fy * yn * r2
    d_dist[:, 0, 1] = fx * xn * r2 * r2
    d_dist[:, 1, 1] = fy * yn * r2 * r2
    d_dist[:, 0, 2] = fx * 2.0 * xn * yn
    d_dist[:, 1, 2] = fy * (r2 + 2.0 * yn * yn)
    d_dist[:, 0, 3] = fx * (r2 + 2.0 * xn * xn)
    d_dist[:, 1, 3] = fy * 2.0 * xn * yn
    d_dist[:, 0, 4] = fx * xn * r2 ** 3
    d_dist[:, 1, 4] = fy * yn * r2 ** 3

    # d(x'', y'') / d(x', y')
    dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dr_dx = dradial_dr2 * 2.0 * xn
    dr_dy = dradial_dr2 * 2.0 * yn
    a = np.empty((n, 2, 2))
    a[:, 0, 0] = radial + xn * dr_dx + 2.0 * p1 * yn + 6.0 * p2 * xn
    a[:, 0, 1] = xn * dr_dy + 2.0 * p1 * xn + 2.0 * p2 * yn
    a[:, 1, 0] = yn * dr_dx + 2.0 * p1 * xn + 2.0 * p2 * yn
    a[:, 1, 1] = radial + yn * dr_dy + 6.0 * p1 * yn + 2.0 * p2 * xn
    a[:, 0, :] *= fx
    a[:, 1, :] *= fy
    # d uv / d Xc = a @ b with b = d(x', y') / d Xc = [[1, 0, -x'], [0, 1, -y']] / z, written
    # out: b is sparse, and batched matmuls of 2x2 and 2x3 blocks cost more than the products.
    d_xc = np.empty((n, 2, 3))
    d_xc[:, :, 0] = a[:, :, 0] * iz[:, None]
    d_xc[:, :, 1] = a[:, :, 1] * iz[:, None]
    d_xc[:, :, 2] = -(d_xc[:, :, 0] * xn[:, None] + d_xc[:, :, 1] * yn[:, None])

    d_point = (d_xc.reshape(2 * n, 3) @ R).reshape(n, 2, 3)     # one GEMM for every row
    # Left rotation increment: d Xc / d w = -[R X]_x, so each row d of d uv / d Xc maps to
    # -d^T [R X]_x = (R X) x d, a cross product per row.
    d_pose = np.empty((n, 2, 6))
    v0, v1, v2 = RX[:, 0, None], RX[:, 1, None], RX[:, 2, None]
    e0, e1, e2 = d_xc[:, :, 0], d_xc[:, :, 1], d_xc[:, :, 2]
    d_pose[:, :, 0] = v1 * e2 - v2 * e1
    d_pose[:, :, 1] = v2 * e0 - v0 * e2
    d_pose[:, :, 2] = v0 * e1 - v1 * e0
    d_pose[:, :, 3:] = d_xc
    return ProjectionJacobians(uv, d_intr, d_dist, d_pose, d_point, z)


def undistort_normalized(cam: Camera, uv, iterations=20):
    """
    Pixels (N, 2) -> normalised undistorted coordinates (N, 2) by fixed-point iteration.

    The same scheme as cv2.undistortPoints; converges for the moderate distortion of
    ordinary lenses.
    """
    uv = np.asarray(uv, float).reshape(-1, 2)
    xd = (uv[:, 0] - cam.cx) / cam.fx
    yd = (uv[:, 1] - cam.cy) / cam.fy
    k1, k2, p1, p2, k3 = cam.dist
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return np.column_stack([x, y])
