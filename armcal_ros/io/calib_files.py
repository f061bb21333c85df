"""
Calibration files: ``camera_info`` YAML and ``extrinsics.yaml``.

``<camera>.yaml`` follows the camera_calibration_parsers format that camera_info_manager loads
(``image_width``, ``image_height``, ``camera_name``, ``camera_matrix``, ``distortion_model``,
``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix``; each matrix as
``rows``, ``cols``, ``data``).  For a monocular camera the rectification is the identity and the
projection matrix is P = [K | 0].  The camera pose is not part of that file; it goes to
``extrinsics.yaml``::

    base_frame: base_link
    cameras:
      cam1:
        frame_id: cam1_optical_frame
        translation: [x, y, z]        # optical-frame origin in base_frame, metres
        rotation: [qx, qy, qz, qw]    # optical-frame orientation in base_frame

i.e. T_base_camera in the TF convention.  Every write goes to a temporary file in the target
directory first and is moved into place with ``os.replace``, so a reader never sees half a file.
"""

import os
import re
import tempfile

import numpy as np
import yaml

from armcal_ros.core.camera import Camera

_NAME_RE = re.compile(r'^[A-Za-z0-9_]+$')


def validate_camera_name(name):
    """Return ``name`` if it is a non-empty [A-Za-z0-9_] string, else raise ValueError."""
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(f'camera name must match [A-Za-z0-9_]+, got {name!r}')
    return name


def atomic_write_text(path, text):
    """Write ``text`` to ``path`` through a temporary file in the same directory and os.replace."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.', dir=directory)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)       # mkstemp makes 0600; give the usual mode
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _matrix(rows, cols, values):
    return {'rows': int(rows), 'cols': int(cols),
            'data': [float(v) for v in np.asarray(values, float).reshape(-1)]}


def camera_info_dict(cam: Camera, camera_name=None):
    """Return the camera_calibration_parsers dictionary for ``cam`` (monocular, plumb_bob)."""
    name = validate_camera_name(camera_name if camera_name is not None else cam.name)
    K = cam.K
    P = np.hstack([K, np.zeros((3, 1))])
    return {
        'image_width': int(cam.width),
        'image_height': int(cam.height),
        'camera_name': name,
        'camera_matrix': _matrix(3, 3, K),
        'distortion_model': 'plumb_bob',
        'distortion_coefficients': _matrix(1, 5, cam.dist),
        'rectification_matrix': _matrix(3, 3, np.eye(3)),
        'projection_matrix': _matrix(3, 4, P),
    }


def camera_info_yaml(cam: Camera, camera_name=None):
    """Return the camera_info YAML text for ``cam``."""
    return yaml.safe_dump(camera_info_dict(cam, camera_name), sort_keys=False,
                          default_flow_style=None)


def write_camera_info(path, cam: Camera, camera_name=None):
    """Write ``cam``'s intrinsics and distortion to ``path`` (atomic)."""
    atomic_write_text(path, camera_info_yaml(cam, camera_name))


def _read_matrix(doc, key, rows, cols, path):
    m = doc.get(key)
    if not isinstance(m, dict) or 'data' not in m:
        raise ValueError(f'{path}: {key} must be a mapping with rows, cols, data')
    data = np.asarray(m['data'], float).reshape(-1)
    if int(m.get('rows', rows)) != rows or int(m.get('cols', cols)) != cols \
            or data.size != rows * cols:
        raise ValueError(f'{path}: {key} must be {rows}x{cols}, got rows={m.get("rows")} '
                         f'cols={m.get("cols")} with {data.size} values')
    return data.reshape(rows, cols)


def camera_from_info_dict(doc, source='camera_info'):
    """Build a :class:`Camera` (identity pose) from a camera_calibration_parsers dictionary."""
    if not isinstance(doc, dict):
        raise ValueError(f'{source}: expected a YAML mapping')
    for key in ('image_width', 'image_height', 'camera_matrix', 'distortion_coefficients'):
        if key not in doc:
            raise ValueError(f'{source}: missing {key}')
    model = doc.get('distortion_model', 'plumb_bob')
    if model != 'plumb_bob':
        raise ValueError(f'{source}: distortion_model must be plumb_bob, got {model!r}')
    K = _read_matrix(doc, 'camera_matrix', 3, 3, source)
    dist = np.asarray(doc['distortion_coefficients']['data'], float).reshape(-1)
    if dist.size != 5:
        raise ValueError(f'{source}: plumb_bob needs 5 distortion coefficients, got {dist.size}')
    name = validate_camera_name(str(doc.get('camera_name', 'camera')))
    return Camera(name, int(doc['image_width']), int(doc['image_height']),
                  K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist)


def read_camera_info(path, name=None):
    """
    Read a camera_info YAML file into a :class:`Camera` with identity pose.

    ``name`` replaces the file's ``camera_name`` (a driver's name, '/' included, is then not
    checked: only K, D and the image size are wanted).
    """
    with open(path, encoding='utf-8') as f:
        doc = yaml.safe_load(f)
    if name is not None and isinstance(doc, dict):
        doc = dict(doc, camera_name=name)
    return camera_from_info_dict(doc, source=os.fspath(path))


def extrinsics_dict(cameras, base_frame='base_link'):
    """Return the extrinsics.yaml dictionary for a list of cameras (T_base_camera each)."""
    if not isinstance(base_frame, str) or not base_frame:
        raise ValueError(f'base_frame must be a non-empty string, got {base_frame!r}')
    out = {}
    for cam in cameras:
        name = validate_camera_name(cam.name)
        if name in out:
            raise ValueError(f'cameras: duplicate camera name {name!r}')
        t, q = cam.pose_in_world()
        out[name] = {'frame_id': f'{name}_optical_frame',
                     'translation': [float(v) for v in t],
                     'rotation': [float(v) for v in q]}
    return {'base_frame': base_frame, 'cameras': out}


def write_extrinsics(path, cameras, base_frame='base_link'):
    """Write the cameras' poses in ``base_frame`` to ``path`` (atomic)."""
    text = yaml.safe_dump(extrinsics_dict(cameras, base_frame), sort_keys=False,
                          default_flow_style=None)
    atomic_write_text(path, text)


def read_extrinsics(path):
    """
    Read extrinsics.yaml.

    Returns (base_frame, {name: (translation (3,), quaternion [qx, qy, qz, qw] (4,), frame_id)}).
    """
    with open(path, encoding='utf-8') as f:
        doc = yaml.safe_load(f)
    if not isinstance(doc, dict) or 'cameras' not in doc:
        raise ValueError(f'{path}: expected a mapping with base_frame and cameras')
    base = str(doc.get('base_frame', 'base_link'))
    out = {}
    for name, entry in (doc['cameras'] or {}).items():
        validate_camera_name(str(name))
        t = np.asarray(entry['translation'], float).reshape(-1)
        q = np.asarray(entry['rotation'], float).reshape(-1)
        if t.size != 3 or q.size != 4:
            raise ValueError(f'{path}: camera {name}: translation needs 3 and rotation 4 values')
        if not np.isfinite(q).all() or abs(np.linalg.norm(q) - 1.0) > 1e-6:
            raise ValueError(f'{path}: camera {name}: rotation must be a unit quaternion')
        out[str(name)] = (t, q, str(entry.get('frame_id', f'{name}_optical_frame')))
    return base, out


def apply_extrinsics(cam: Camera, translation, quat_xyzw):
    """Return a copy of ``cam`` with its pose set from T_base_camera."""
    posed = Camera.from_pose_in_world(cam.name, cam.width, cam.height, cam.K, cam.dist,
                                      translation, quat_xyzw)
    return posed


def read_cameras(directory, names=None):
    """
    Read ``<name>.yaml`` and ``extrinsics.yaml`` from ``directory`` into posed cameras.

    ``names`` defaults to the cameras listed in extrinsics.yaml, in file order.
    Returns (base_frame, [Camera]).
    """
    base, poses = read_extrinsics(os.path.join(directory, 'extrinsics.yaml'))
    names = list(poses) if names is None else list(names)
    cams = []
    for name in names:
        if name not in poses:
            raise ValueError(f'names: camera {name!r} is not in {directory}/extrinsics.yaml')
        cam = read_camera_info(os.path.join(directory, f'{validate_camera_name(name)}.yaml'))
        cam.name = name
        t, q, _ = poses[name]
        cams.append(apply_extrinsics(cam, t, q))
    return base, cams


def write_cameras(directory, cameras, base_frame='base_link'):
    """Write ``<name>.yaml`` for every camera and ``extrinsics.yaml`` into ``directory``."""
    for cam in cameras:
        write_camera_info(os.path.join(directory, f'{validate_camera_name(cam.name)}.yaml'), cam)
    write_extrinsics(os.path.join(directory, 'extrinsics.yaml'), cameras, base_frame)
