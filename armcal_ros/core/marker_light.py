"""
A matte ball lit from one side: where its image's intensity centroid lies, and the correction.

A sphere detector measures the intensity-weighted centroid of the ball's image.  A ball that
glows alike from every side has its centroid at its centre's image; a matte (Lambertian) ball
lit by one lamp is brighter towards the lamp, and its centroid moves that way by a fraction of
its image radius - differently in every camera, since each sees the lit side at another angle
(bench/realism.py: 0.5-0.6 px for a 5 mm ball at 1.5 m under a lamp 1.5 m above the cell).

Model.  Seen along the viewing ray e3 (camera to ball), with e1, e2 completing a right-handed
frame, the visible hemisphere's normal at the disc point (x, y) (units of the ball's radius) is
n = x e1 + y e2 - sqrt(1 - x^2 - y^2) e3, and its brightness with a unit vector l to the lamp
and an ambient fraction a is I = a + (1 - a) max(0, n . l).  The centroid of I over the disc,
(c1, c2) = int (x, y) I / int I, is the offset of the image centroid on the plane through the
centre perpendicular to the ray, in units of the radius r: the 3-D offset r (c1 e1 + c2 e2)
maps to pixels through the projection's Jacobian (distortion and obliquity included).  Blur
and motion do not move a centroid.  For l perpendicular to the ray and a = 0.25 the offset is
(1 - a)(pi / 8) / (a pi + (1 - a) 2 / 3) = 0.229 r; the renderer's centroids agree within
0.01 px (test_core_marker_light.py).
"""

import numpy as np

from armcal_ros.core.camera import project_with_jacobians

#: Points per axis of the disc's quadrature: a 96 x 96 grid puts the centroid within 1e-4 of the
#: radius of the exact integral.
GRID = 96


def centroid_offset(l_ray, ambient):
    """
    Return (c1, c2): the disc centroid of a lit matte ball, units of its radius (module doc).

    ``l_ray`` (3,) is the unit vector to the lamp in the ray frame (e1, e2, e3 = the viewing
    ray); ``ambient`` the brightness of the unlit side as a fraction of full light.
    """
    l_ray = np.asarray(l_ray, float).reshape(3)
    if not 0.0 <= ambient <= 1.0:
        raise ValueError(f'ambient must be in [0, 1], got {ambient}')
    g = (np.arange(GRID) + 0.5) / GRID * 2.0 - 1.0
    x, y = np.meshgrid(g, g)
    inside = x * x + y * y <= 1.0
    x, y = x[inside], y[inside]
    z = np.sqrt(1.0 - x * x - y * y)
    light = ambient + (1.0 - ambient) * np.maximum(x * l_ray[0] + y * l_ray[1] - z * l_ray[2],
                                                   0.0)
    return np.array([(x * light).sum(), (y * light).sum()]) / light.sum()


def _ray_frame(ray):
    """Return (e1, e2, e3) with e3 = ``ray`` (unit) and e1 close to the camera's x axis."""
    e3 = ray / np.linalg.norm(ray)
    e1 = np.array([1.0, 0.0, 0.0]) - e3[0] * e3
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(e3, e1), e3


def image_offsets(cameras, camera_index, points, lamp, ambient, radius):
    """
    Return (M, 2) pixel offsets of lit-ball centroids from their centres' images.

    ``cameras`` a list of :class:`~armcal_ros.core.camera.Camera`; observation m is the ball
    at world point ``points[m]`` seen by ``cameras[camera_index[m]]``; ``lamp`` (3,) the lamp's
    world position, ``ambient`` as in :func:`centroid_offset`, ``radius`` the ball's (m).
    A detector's centroid minus the returned offset is the centre's image.
    """
    points = np.asarray(points, float).reshape(-1, 3)
    camera_index = np.asarray(camera_index, int).reshape(-1)
    if camera_index.shape[0] != points.shape[0]:
        raise ValueError(f'camera_index has {camera_index.shape[0]} entries for '
                         f'{points.shape[0]} points')
    if not radius > 0:
        raise ValueError(f'radius must be > 0 (m), got {radius}')
    lamp = np.asarray(lamp, float).reshape(3)
    out = np.zeros((len(points), 2))
    for m, (j, X) in enumerate(zip(camera_index, points)):
        cam = cameras[j]
        Xc = cam.to_camera(X[None])[0]
        if Xc[2] <= 0:
            continue
        e1, e2, e3 = _ray_frame(Xc)
        to_lamp = cam.rotation @ (lamp - X)
        to_lamp /= np.linalg.norm(to_lamp)
        c = centroid_offset([to_lamp @ e1, to_lamp @ e2, to_lamp @ e3], ambient)
        offset_world = cam.rotation.T @ (radius * (c[0] * e1 + c[1] * e2))
        J = project_with_jacobians(cam.intrinsics(), cam.dist, cam.rotation, cam.translation,
                                   X[None]).d_point[0]
        out[m] = J @ offset_world
    return out
