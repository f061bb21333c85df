"""
Point-level observations of a simulated session: the dwells as a detector would pool them.

Rendering and detecting every frame is the honest path (bench/pipeline.py); for benchmarks that
need many sessions (change detection over seeds and cells) this gives the same samples without
images: each dwell's true marker projected by every camera as it was at that moment (a knocked
camera's new pose after its knock), with Gaussian image noise of the pooled detections, in view
and in front only.  Link occlusion is ignored.
"""

from dataclasses import dataclass
from typing import List

import numpy as np


@dataclass
class DwellObservations:
    """Per dwell k: stamp (ns), nominal point (3,), joints (n,), and camera name -> uv (2,)."""

    stamp_ns: np.ndarray
    nominal: np.ndarray
    q: np.ndarray
    uv: List[dict]


def dwell_observations(result, pixel_sigma, rng, margin=10.0) -> DwellObservations:
    """Return every dwell of ``result`` as pooled observations with ``pixel_sigma`` px noise."""
    if not (np.isfinite(pixel_sigma) and pixel_sigma >= 0):
        raise ValueError(f'pixel_sigma must be finite and >= 0, got {pixel_sigma}')
    d = result.dwells
    out = []
    for k in range(len(d)):
        t = int(d.stamp_ns[k])
        X = d.true_marker[k:k + 1]
        seen = {}
        for j in range(len(result.cameras)):
            cam = result.camera_at(j, t)
            if not cam.in_front(X)[0]:
                continue
            uv = cam.project(X)[0]
            if margin <= uv[0] <= cam.width - 1 - margin and \
                    margin <= uv[1] <= cam.height - 1 - margin:
                seen[cam.name] = uv + rng.normal(0.0, pixel_sigma, 2)
        out.append(seen)
    return DwellObservations(np.asarray(d.stamp_ns), np.asarray(d.nominal_marker),
                             np.asarray(d.q), out)
