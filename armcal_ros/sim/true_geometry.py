"""
The arm's true geometry written as a URDF: the limit a calibration of the detections can reach.

A calibration given the arm's true geometry and the ``fixed`` model has nothing left to learn
about the arm: its error is what the detections leave (their noise and bias).  Benchmarks put
it beside ``auto``'s (docs/BENCHMARKS.md).  Only the geometric errors of
:mod:`armcal_ros.sim.true_robot` are a geometry (the ``geometric`` scenario has no other); the
periodic joint errors, the compliance and a bias field are not, and stay out.

Each movable joint's error block (:mod:`armcal_ros.robot.kinematics`: an offset o, a
translation t and a rotation r on the right of the joint origin O) becomes its new origin,

    O' = O [Exp(r) | t] M(o),

M(o) the joint's own motion by o (a rotation about its axis, a translation along it): for a
revolute joint Rot(a, q + o) = Rot(a, o) Rot(a, q), so the offset folds into the origin
exactly.  The tip block [Exp(r) | t] moves the marker's point p on the tip link to
Exp(r) p + t (:func:`true_marker_offset`).
"""

import os
import xml.etree.ElementTree as ET

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from armcal_ros.io.calib_files import atomic_write_text
from armcal_ros.robot.kinematics import so3_exp
from armcal_ros.robot.urdf import origin_matrix
from armcal_ros.sim.cell import default_urdf_path

#: The scenarios whose true arm is a geometry alone (:data:`armcal_ros.sim.cell.SCENARIOS`).
EXACT_SCENARIOS = ('geometric',)


def _motion(axis, jtype, value):
    T = np.eye(4)
    if jtype == 'prismatic':
        T[:3, 3] = np.asarray(axis, float) * value
    else:
        T[:3, :3] = Rotation.from_rotvec(np.asarray(axis, float) * value).as_matrix()
    return T


def true_geometry_urdf(urdf_text: str, chain, errors) -> str:
    """
    Return ``urdf_text`` with ``chain``'s movable joints' origins moved by ``errors``.

    ``chain`` is the nominal :class:`~armcal_ros.robot.kinematics.KinematicChain` built from
    the same URDF, ``errors`` its error vector (``chain.error_names``).  The tip block is not
    in the URDF: see :func:`true_marker_offset`.
    """
    e = np.asarray(errors, float).reshape(-1)
    if e.shape != (chain.n_errors,):
        raise ValueError(f'errors must have shape ({chain.n_errors},), got {e.shape}')
    root = ET.fromstring(urdf_text)
    joints = {j.get('name'): j for j in root.iter('joint')}
    for k, name in enumerate(chain.joint_names):
        elem = joints.get(name)
        if elem is None:
            raise ValueError(f'joint {name!r} of the chain is not in the URDF')
        origin = elem.find('origin')
        if origin is None:
            origin = ET.SubElement(elem, 'origin')
        xyz = [float(v) for v in origin.get('xyz', '0 0 0').split()]
        rpy = [float(v) for v in origin.get('rpy', '0 0 0').split()]
        axis_elem = elem.find('axis')
        axis = np.array([float(v) for v in (axis_elem.get('xyz', '1 0 0')
                                            if axis_elem is not None else '1 0 0').split()])
        axis = axis / np.linalg.norm(axis)
        b = e[7 * k:7 * k + 7]
        D = np.eye(4)
        D[:3, :3], D[:3, 3] = so3_exp(b[4:7]), b[1:4]
        T = origin_matrix(xyz, rpy) @ D @ _motion(axis, elem.get('type'), b[0])
        origin.set('xyz', ' '.join(f'{v:.12g}' for v in T[:3, 3]))
        origin.set('rpy', ' '.join(f'{v:.12g}' for v in
                                   Rotation.from_matrix(T[:3, :3]).as_euler('xyz')))
    return ET.tostring(root, encoding='unicode')


def true_marker_offset(chain, errors, point) -> np.ndarray:
    """Return the marker's true place on the tip link: Exp(r_tip) p + t_tip (p without)."""
    p = np.asarray(point, float).reshape(3)
    if not chain.tip_errors:
        return p
    e = np.asarray(errors, float).reshape(-1)[-6:]
    return so3_exp(e[3:]) @ p + e[:3]


def write_true_geometry(result, directory, parameters):
    """
    Write ``true_geometry.urdf`` and ``params_true_geometry.yaml`` into ``directory``.

    ``result`` is a :class:`~armcal_ros.sim.cell.SimResult`, ``parameters`` the calibrator's
    parameters for its cell (``ground_truth/params.yaml``'s); the new file has the true URDF,
    the marker's true place and the ``fixed`` model.  Returns the parameter file's path.
    """
    robot = result.robot
    with open(result.settings.urdf_path or default_urdf_path(), encoding='utf-8') as f:
        text = true_geometry_urdf(f.read(), result.chain, robot.errors)
    atomic_write_text(os.path.join(directory, 'true_geometry.urdf'), text)
    exact = result.scenario in EXACT_SCENARIOS
    values = dict(parameters, robot_description_file='true_geometry.urdf', noise_model='fixed',
                  marker_offset=[float(v) for v in true_marker_offset(result.chain,
                                                                      robot.errors,
                                                                      robot.point)])
    path = os.path.join(directory, 'params_true_geometry.yaml')
    what = 'exact' if exact else \
        f'geometric errors only: scenario {result.scenario} has others besides'
    head = ('# the limit of the detections: this cell with the arm\'s true geometry and the '
            f'fixed model\n# ({what})\n')
    atomic_write_text(path, head + yaml.safe_dump({'armcal': {'ros__parameters': values}},
                                                  sort_keys=False))
    return path


__all__ = ['EXACT_SCENARIOS', 'true_geometry_urdf', 'true_marker_offset', 'write_true_geometry']
