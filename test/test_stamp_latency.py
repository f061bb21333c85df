"""
The stamp-latency timer fed as a stream (stamp_latency.LatencyTimer), against a known delay.

A PUMA 560 moves smoothly; a camera looking at its marker stamps each image ``DELAY`` after
the exposure.  The images are stand-ins that carry the marker's true projection at exposure
(a mono8 row of the two float64 coordinates' bytes) and the detector reads it back with
0.05 px of noise, so the timer's selection, joint-state windows and fit are tested without
rendering.  The estimate must be within 1 ms of the delay (its own deviation is ~0.1 ms here);
a time jump must reset it, an out-of-order joint state must not, and a long stream must stay
within its bounds.
"""
from types import SimpleNamespace

import numpy as np
import pytest

from armcal_ros.core.camera import Camera
from armcal_ros.frontend.detectors import Detection
from armcal_ros.frontend.image_decode import encode_raw_image
from armcal_ros.robot.kinematics import KinematicChain
from armcal_ros.sim.cell import default_urdf_path
from armcal_ros.stamp_latency import LatencyTimer, measure_latencies

DELAY = 0.04
OFFSET = np.zeros(3)


class CoordinateImage:
    """An Image message whose pixels are the bytes of (u, v) as float64."""

    def __init__(self, uv):
        raw = np.frombuffer(np.asarray(uv, float).tobytes(), np.uint8).reshape(1, 16)
        for k, v in encode_raw_image(raw, 'mono8').items():
            setattr(self, k, v)


class CoordinateDetector:
    """Reads (u, v) back from a CoordinateImage, with a little detection noise."""

    def __init__(self, seed=0):
        self.rng = np.random.default_rng(seed)

    def detect(self, image):
        uv = np.frombuffer(np.ascontiguousarray(image).tobytes(), float)[:2]
        return [Detection(uv=uv + self.rng.normal(0, 0.05, 2), id=0, quality=1.0, radius_px=3.0)]


@pytest.fixture(scope='module')
def chain():
    return KinematicChain.from_file(default_urdf_path(), 'base_link', 'marker')


def joints(t):
    """Return the joints at ``t``: a smooth motion, slowest near the extremes of sin(0.7 t)."""
    q0 = np.array([0.2, -0.6, 0.4, 0.1, 0.5, 0.0])
    a = np.array([0.35, 0.2, 0.25, 0.3, 0.3, 0.4])
    return q0 + a * np.sin(0.7 * t + np.arange(6))


def camera_for(chain):
    X = chain.fk(np.array([joints(t) for t in np.linspace(0, 20, 50)]), OFFSET)
    centre = X.mean(axis=0)
    return Camera.look_at('cam1', 640, 480, 800.0, 800.0, 320.0, 240.0, [0.0] * 5,
                          eye=centre + [1.2, -0.9, 0.6], target=centre)


def calibration_of(cam):
    """Return what the timer reads of a core Calibration: each camera's model."""
    return SimpleNamespace(cameras={'cam1': SimpleNamespace(camera=cam)})


def stream(chain, cam, t_start, t_end, joint_rate=200.0, frame_rate=15.0, jitter=None,
           jitter_seed=2):
    """
    Yield the events of [t_start, t_end): joint states and images stamped DELAY late.

    ``jitter`` (a dict) adds 2 ms of Gaussian jitter to each image stamp and records it by
    the stamp (ns).
    """
    rng = np.random.default_rng(jitter_seed)
    names = list(chain.joint_names)
    order = np.random.default_rng(1).permutation(len(names))
    events = []
    for t in np.arange(t_start, t_end, 1.0 / joint_rate):
        q = joints(t)
        events.append((t, 'joints', int(round(t * 1e9)), [names[i] for i in order],
                       list(q[order])))
    for t in np.arange(t_start, t_end, 1.0 / frame_rate):
        uv = cam.project(chain.fk(joints(t)[None], OFFSET))[0]
        stamp = t + DELAY
        if jitter is not None:
            j = rng.normal(0.0, 0.002)
            stamp += j
            jitter[int(round(stamp * 1e9))] = j
        events.append((stamp, 'image', 'cam1', int(round(stamp * 1e9)), CoordinateImage(uv)))
    for e in sorted(events, key=lambda e: e[0]):
        yield e[1:]


def feed(timer, events):
    for e in events:
        if e[0] == 'joints':
            timer.add_joint_state(*e[1:])
        else:
            timer.add_image(*e[1:])


def test_a_stream_times_the_camera_with_or_without_a_calibration_to_choose_by(chain):
    cam = camera_for(chain)
    for known in (True, False):
        timer = LatencyTimer({'cam1': CoordinateDetector()}, chain, OFFSET)
        if known:
            timer.set_cameras({'cam1': cam})
        feed(timer, stream(chain, cam, 0.0, 40.0))
        est = timer.estimate(calibration_of(cam))['cam1']
        assert est.ok, est
        assert abs(est.latency_s - DELAY) < 0.001, (known, est)
        assert est.std_s < 0.001 and est.frames >= 50, est


def test_the_offline_pass_is_the_same_timer(chain):
    cam = camera_for(chain)

    class Recording:
        def events(self):
            return stream(chain, cam, 0.0, 30.0)
    est = measure_latencies(Recording(), {'cam1': CoordinateDetector()}, chain, OFFSET,
                            calibration_of(cam))['cam1']
    assert est.ok and abs(est.latency_s - DELAY) < 0.001, est


def test_time_jump_resets_out_of_order_does_not_and_memory_stays_bounded(chain):
    cam = camera_for(chain)
    timer = LatencyTimer({'cam1': CoordinateDetector()}, chain, OFFSET, max_frames=50)
    timer.set_cameras({'cam1': cam})
    feed(timer, stream(chain, cam, 0.0, 10.0))
    n = timer.frames('cam1')
    assert n > 0
    names = list(chain.joint_names)
    timer.add_joint_state(int(9.9995e9), names, list(joints(9.9995)))   # 0.5 ms back
    assert timer.frames('cam1') == n
    timer.add_joint_state(int(2e9), names, list(joints(2.0)))            # 8 s back: a jump
    assert timer.frames('cam1') == 0
    # A long stream: at most 2 max_frames frames, and joint states only around them.
    feed(timer, stream(chain, cam, 100.0, 400.0))
    assert 50 <= timer.frames('cam1') < 100
    # Each frame's window of joint states is 0.41 s: 82 at 200 Hz.
    assert len(timer._kept_t) <= 100 * 83
    est = timer.estimate(calibration_of(cam))['cam1']
    assert est.ok and abs(est.latency_s - DELAY) < 0.001, est
    timer.forget('cam1')
    assert timer.frames('cam1') == 0
    assert timer.estimate(calibration_of(cam))['cam1'].status == 'too_few_frames'


def test_arguments_are_checked(chain):
    with pytest.raises(ValueError, match='bounds'):
        LatencyTimer({}, chain, OFFSET, bounds=(0.1, 0.0))
    with pytest.raises(ValueError, match='max_frames'):
        LatencyTimer({}, chain, OFFSET, max_frames=2)


def test_the_frames_kept_are_not_chosen_by_their_stamps_jitter(chain):
    """
    A stamp's jitter must not decide whether its frame is timed.

    Spacing the frames kept by their stamps (at least s after the last) picks, where s is a
    whole number of frame intervals, the frames stamped late, and the estimate is late by a
    good part of the jitter (such a rule kept frames jittered late by 0.2 of the jitter's
    deviation here: 6 standard errors over these two streams).  The frames kept must jitter
    as all frames do: their mean within 3 standard errors of zero.
    """
    cam = camera_for(chain)
    kept = []
    for seed in (100, 101):
        timer = LatencyTimer({'cam1': CoordinateDetector()}, chain, OFFSET)
        timer.set_cameras({'cam1': cam})
        jitter = {}
        feed(timer, stream(chain, cam, 0.0, 200.0, jitter=jitter, jitter_seed=seed))
        kept += [jitter[int(round(t * 1e9))] for t, _ in timer._frames['cam1']]
    assert len(kept) >= 400
    z = np.mean(kept) / (0.002 / np.sqrt(len(kept)))
    assert abs(z) < 3, (z, len(kept))
