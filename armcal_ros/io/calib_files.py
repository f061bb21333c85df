"""
Calibration files: ``camera_info`` YAML (and INI) and ``extrinsics.yaml``.

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

Reading is wider than writing: :func:`read_camera_info_file` takes every file that ROS's own
tools write, whatever the camera's name or distortion model, as a :class:`CameraInfoFile`:

- the YAML of camera_calibration_parsers (yaml-cpp's layout, what camera_info_manager saves) and
  of camera_calibration (``ost.yaml``, ``left.yaml``/``right.yaml`` of a stereo pair);
- the INI format of camera_calibration_parsers (``.ini``) and camera_calibration's ``ost.txt``
  (``# oST version 5.0 parameters``): an ``[image]`` section (``width``, ``height``), then a
  ``[<camera name>]`` section with ``camera matrix``, ``distortion``, ``rectification`` and
  ``projection``, each key on its own line and the matrix rows under it.  A stereo ``ost.txt``
  holds two cameras (:func:`read_camera_info_sections`).  The INI format has no model name: a
  distortion row of 5 values is plumb_bob and of 6 or more rational_polynomial (as
  camera_calibration_parsers reads it); of 4 values it is camera_calibration's fisheye model
  (``equidistant``: its only model with 4 coefficients).

What the estimator can use is a separate, explicit step, :func:`camera_from_info_file`: armcal's
:class:`Camera` is plumb_bob (k1, k2, p1, p2, k3), so a file converts when its distortion *is*
plumb_bob (any model whose coefficients beyond those five are zero), and is refused otherwise
with a message that says which model and which coefficients.
"""

from dataclasses import dataclass
import math
import os
import re
import tempfile
from typing import List

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


#: OpenCV's names of the coefficients of D, in order (plumb_bob is the first five).
OPENCV_DISTORTION_NAMES = ('k1', 'k2', 'p1', 'p2', 'k3', 'k4', 'k5', 'k6', 's1', 's2', 's3',
                           's4', 'tauX', 'tauY')
#: The names of D for OpenCV's fisheye model (sensor_msgs' ``equidistant``).
FISHEYE_DISTORTION_NAMES = ('k1', 'k2', 'k3', 'k4')
#: What to do about a model armcal cannot use, for a calibration file.
FILE_ADVICE = ('armcal fits plumb_bob (k1, k2, p1, p2, k3): calibrate the lens with a plumb_bob '
               'model, or give no intrinsics file and let armcal estimate them')


@dataclass
class CameraInfoFile:
    """
    One camera of a calibration file, as the file has it: nothing dropped, nothing renamed.

    ``camera_name`` is the file's own name, verbatim (``narrow_stereo/left`` and the like),
    ``distortion_model`` the model the file names (``plumb_bob``, ``rational_polynomial``,
    ``equidistant``, ...), ``D`` its coefficients in the file's order, however many, ``K``
    (3, 3), ``R`` (3, 3) the rectification and ``P`` (3, 4) the projection matrix.  ``source``
    says where it was read from, for messages.
    """

    camera_name: str
    width: int
    height: int
    K: np.ndarray
    distortion_model: str
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    source: str = ''


def sanitize_camera_name(name):
    """Return ``name`` with every character outside [A-Za-z0-9_] made '_' ('camera' if empty)."""
    out = re.sub(r'[^A-Za-z0-9_]', '_', str(name))
    return out or 'camera'


def _number(value, where):
    """Return ``value`` (a YAML or INI number, or a string of one) as a finite float."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ValueError(f'{where}: {value!r} is not a number')
    try:
        x = float(value)
    except ValueError:
        raise ValueError(f'{where}: {value!r} is not a number') from None
    if not math.isfinite(x):
        raise ValueError(f'{where}: {value!r} is not a finite number')
    return x


def _whole(value, where):
    x = _number(value, where)
    if x != int(x) or x < 0:
        raise ValueError(f'{where}: must be a whole number >= 0, got {value!r}')
    return int(x)


def _yaml_matrix(doc, key, shape, source):
    """Return ``doc[key]`` ({rows, cols, data}) as a ``shape`` array, or as a vector if None."""
    where = f'{source}: {key}'
    m = doc[key]
    if not isinstance(m, dict) or 'data' not in m:
        raise ValueError(f'{where} must be a mapping with rows, cols and data')
    if not isinstance(m['data'], list):
        raise ValueError(f'{where}: data must be a list of numbers, got {m["data"]!r}')
    values = np.array([_number(v, f'{where}: data[{i}]') for i, v in enumerate(m['data'])],
                      dtype=float)
    rows = _whole(m['rows'], f'{where}: rows') if 'rows' in m else None
    cols = _whole(m['cols'], f'{where}: cols') if 'cols' in m else None
    if shape is not None:
        r, c = shape
        if rows not in (None, r) or cols not in (None, c) or values.size != r * c:
            raise ValueError(f'{where} must be {r}x{c}, got rows={m.get("rows")} '
                             f'cols={m.get("cols")} with {values.size} values')
        return values.reshape(r, c)
    if rows is not None and cols is not None and rows * cols != values.size:
        raise ValueError(f'{where}: rows x cols is {rows} x {cols} but data has '
                         f'{values.size} values')
    if rows not in (None, 0, 1) and cols not in (None, 0, 1):
        raise ValueError(f'{where} must be one row (or one column), got {rows}x{cols}')
    return values


def _yaml_text(doc, raw, key, default, source):
    """Return the scalar ``doc[key]`` as the file writes it (``raw``), or ``default``."""
    if key not in doc:
        return default
    value = doc[key]
    if isinstance(value, (dict, list)):
        raise ValueError(f'{source}: {key} must be a single value, got {value!r}')
    if raw is not None and key in raw:
        return raw[key]
    return '' if value is None else str(value)


def info_file_from_dict(doc, source='camera_info', raw=None) -> CameraInfoFile:
    """
    Return the :class:`CameraInfoFile` of a camera_calibration_parsers dictionary.

    Required: ``image_width``, ``image_height``, ``camera_matrix`` and
    ``distortion_coefficients``.  As camera_calibration_parsers does, a missing
    ``distortion_model`` is plumb_bob and a missing ``camera_name`` 'unknown'; a missing
    ``rectification_matrix`` is the identity and a missing ``projection_matrix`` [K | 0] (the
    monocular convention).  ``raw`` maps keys to their scalar text as written, so that a name
    YAML would read as a number or a boolean is kept verbatim.
    """
    if not isinstance(doc, dict):
        raise ValueError(f'{source}: expected a YAML mapping (the camera_calibration_parsers '
                         f'format), got {type(doc).__name__}')
    for key in ('image_width', 'image_height', 'camera_matrix', 'distortion_coefficients'):
        if key not in doc:
            raise ValueError(f'{source}: missing key {key}')
    K = _yaml_matrix(doc, 'camera_matrix', (3, 3), source)
    D = _yaml_matrix(doc, 'distortion_coefficients', None, source)
    R = (_yaml_matrix(doc, 'rectification_matrix', (3, 3), source)
         if 'rectification_matrix' in doc else np.eye(3))
    P = (_yaml_matrix(doc, 'projection_matrix', (3, 4), source)
         if 'projection_matrix' in doc else np.hstack([K, np.zeros((3, 1))]))
    return CameraInfoFile(
        camera_name=_yaml_text(doc, raw, 'camera_name', 'unknown', source),
        width=_whole(doc['image_width'], f'{source}: image_width'),
        height=_whole(doc['image_height'], f'{source}: image_height'),
        K=K, distortion_model=_yaml_text(doc, raw, 'distortion_model', 'plumb_bob', source),
        D=D, R=R, P=P, source=source)


def _yaml_scalars(text):
    """Return {key: scalar text as written} of the top-level mapping of a YAML document."""
    node = yaml.compose(text, Loader=yaml.SafeLoader)
    out = {}
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            if isinstance(key, yaml.ScalarNode) and isinstance(value, yaml.ScalarNode):
                out[key.value] = value.value
    return out


def _read_yaml(text, source):
    try:
        doc = yaml.safe_load(text)
        raw = _yaml_scalars(text)
    except yaml.YAMLError as exc:
        raise ValueError(f'{source}: not valid YAML: {exc}') from exc
    return [info_file_from_dict(doc, source, raw)]


def _ini_rows(lines, at, key, rows, cols, where):
    """Return the ``rows`` lines after ``lines[at]`` as numbers (``cols`` each, None: any)."""
    out = []
    for i in range(rows):
        if at + 1 + i >= len(lines):
            raise ValueError(f'{where}: {key} needs {rows} row(s), the section ends after '
                             f'{i}')
        lineno, text = lines[at + 1 + i]
        values = [_number(v, f'{where}: {key}, line {lineno}') for v in text.split()]
        if cols is not None and len(values) != cols:
            raise ValueError(f'{where}: {key}, line {lineno}: expected {cols} numbers, got '
                             f'{text!r}')
        out.append(values)
    return out


def _ini_key(lines, key, where):
    for i, (_, text) in enumerate(lines):
        if text == key:
            return i
    raise ValueError(f'{where}: missing key {key!r}')


def _ini_model(D, where):
    if D.size == 4:
        return 'equidistant'
    if D.size == 5:
        return 'plumb_bob'
    if D.size >= 6:
        return 'rational_polynomial'
    raise ValueError(f'{where}: distortion has {D.size} values; the INI format has 5 '
                     '(plumb_bob), 8 (rational_polynomial) or 4 (fisheye)')


def _read_ini(text, source):
    """Return the cameras of an INI calibration (camera_calibration_parsers, ost.txt)."""
    sections = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s[0] in '#;':
            continue
        if s.startswith('[') and s.endswith(']'):
            sections.append((s[1:-1], []))
        elif not sections:
            raise ValueError(f'{source}: line {lineno}: {s!r} is outside any [section]')
        else:
            sections[-1][1].append((lineno, s))
    images = [k for k, (name, _) in enumerate(sections) if name == 'image']
    if not images:
        raise ValueError(f'{source}: missing section [image] (width, height)')
    out = []
    for k, (name, lines) in enumerate(sections):
        if name in ('image', 'externals'):
            continue
        where = f'{source}: [{name}]'
        image = max([i for i in images if i < k], default=images[0])
        img_where = f'{source}: [image]'
        img_lines = sections[image][1]
        size = [_whole(_ini_rows(img_lines, _ini_key(img_lines, key, img_where), key, 1, 1,
                                 img_where)[0][0], f'{img_where}: {key}')
                for key in ('width', 'height')]
        K = np.array(_ini_rows(lines, _ini_key(lines, 'camera matrix', where), 'camera matrix',
                               3, 3, where))
        D = np.array(_ini_rows(lines, _ini_key(lines, 'distortion', where), 'distortion', 1,
                               None, where)[0])
        R = np.array(_ini_rows(lines, _ini_key(lines, 'rectification', where), 'rectification',
                               3, 3, where))
        P = np.array(_ini_rows(lines, _ini_key(lines, 'projection', where), 'projection', 3, 4,
                               where))
        out.append(CameraInfoFile(name, size[0], size[1], K, _ini_model(D, where), D, R, P,
                                  source))
    if not out:
        raise ValueError(f'{source}: no camera section ([<camera name>] with camera matrix, '
                         'distortion, rectification, projection)')
    return out


def _is_ini(path, text):
    """Tell the INI format by the extension, else by the first line that is not a comment."""
    ext = os.path.splitext(path)[1].lower()
    if ext in ('.ini', '.txt'):
        return True
    if ext in ('.yaml', '.yml'):
        return False
    for line in text.splitlines():
        s = line.strip()
        if s and s[0] not in '#;':
            return s.startswith('[')
    return False


def read_camera_info_sections(path) -> List[CameraInfoFile]:
    """
    Return every camera of a calibration file, in file order.

    A YAML file holds one; an INI file one per camera section (camera_calibration's stereo
    ``ost.txt`` holds ``<name>/left`` and ``<name>/right``).  ValueError, naming the file and
    the key, for a malformed file (a missing key, a matrix of the wrong size, a value that is
    not a finite number); never for the camera's name or its distortion model.
    """
    source = os.fspath(path)
    try:
        with open(path, encoding='utf-8') as f:
            text = f.read()
    except UnicodeDecodeError as exc:
        raise ValueError(f'{source}: not a text file: {exc}') from exc
    return _read_ini(text, source) if _is_ini(source, text) else _read_yaml(text, source)


def read_camera_info_file(path, camera_name=None) -> CameraInfoFile:
    """
    Read the calibration of one camera, YAML or INI, as the file has it.

    ``camera_name`` picks a camera of a file that holds several (a stereo ``ost.txt``); a file
    of several cameras read without it (or with a name none of them has) is refused, naming
    them.  A file of one camera gives that camera, whatever its name.
    """
    cams = read_camera_info_sections(path)
    if camera_name is not None:
        cams = [c for c in cams if c.camera_name == camera_name] or cams
    if len(cams) > 1:
        names = ', '.join(repr(c.camera_name) for c in cams)
        raise ValueError(f'{os.fspath(path)}: holds {len(cams)} cameras ({names}); give the '
                         'file of one camera (camera_calibration writes left.yaml and '
                         'right.yaml beside its stereo ost.txt)')
    return cams[0]


def _nonzero_beyond(model, D, usable):
    """Return ['name=value'] of the coefficients of D from index ``usable`` on that are not 0."""
    if model in ('plumb_bob', 'rational_polynomial'):
        names = OPENCV_DISTORTION_NAMES
    elif model in ('equidistant', 'fisheye'):
        names = FISHEYE_DISTORTION_NAMES
    else:
        names = ()
    return [f'{names[i] if i < len(names) else f"D[{i}]"}={D[i]:.6g}'
            for i in range(usable, D.size) if D[i] != 0]


def plumb_bob_coefficients(model, D, source='camera_info', advice=FILE_ADVICE):
    """
    Return the plumb_bob (k1, k2, p1, p2, k3) that distortion ``model`` with ``D`` amounts to.

    - ``plumb_bob``: D as is; fewer than 5 values are padded with zeros (4 values: k3 = 0),
      more than 5 must be zeros;
    - ``rational_polynomial``: the first five, when k4, k5, k6 and any further coefficient
      (thin prism s1-s4, tilt tauX, tauY) are zero: the rational model is then plumb_bob;
    - ``equidistant`` (and any other model): all coefficients zero, i.e. no distortion.

    Anything else raises ValueError: the model cannot be estimated or used by armcal, with the
    non-zero coefficients named and ``advice`` said.
    """
    D = np.asarray(D, dtype=float).reshape(-1)
    if not np.all(np.isfinite(D)):
        raise ValueError(f'{source}: the distortion coefficients must be finite, got {D}')
    usable = 5 if model in ('plumb_bob', 'rational_polynomial') else 0
    extra = _nonzero_beyond(model, D, usable)
    if extra:
        raise ValueError(
            f'{source}: read, but its distortion model {model!r} cannot be estimated or used by '
            f'armcal: {", ".join(extra)} {"is" if len(extra) == 1 else "are"} not zero. '
            f'{advice}')
    out = np.zeros(5)
    n = min(usable, D.size)
    out[:n] = D[:n]
    return out


def camera_from_info_file(info: CameraInfoFile, name=None, advice=FILE_ADVICE) -> Camera:
    """
    Return the :class:`Camera` (identity pose) of a calibration, if armcal can use it.

    ``name`` is the Camera's name; by default the file's camera_name made a valid armcal name
    (:func:`sanitize_camera_name`).  The distortion goes through :func:`plumb_bob_coefficients`;
    K must be a pinhole matrix without skew, and calibrated (K[0] != 0).  R and P are not used:
    the Camera describes the raw (unrectified) image, as K and D do.
    """
    source = info.source or 'camera_info'
    K = np.asarray(info.K, dtype=float).reshape(3, 3)
    if K[0, 0] == 0:
        raise ValueError(f'{source}: K[0] == 0 means uncalibrated')
    if K[0, 0] < 0 or K[1, 1] <= 0 or K[0, 1] != 0 or K[1, 0] != 0 \
            or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f'{source}: read, but its camera matrix cannot be used by armcal: it '
                         f'must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got '
                         f'{K.tolist()}')
    dist = plumb_bob_coefficients(info.distortion_model, info.D, source, advice)
    cam_name = name if name is not None else sanitize_camera_name(info.camera_name)
    return Camera(cam_name, int(info.width), int(info.height), K[0, 0], K[1, 1], K[0, 2],
                  K[1, 2], dist)


def camera_from_info_dict(doc, source='camera_info'):
    """Build a :class:`Camera` (identity pose) from a camera_calibration_parsers dictionary."""
    return camera_from_info_file(info_file_from_dict(doc, source))


def read_camera_info(path, name=None):
    """
    Read a calibration file (YAML or INI) into a :class:`Camera` with identity pose.

    Any file of camera_calibration or camera_calibration_parsers is read
    (:func:`read_camera_info_file`), then converted if armcal can use its distortion model
    (:func:`camera_from_info_file`).  ``name`` is the Camera's name; without it the file's
    camera_name, made a valid armcal name ('narrow_stereo/left' -> 'narrow_stereo_left').
    """
    return camera_from_info_file(read_camera_info_file(path), name)


def extrinsics_dict(cameras, base_frame='base_link', frame_ids=None):
    """
    Return the extrinsics.yaml dictionary for a list of cameras (T_base_camera each).

    ``frame_ids`` maps a camera name to its optical frame (the frame_id its images carry);
    a camera not in it gets ``<name>_optical_frame``.
    """
    frame_ids = frame_ids or {}
    if not isinstance(base_frame, str) or not base_frame:
        raise ValueError(f'base_frame must be a non-empty string, got {base_frame!r}')
    out = {}
    for cam in cameras:
        name = validate_camera_name(cam.name)
        if name in out:
            raise ValueError(f'cameras: duplicate camera name {name!r}')
        t, q = cam.pose_in_world()
        out[name] = {'frame_id': str(frame_ids.get(name) or f'{name}_optical_frame'),
                     'translation': [float(v) for v in t],
                     'rotation': [float(v) for v in q]}
    return {'base_frame': base_frame, 'cameras': out}


def write_extrinsics(path, cameras, base_frame='base_link', frame_ids=None):
    """Write the cameras' poses in ``base_frame`` to ``path`` (atomic); see extrinsics_dict."""
    text = yaml.safe_dump(extrinsics_dict(cameras, base_frame, frame_ids), sort_keys=False,
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


def write_cameras(directory, cameras, base_frame='base_link', frame_ids=None):
    """Write ``<name>.yaml`` for every camera and ``extrinsics.yaml`` into ``directory``."""
    for cam in cameras:
        write_camera_info(os.path.join(directory, f'{validate_camera_name(cam.name)}.yaml'), cam)
    write_extrinsics(os.path.join(directory, 'extrinsics.yaml'), cameras, base_frame, frame_ids)
