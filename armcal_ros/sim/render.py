"""
Rendering a bright sphere marker into a camera image, with a physically plain sensor model.

Geometry
--------
The marker is a diffusely glowing sphere (an LED behind a diffusing ball) of radius r, so its
image is a uniformly bright region: the set of pixels whose viewing ray meets the sphere.  A
pixel's coverage is computed by supersampling: S x S sub-pixel points per pixel are
undistorted (the exact inverse of the plumb_bob model, by fixed-point iteration) to viewing
rays d = (x, y, 1), and a ray hits the sphere of centre C (camera frame) iff
|C x d|^2 <= r^2 |d|^2 with C . d > 0.  Pixel (u, v) covers [u - 1/2, u + 1/2] x [v - 1/2,
v + 1/2] (OpenCV's convention: integer coordinates are pixel centres).

Which point is the truth
------------------------
The ground truth of an observation is the projection pi(C) of the sphere's centre: that is the
point the calibrator models (the marker position is the centre's, from FK).  The image of a
sphere is not centred on pi(C), though: the tangent cone meets the image plane in an ellipse
whose centre lies further from the principal point.  With angular radius a = asin(r / |C|)
and field angle t of the centre, in an undistorted image the ellipse centre is at
f (tan(t + a) + tan(t - a)) / 2 = f tan t + f a^2 tan t / cos^2 t + O(a^4) along the radial
direction (:func:`sphere_image_offset`).  For r = 5 mm at 1.75 m (a = 2.9 mrad), f = 800 px
and t up to 27 deg (the corner of a 640 x 480 image) this is at most 0.004 px; lens
distortion across a disc of a few pixels adds less.  So a centroid detector measures pi(C) to
well under 0.01 px, and the simulator stores pi(C).

Sensor
------
A short-exposure camera watching an LED marker (like a motion-capture camera): the exposure
(2 ms by default) is set for the marker, so the rest of the scene stays at the black level.
The signal in DN is ``peak * coverage * vignetting`` where vignetting is the natural
cos^4 law of the field angle, blurred by a Gaussian point-spread (defocus, sigma growing with
the distance from the focus plane) and averaged over the exposure (motion blur).  Then shot
noise (Poisson in electrons, ``gain`` e-/DN), read noise (Gaussian, ``read_noise`` DN),
black level, rounding and clipping to 8 bits.  With a full well of ~10,000 e- spread over 255
DN (gain 40 e-/DN) a 2-3 e- read noise is 0.06 DN, so a background pixel rounds to the black
level with probability 1 - 2 Q(0.5 / 0.06) ~ 1 - 1e-16: the model therefore adds read noise
only where there is signal when ``read_noise`` < 0.1 DN (identical in distribution to that
precision), and everywhere otherwise.  Spurious highlights (glints off the arm) are small
Gaussian specks of random brightness, now and then close to the marker.

A lamp (off by default, ``SensorModel.lamp``): a matte white ball lit by one lamp is shaded -
bright towards the lamp, down to an ``ambient`` fraction on its far side - and which side each
camera sees bright depends on where it stands.  Its intensity centroid then moves towards the
lit side by a fraction of the image radius, differently in every camera: the bias a real
marker's appearance brings (bench/realism.py measures what it does to the detector).

Clutter (off by default): a camera exposed for the scene rather than for the marker sees the
cell behind it.  ``clutter_level`` > 0 gives each camera a static scene (:func:`clutter_scene`):
shaded surfaces, boxes, discs and bars of random brightness around that level, with sharp
edges; ``clutter_spots`` adds static round bright spots the size and brightness of the
marker (indicator lamps, polished bolt heads) - look-alikes only their stillness gives away.
Shot and read noise then apply to every pixel.  The ball is opaque: it hides the scene in
proportion to its blurred coverage, so a lit ball's unlit side is darker than a brighter
scene it stands before.

An LED in a diffusing ball (``SensorModel.led_axis``) is brightest where the LED points, with
an angular fall-off; the bright side turns with the tool, so its centroid's offset depends on
the tool's orientation as well as on the camera.
"""

from dataclasses import dataclass
import math
from typing import Optional

import numpy as np
from scipy.ndimage import gaussian_filter

from armcal_ros.core.camera import undistort_normalized


@dataclass
class SensorModel:
    """Image formation settings (see the module docstring); DN are 8-bit digital numbers."""

    peak: float = 190.0             # marker brightness at the image centre, DN
    black_level: float = 2.0        # DN
    gain: float = 40.0              # electrons per DN
    read_noise: float = 0.06        # DN (2.4 e-)
    defocus_sigma: float = 0.6      # px, point-spread at the focus distance
    defocus_slope: float = 1.0      # px of extra sigma per metre away from focus
    exposure: float = 0.002         # s
    motion_samples: int = 5         # instants averaged over the exposure
    supersample: int = 8            # sub-pixels per pixel and axis
    vignetting: bool = True         # natural cos^4 fall-off
    glint_rate: float = 0.05        # expected spurious highlights per frame
    glint_near_marker: float = 0.3  # fraction of glints within 40 px of the marker
    colour_gains: tuple = (1.0, 0.95, 0.85)   # R, G, B response to the (white) LED
    clutter_level: float = 0.0      # DN, mean brightness of a static scene (0: black)
    clutter_spots: int = 0          # static marker look-alikes per camera
    #: Lighting of the marker: None, a sphere that glows alike from every side (its image's
    #: intensity centroid is its centre's image); or the base-frame position (m) of one lamp
    #: shading a matte (Lambertian) ball, with ``ambient`` the fraction of ``peak`` its unlit
    #: side still has.  Which side is bright depends on where each camera stands.
    lamp: Optional[tuple] = None
    ambient: float = 0.25
    #: Or an LED in a diffusing ball: the unit vector (marker link frame) the LED points
    #: along.  Its light reaches the inside of the diffuser as cos^m of the angle off that
    #: axis (``led_falloff`` m: 1 for a Lambertian LED, larger for a narrower beam) and the
    #: diffuser re-emits it, so the ball's surface at normal n is ``ambient`` +
    #: (1 - ``ambient``) max(0, n . a)^m: brightest where the LED points, and that side turns
    #: with the tool.
    led_axis: Optional[tuple] = None
    led_falloff: float = 1.0
    #: Auto-exposure in steps: (period s, largest factor F): every period each camera's
    #: exposure (the marker's and the scene's brightness) is set anew to a factor in
    #: [1/F, F], log-uniform; () keeps it fixed.
    exposure_steps: tuple = ()

    def __post_init__(self):
        for name in ('peak', 'gain', 'exposure'):
            if getattr(self, name) <= 0:
                raise ValueError(f'{name} must be > 0, got {getattr(self, name)}')
        for name in ('black_level', 'read_noise', 'defocus_sigma', 'defocus_slope',
                     'glint_rate', 'clutter_level', 'clutter_spots'):
            if getattr(self, name) < 0:
                raise ValueError(f'{name} must be >= 0, got {getattr(self, name)}')
        if int(self.supersample) < 1 or int(self.motion_samples) < 1:
            raise ValueError('supersample and motion_samples must be >= 1')
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f'ambient must be in [0, 1], got {self.ambient}')
        if self.lamp is not None:
            lamp = np.asarray(self.lamp, float)
            if lamp.shape != (3,) or not np.all(np.isfinite(lamp)):
                raise ValueError(f'lamp must be 3 finite numbers (m, base frame), got {self.lamp}')
            self.lamp = tuple(float(v) for v in lamp)
        if self.led_axis is not None:
            axis = np.asarray(self.led_axis, float)
            if axis.shape != (3,) or not np.all(np.isfinite(axis)) or \
                    not np.linalg.norm(axis) > 0:
                raise ValueError(f'led_axis must be 3 finite numbers, not all 0, got '
                                 f'{self.led_axis}')
            if self.lamp is not None:
                raise ValueError('lamp and led_axis are two kinds of marker: give one')
            self.led_axis = tuple(float(v) for v in axis / np.linalg.norm(axis))
        if not (np.isfinite(self.led_falloff) and self.led_falloff > 0):
            raise ValueError(f'led_falloff must be > 0, got {self.led_falloff}')
        if self.exposure_steps:
            steps = tuple(float(v) for v in self.exposure_steps)
            if len(steps) != 2 or not (steps[0] > 0 and 1.0 <= steps[1] <= 10.0):
                raise ValueError(f'exposure_steps must be (period s > 0, largest factor in '
                                 f'[1, 10]), got {self.exposure_steps}')
            self.exposure_steps = steps


def sphere_image_offset(cam, X, radius):
    """
    Distance (px) between the centre of a sphere's (undistorted) image and pi(centre).

    Exact for the pinhole: f (tan(t + a) + tan(t - a)) / 2 - f tan t along the radial
    direction, with t the field angle of the centre and a = asin(radius / distance), using
    the mean focal length.  Returns (N,).
    """
    Xc = cam.to_camera(np.atleast_2d(X))
    dist = np.linalg.norm(Xc, axis=1)
    a = np.arcsin(np.clip(radius / dist, 0.0, 1.0))
    t = np.arccos(np.clip(Xc[:, 2] / dist, -1.0, 1.0))
    f = 0.5 * (cam.fx + cam.fy)
    return f * (0.5 * (np.tan(t + a) + np.tan(t - a)) - np.tan(t))


def sphere_coverage(cam, centres, radius, u0, v0, width, height, supersample=8, lamp=None,
                    ambient=0.25, led_axis=None, led_falloff=1.0):
    """
    Return the fraction of each pixel of a window covered by the image of a sphere.

    The window is [u0, u0 + width) x [v0, v0 + height); the sphere has ``radius`` and is
    centred at world point(s) ``centres`` (3,) or (K, 3).

    With K centres the coverage is averaged over them (instants of an exposure), sharing the
    undistorted rays.  Returns (height, width) floats in [0, 1].

    With a ``lamp`` (world position) each covered sub-pixel is weighted by the Lambertian
    shading of the surface point its ray meets first, ambient + (1 - ambient) max(0, n . l):
    P = t d with t = (d.C - sqrt((d.C)^2 - |d|^2 (|C|^2 - r^2))) / |d|^2, n = (P - C) / r,
    l the unit vector from P to the lamp (camera frame).  With ``led_axis`` (a world-frame
    unit vector a) instead, ambient + (1 - ambient) max(0, n . a)^``led_falloff``
    (:class:`SensorModel`).
    """
    S = int(supersample)
    # Undistort the pixel corners exactly, then interpolate bilinearly inside each pixel: the
    # distortion is so smooth that this is exact to ~1e-5 px and 50 times cheaper.
    cu = u0 - 0.5 + np.arange(width + 1)
    cv = v0 - 0.5 + np.arange(height + 1)
    gu, gv = np.meshgrid(cu, cv)
    grid = undistort_normalized(cam, np.column_stack([gu.ravel(), gv.ravel()]))
    grid = grid.reshape(height + 1, width + 1, 2)
    C_all = cam.to_camera(np.atleast_2d(np.asarray(centres, float)))
    # Only the pixels the sphere's cone can reach are supersampled: a sub-pixel's ray is a
    # convex combination of its pixel's corners, so a pixel whose corners' bounding box misses
    # the cone's (:func:`_cone_box`) has no sub-pixel inside.  The rest is zero, as the test
    # below would find it, and the pixels kept are computed exactly as over the whole window.
    py, px = np.nonzero(_near_cone(grid, C_all, radius))
    a = ((np.arange(S) + 0.5) / S)
    A = a[None, None, :, None]                  # along u
    B = a[None, :, None, None]                  # along v
    g00 = grid[py, px][:, None, None, :]
    g01 = grid[py, px + 1][:, None, None, :]
    g10 = grid[py + 1, px][:, None, None, :]
    g11 = grid[py + 1, px + 1][:, None, None, :]
    xy = ((1 - A) * (1 - B) * g00 + A * (1 - B) * g01 + (1 - A) * B * g10 + A * B * g11)
    xy = xy.reshape(-1, 2)
    d = np.column_stack([xy, np.ones(len(xy))])
    dd = np.einsum('ij,ij->i', d, d)
    hits = np.zeros(len(d))
    lamp_c = None if lamp is None else cam.to_camera(np.asarray(lamp, float)[None])[0]
    axis_c = None if led_axis is None else cam.rotation @ np.asarray(led_axis, float)
    for C in C_all:
        cross = np.cross(d, C)
        inside = (np.einsum('ij,ij->i', cross, cross) <= radius ** 2 * dd) & (d @ C > 0)
        if lamp_c is None and axis_c is None:
            hits += inside
            continue
        di, ddi = d[inside], dd[inside]
        dc = di @ C
        t = (dc - np.sqrt(np.maximum(dc * dc - ddi * (C @ C - radius ** 2), 0.0))) / ddi
        P = di * t[:, None]
        n = (P - C) / radius
        if axis_c is not None:
            cos = np.maximum(n @ axis_c, 0.0)
            hits[inside] += ambient + (1.0 - ambient) * cos ** led_falloff
            continue
        toward = lamp_c - P
        toward /= np.linalg.norm(toward, axis=1, keepdims=True)
        shade = ambient + (1.0 - ambient) * np.maximum(np.einsum('ij,ij->i', n, toward), 0.0)
        hits[inside] += shade
    hits /= len(C_all)
    fine = np.zeros((height, S, width, S))
    fine[py, :, px, :] = hits.reshape(-1, S, S)
    return fine.mean(axis=(1, 3))


def _cone_box(C, radius):
    """
    Return (lo (2,), hi (2,)) bounding the sphere's cone on the plane z = 1, or None.

    The rays within a = asin(r / |C|) of the centre's direction meet z = 1 in an ellipse; its
    farthest point from c = C / C_z is the outer end of its major axis, at tan(t + a) - tan t
    from c (t the centre's field angle; tan is convex, so the outer end is the farther).  None
    when the cone reaches z <= 0 (t + a >= 90 deg): then every ray must be tested.
    """
    D = float(np.linalg.norm(C))
    if not (D > radius and C[2] > 0):
        return None
    alpha = math.asin(radius / D)
    theta = math.acos(min(C[2] / D, 1.0))
    if theta + alpha >= 0.5 * math.pi - 1e-6:
        return None
    reach = 1.01 * (math.tan(theta + alpha) - math.tan(theta)) + 1e-9
    c = C[:2] / C[2]
    return c - reach, c + reach


def _near_cone(grid, C_all, radius):
    """
    Return (h, w) bool: the pixels that may see the sphere from some centre of ``C_all``.

    A pixel may when its corners' bounding box (``grid`` (h+1, w+1, 2), the normalised
    corners) meets the box of :func:`_cone_box`; every pixel when a cone has no box.
    """
    corners = (grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:])
    lo = np.minimum.reduce(corners)
    hi = np.maximum.reduce(corners)
    near = np.zeros(lo.shape[:2], bool)
    for C in C_all:
        box = _cone_box(C, radius)
        if box is None:
            return np.ones(lo.shape[:2], bool)
        near |= np.all((hi >= box[0]) & (lo <= box[1]), axis=-1)
    return near


def vignetting(cam, u, v):
    """Natural vignetting cos^4(field angle) at pixels (u, v) (arrays of the same shape)."""
    x = (np.asarray(u, float) - cam.cx) / cam.fx
    y = (np.asarray(v, float) - cam.cy) / cam.fy
    return 1.0 / (1.0 + x * x + y * y) ** 2


def marker_signal(cam, centres, radius, sensor: SensorModel, blur_sigma, margin=3,
                  led_axis=None, with_alpha=False):
    """
    Noise-free marker signal in DN on a window around the marker.

    ``centres`` (K, 3) are the sphere centre's world positions at instants spread over the
    exposure (motion blur is their average); ``led_axis`` the world direction the LED points
    in this frame (with ``sensor.led_axis``).  Returns (u0, v0, patch) with patch (h, w) in
    DN, or None when the window misses the image.  ``with_alpha`` returns (u0, v0, patch,
    alpha) with alpha (h, w) the fraction of each pixel's light that comes from the ball
    (its coverage, through the same motion and blur): what it hides of a scene behind it.
    """
    centres = np.atleast_2d(np.asarray(centres, float))
    uv = cam.project(centres)
    depth = cam.to_camera(centres)[:, 2]
    if np.any(depth <= radius):
        return None
    r_px = max(cam.fx, cam.fy) * radius / depth.min()
    pad = r_px + 4.0 * blur_sigma + margin
    u0 = int(np.floor(uv[:, 0].min() - pad))
    v0 = int(np.floor(uv[:, 1].min() - pad))
    u1 = int(np.ceil(uv[:, 0].max() + pad)) + 1
    v1 = int(np.ceil(uv[:, 1].max() + pad)) + 1
    if u1 <= 0 or v1 <= 0 or u0 >= cam.width or v0 >= cam.height:
        return None
    w, h = u1 - u0, v1 - v0
    shaded = sphere_coverage(cam, centres, radius, u0, v0, w, h, sensor.supersample,
                             sensor.lamp, sensor.ambient, led_axis, sensor.led_falloff)
    signal = sensor.peak * shaded
    if sensor.vignetting:
        vv, uu = np.mgrid[v0:v1, u0:u1]
        signal *= vignetting(cam, uu, vv)
    if blur_sigma > 0:
        signal = gaussian_filter(signal, blur_sigma, mode='constant', truncate=4.0)
    if not with_alpha:
        return u0, v0, signal
    alpha = shaded if sensor.lamp is None and led_axis is None else \
        sphere_coverage(cam, centres, radius, u0, v0, w, h, sensor.supersample)
    if blur_sigma > 0:
        alpha = gaussian_filter(alpha, blur_sigma, mode='constant', truncate=4.0)
    return u0, v0, signal, alpha


def _paste(image, u0, v0, patch):
    """Add ``patch`` into ``image`` at column u0, row v0, clipped to the image."""
    H, W = image.shape[:2]
    h, w = patch.shape[:2]
    a, b = max(0, -v0), max(0, -u0)
    c, d = min(h, H - v0), min(w, W - u0)
    if c <= a or d <= b:
        return None
    image[v0 + a:v0 + c, u0 + b:u0 + d] += patch[a:c, b:d]
    return (slice(v0 + a, v0 + c), slice(u0 + b, u0 + d))


def glint_patches(cam, rng, sensor: SensorModel, near_uv=None):
    """Random spurious highlights for one frame: list of (u0, v0, patch DN)."""
    out = []
    for _ in range(rng.poisson(sensor.glint_rate)):
        if near_uv is not None and rng.random() < sensor.glint_near_marker:
            ang = rng.uniform(0, 2 * np.pi)
            rad = rng.uniform(8.0, 40.0)
            u, v = near_uv[0] + rad * np.cos(ang), near_uv[1] + rad * np.sin(ang)
        else:
            u, v = rng.uniform(0, cam.width), rng.uniform(0, cam.height)
        sigma = rng.uniform(0.4, 1.2)
        amp = rng.uniform(60.0, 300.0)
        half = int(np.ceil(4 * sigma)) + 1
        u0, v0 = int(np.floor(u)) - half, int(np.floor(v)) - half
        vv, uu = np.mgrid[v0:v0 + 2 * half + 2, u0:u0 + 2 * half + 2]
        out.append((u0, v0, amp * np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * sigma ** 2))))
    return out


def clutter_scene(width, height, sensor: SensorModel, rng):
    """
    Return a static cluttered scene (height, width) in DN for one camera (module docstring).

    Shaded background at 0.5-1 x ``clutter_level``; 40 boxes, 20 discs and 20 bars (up to
    400 px long) of brightness uniform in [0, 2 x ``clutter_level``]; ``clutter_spots`` discs
    of radius 2-8 px at 0.6-1.1 x the marker's ``peak`` with a soft edge like the marker's.
    """
    level = float(sensor.clutter_level)
    v, u = np.mgrid[0:height, 0:width].astype(float)
    a, b = rng.uniform(-1, 1, 2)
    scene = level * (0.75 + 0.25 * (a * (u / width - 0.5) + b * (v / height - 0.5)))
    for _ in range(40):
        u0, v0 = rng.uniform(0, width), rng.uniform(0, height)
        w, h = rng.uniform(10, 150, 2)
        scene[(abs(u - u0) < w / 2) & (abs(v - v0) < h / 2)] = rng.uniform(0, 2 * level)
    for _ in range(20):
        u0, v0, r = rng.uniform(0, width), rng.uniform(0, height), rng.uniform(4, 40)
        scene[(u - u0) ** 2 + (v - v0) ** 2 < r * r] = rng.uniform(0, 2 * level)
    for _ in range(20):
        t, u0, v0 = rng.uniform(0, np.pi), rng.uniform(0, width), rng.uniform(0, height)
        along = (u - u0) * np.cos(t) + (v - v0) * np.sin(t)
        across = (u - u0) * np.sin(t) - (v - v0) * np.cos(t)
        bar = (abs(across) < rng.uniform(1, 4)) & (abs(along) < rng.uniform(20, 200))
        scene[bar] = rng.uniform(0, 2 * level)
    scene = gaussian_filter(scene, 0.7)
    for _ in range(int(sensor.clutter_spots)):
        u0, v0 = rng.uniform(20, width - 20), rng.uniform(20, height - 20)
        r, peak = rng.uniform(2, 8), rng.uniform(0.6, 1.1) * sensor.peak
        disc = np.clip(r + 0.5 - np.hypot(u - u0, v - v0), 0, 1)
        scene = np.maximum(scene, gaussian_filter(disc, sensor.defocus_sigma) * peak)
    return np.clip(scene, 0, 250)


def expose(cam, patches, rng, sensor: SensorModel, encoding='mono8', background=None,
           occluders=()):
    """
    Turn signal patches [(u0, v0, DN)] into an 8-bit image with shot and read noise.

    ``encoding`` is mono8, rgb8 or bgr8 (colour: the same signal through ``colour_gains``,
    independent noise per channel).  ``background`` (H, W) DN is a static scene behind the
    patches (:func:`clutter_scene`); with it every pixel gets shot and read noise.  Where
    ``occluders`` [(u0, v0, alpha)] (:func:`marker_signal` ``with_alpha``) cover it, the scene
    is hidden: a pixel shows ``signal + (1 - alpha) scene`` - an opaque ball in front, its
    unlit side darker than a bright scene it stands before.  Without them the brighter of
    signal and scene is shown.
    """
    if encoding not in ('mono8', 'rgb8', 'bgr8'):
        raise ValueError(f'encoding must be mono8, rgb8 or bgr8, got {encoding!r}')
    gains = [1.0] if encoding == 'mono8' else list(sensor.colour_gains)
    if encoding == 'bgr8':
        gains = gains[::-1]
    H, W = cam.height, cam.width
    full_noise = sensor.read_noise >= 0.1 or background is not None
    channels = []
    for g in gains:
        signal = np.zeros((H, W))
        regions = []
        for u0, v0, p in patches:
            region = _paste(signal, u0, v0, p * g)
            if region is not None:
                regions.append(region)
        if background is not None and occluders:
            alpha = np.zeros((H, W))
            for u0, v0, a in occluders:
                _paste(alpha, u0, v0, a)
            signal = signal + (1.0 - np.minimum(alpha, 1.0)) * (background * g)
        elif background is not None:
            signal = np.maximum(signal, background * g)
        if full_noise:
            vals = sensor.black_level + rng.normal(0.0, sensor.read_noise, (H, W))
            vals += rng.poisson(np.clip(signal, 0, None) * sensor.gain) / sensor.gain
            channels.append(np.clip(np.rint(vals), 0, 255).astype(np.uint8))
            continue
        out = np.full((H, W), np.uint8(np.clip(np.rint(sensor.black_level), 0, 255)))
        # Only pixels with signal can differ from the black level (see the module docstring);
        # where regions overlap the later draw replaces the earlier one (one sample each).
        for sl in regions:
            s = np.clip(signal[sl], 0, None)
            vals = sensor.black_level + rng.poisson(s * sensor.gain) / sensor.gain
            if sensor.read_noise > 0:
                vals += rng.normal(0.0, sensor.read_noise, s.shape)
            out[sl] = np.clip(np.rint(vals), 0, 255).astype(np.uint8)
        channels.append(out)
    return channels[0] if len(channels) == 1 else np.dstack(channels)
