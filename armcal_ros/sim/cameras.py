"""Camera placements for simulated cells: a ring of cameras looking at the workspace."""

import numpy as np

from armcal_ros.core.camera import Camera


def ring_of_cameras(n, target, rng, distance=(1.5, 2.0), height=(0.4, 1.0), width=640,
                    height_px=480, focal=800.0, dist=(-0.15, 0.05, 0.0, 0.0, 0.0), names=None,
                    jitter=0.05):
    """
    Place ``n`` cameras around ``target`` at ``distance`` metres, spread in azimuth.

    Each camera is ``distance`` (uniform in the range) from the target, ``height`` metres above it,
    at azimuths spread evenly with random jitter, looking at the target with small random
    perturbations of the focal length, principal point and distortion so no two are alike.
    """
    target = np.asarray(target, float)
    names = names or [f'cam{i + 1}' for i in range(n)]
    az0 = rng.uniform(0, 2 * np.pi)
    cams = []
    for i in range(n):
        az = az0 + 2 * np.pi * i / n + rng.uniform(-0.3, 0.3)
        r = rng.uniform(*distance)
        h = rng.uniform(*height)
        horiz = np.sqrt(max(r * r - h * h, 1e-6))
        eye = target + np.array([horiz * np.cos(az), horiz * np.sin(az), h])
        aim = target + rng.normal(0.0, jitter, 3)
        f = focal * rng.uniform(0.95, 1.05)
        d = np.asarray(dist, float) * rng.uniform(0.8, 1.2, 5)
        d[2:4] = rng.normal(0.0, 5e-4, 2) if dist[2] == 0 and dist[3] == 0 else d[2:4]
        cx = width / 2 + rng.normal(0.0, 4.0)
        cy = height_px / 2 + rng.normal(0.0, 4.0)
        cams.append(Camera.look_at(names[i], width, height_px, f, f * rng.uniform(0.998, 1.002),
                                   cx, cy, d, eye, aim))
    return cams
