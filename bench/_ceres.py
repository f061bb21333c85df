"""
The bench's adjustment problem for Ceres, through pycolmap's bundle adjuster.

The fair comparison with armcal's own solver: the same objective, start and stopping tolerance,
solved by COLMAP's compiled (autodiff) reprojection cost functions and Ceres' Schur-complement
Levenberg-Marquardt.  The mapping:

* one OPENCV camera per armcal camera (fx, fy, cx, cy, k1, k2, p1, p2 - armcal's plumb_bob with
  k3 = 0; COLMAP projects u = fx x'' + cx with no half-pixel shift, so the pixels agree), each
  with its own trivial rig and one image whose frame pose is cam_from_world = (R, t);
* the robot points as Point3D, their observations as the images' points2D;
* ``fixed``: every point constant (BundleAdjustmentConfig.add_constant_point);
  ``independent``: every point variable, plus a pyceres.factors.NormalPrior residual on the
  point's own parameter block (the Point3D's xyz, the memory the adjuster optimises);
* every intrinsic refined (focal length, principal point and the distortion), no robust loss,
  no gauge fixed (BundleAdjustmentGauge.UNSPECIFIED: the measured points leave the problem
  without gauge freedom, as in armcal).

COLMAP insists on tracks of two or more images; a point seen by one camera only gets its
reprojection residual from pycolmap.cost_functions.ReprojErrorCost (the adjuster's own cost
functor) on a parameter block this module owns, added to the adjuster's problem.

Scaling: COLMAP's residual is in pixels and Ceres minimises 0.5 sum r^2, so the prior residual
is (X - X^) s_px / s_pt and armcal's objective is F = 2 C / s_px^2; the relative function
tolerance is scale-free, so Ceres stops on armcal's ftol unchanged.
"""

import time

import numpy as np
import pyceres
import pycolmap
import pycolmap.cost_functions

from armcal_ros.core.camera import Camera


def _build(model, cams0, measured, obs):
    """Return (reconstruction, config, own blocks) for one problem, from the start cameras."""
    rec = pycolmap.Reconstruction()
    counts = np.bincount(obs.point, minlength=measured.shape[0])
    for j, c in enumerate(cams0):
        cam = pycolmap.Camera(model='OPENCV', width=c.width, height=c.height, camera_id=j + 1,
                              params=np.concatenate([c.intrinsics(), c.dist[:4]]))
        rec.add_camera_with_trivial_rig(cam)
        idx = np.flatnonzero(obs.camera == j)
        img = pycolmap.Image(name=c.name, keypoints=obs.uv[idx], camera_id=j + 1,
                             image_id=j + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(c.rotation), c.translation)
        rec.add_image_with_trivial_frame(img, pose)
    # Where each observation sits in its image's points2D.
    k2d = np.empty(len(obs), dtype=np.int64)
    for j in range(len(cams0)):
        idx = np.flatnonzero(obs.camera == j)
        k2d[idx] = np.arange(idx.size)
    order = np.argsort(obs.point, kind='stable')
    starts = np.searchsorted(obs.point[order], np.arange(measured.shape[0] + 1))
    point_ids = np.full(measured.shape[0], -1)
    singles = []
    for i in range(measured.shape[0]):
        mine = order[starts[i]:starts[i + 1]]
        if counts[i] >= 2:
            track = pycolmap.Track([pycolmap.TrackElement(int(obs.camera[k]) + 1, int(k2d[k]))
                                    for k in mine])
            point_ids[i] = rec.add_point3D(measured[i], track)
        elif counts[i] == 1:
            singles.append((i, int(mine[0])))
    config = pycolmap.BundleAdjustmentConfig()
    for j in range(len(cams0)):
        config.add_image(j + 1)
    for pid in point_ids[point_ids >= 0]:
        if model == 'fixed':
            config.add_constant_point(int(pid))
        else:
            config.add_variable_point(int(pid))
    return rec, config, point_ids, singles


def _options(ftol, max_iterations=200):
    """Return BundleAdjustmentOptions: every intrinsic free, plain loss, one thread, ftol."""
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = True
    opts.refine_principal_point = True
    opts.refine_extra_params = True
    opts.refine_rig_from_world = True
    opts.print_summary = False
    opts.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    so = opts.ceres.solver_options
    so.num_threads = 1
    so.function_tolerance = ftol
    # Tight, so that the function tolerance (armcal's test) is what ends the run.
    so.gradient_tolerance = 1e-12
    so.parameter_tolerance = 1e-12
    so.max_num_iterations = max_iterations
    opts.ceres.solver_options = so
    return opts


class CeresRun:
    """
    One built problem: the reconstruction, the adjuster and the extra residuals.

    Build (untimed) with the constructor, then :meth:`solve` (timed by the caller) and read
    the solution with :meth:`cameras` and :meth:`points`.
    """

    def __init__(self, model, cams0, measured, obs, pixel_sigma, point_sigma, ftol):
        """Build the reconstruction, the adjuster and the residuals COLMAP does not add."""
        if model not in ('fixed', 'independent'):
            raise ValueError(f'model must be fixed or independent, got {model!r}')
        self.model = model
        self.cams0 = cams0
        self.measured = np.asarray(measured, float)
        self.obs = obs
        self.rec, config, self.point_ids, self.singles = _build(model, cams0, self.measured,
                                                                obs)
        self.adjuster = pycolmap.create_default_ceres_bundle_adjuster(
            _options(ftol), config, self.rec)
        problem = self.adjuster.problem
        self._keep = []            # parameter blocks and cost functions Ceres points into
        opencv = pycolmap.CameraModelId.OPENCV
        poses = [self.rec.frame(j + 1).rig_from_world.params for j in range(len(cams0))]
        params = [self.rec.camera(j + 1).params for j in range(len(cams0))]
        # Like with like: every camera parameter free (8 intrinsics, a 6-dof pose), no gauge.
        for blk, dof in [(b, 6) for b in poses] + [(b, 8) for b in params]:
            if not problem.has_parameter_block(blk) or problem.is_parameter_block_constant(blk) \
                    or problem.parameter_block_tangent_size(blk) != dof:
                raise RuntimeError('a camera block is missing, constant or partly held')
        if config.todict()['fixed_gauge'] != pycolmap.BundleAdjustmentGauge.UNSPECIFIED:
            raise RuntimeError('the adjuster would fix a gauge')
        cov = np.eye(3) * (point_sigma / pixel_sigma) ** 2 if model == 'independent' else None
        self.single_blocks = {}
        for i, k in self.singles:
            j = int(obs.camera[k])
            if model == 'fixed':
                cost = pycolmap.cost_functions.ReprojErrorCost(opencv, obs.uv[k],
                                                               self.measured[i])
                problem.add_residual_block(cost, None, [poses[j], params[j]])
            else:
                xyz = self.measured[i].copy()
                self.single_blocks[i] = xyz
                cost = pycolmap.cost_functions.ReprojErrorCost(opencv, obs.uv[k])
                problem.add_residual_block(cost, None, [xyz, poses[j], params[j]])
            self._keep.append(cost)
        if model == 'independent':
            n_blocks = problem.num_parameter_blocks()
            for i, pid in enumerate(self.point_ids):
                if pid < 0:
                    if i not in self.single_blocks:
                        continue
                    xyz = self.single_blocks[i]
                else:
                    xyz = self.rec.points3D[int(pid)].xyz
                prior = pyceres.factors.NormalPrior(self.measured[i].copy(), cov)
                problem.add_residual_block(prior, None, [xyz])
                self._keep.append(prior)
            # The priors must sit on the adjuster's own point blocks, not on copies.
            if problem.num_parameter_blocks() != n_blocks:
                raise RuntimeError('a point prior created a new parameter block')

    def solve(self):
        """Run the adjuster (Ceres) and return its summary: the part that is timed."""
        return self.adjuster.solve()

    def cameras(self):
        """Return the adjusted cameras as armcal Camera objects."""
        out = []
        for j, c0 in enumerate(self.cams0):
            p = np.asarray(self.rec.camera(j + 1).params)
            pose = self.rec.frame(j + 1).rig_from_world
            out.append(Camera(c0.name, c0.width, c0.height, p[0], p[1], p[2], p[3],
                              np.array([p[4], p[5], p[6], p[7], 0.0]),
                              pose.rotation.matrix(), np.asarray(pose.translation)))
        return out

    def points(self):
        """Return the adjusted points: X^ under ``fixed`` and where no camera sees a point."""
        X = self.measured.copy()
        for i, pid in enumerate(self.point_ids):
            if pid >= 0:
                X[i] = self.rec.points3D[int(pid)].xyz
        for i, xyz in self.single_blocks.items():
            X[i] = xyz
        return X


def solve(model, cams0, measured, obs, pixel_sigma, point_sigma, ftol):
    """
    Build the problem (untimed), solve it with Ceres and time the solve only.

    Returns (seconds, CeresRun, summary); the run holds the solution.
    """
    run = CeresRun(model, cams0, measured, obs, pixel_sigma, point_sigma, ftol)
    t0 = time.perf_counter()
    summary = run.solve()
    return time.perf_counter() - t0, run, summary
