"""Engine samples from a synthetic problem (:func:`armcal_ros.sim.synthetic.make_problem`)."""

from armcal_ros.frontend.samples import Observation, Sample


def samples_of(prob):
    """One Sample per measured point, with one observation in each camera that sees it."""
    names = [c.name for c in prob.cameras]
    out = []
    for i, X in enumerate(prob.measured):
        sel = prob.obs.point == i
        obs = {names[j]: Observation(uv[None], [0]) for j, uv in
               zip(prob.obs.camera[sel], prob.obs.uv[sel])}
        if obs:
            out.append(Sample(X, obs, stamp_ns=i))
    return out
