"""
SampleCollector, the front end: poses or joint states and images in, samples out.

A board needs one view per camera and dwell, so the collector searches at most
``max_views_per_dwell`` still frames that show it per camera and dwell; a sphere is never capped.
The detectors are stand-ins that replay given detections (:class:`RecordingDetector`).
"""

import inspect

import numpy as np
import pytest

from armcal_ros.frontend.collector import SampleCollector
from armcal_ros.frontend.detectors import Detection
from armcal_ros.frontend.image_decode import encode_raw_image
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.params import BY_NAME, check_value
from helpers.board_scene import BOARD

MS = 1_000_000


class RecordingDetector:
    """A detector stand-in: its results in order, every call recorded."""

    def __init__(self, results):
        self.results = iter(results)
        self.calls = []

    def detect(self, image):
        out = next(self.results)
        self.calls.append(out)
        return out


def _image_msg(img):
    class Msg:
        pass
    m = Msg()
    for k, v in encode_raw_image(img, 'mono8').items():
        setattr(m, k, v)
    return m


def _feed(collector, cameras, dwells=((0, 1000), (1500, 2500)), period_ms=50):
    """
    Pose input: still at one place per dwell (ms ranges), a 0.5 m/s move between them.

    Images every ``period_ms`` per camera; returns the samples.
    """
    img_msg = _image_msg(np.full((24, 32), 128, np.uint8))
    samples = []
    end = dwells[-1][1]
    places = [np.array([0.1 * i, 0.0, 0.0]) for i in range(len(dwells))]

    def where(t):
        for i, (a, b) in enumerate(dwells):
            if t <= b:
                if t >= a or i == 0:
                    return places[i]
                s = (t - dwells[i - 1][1]) / (a - dwells[i - 1][1])
                return (1 - s) * places[i - 1] + s * places[i]
        return places[-1]

    events = [(t, None) for t in range(0, end + 200, 10)]
    events += [(t + 3 + j, c) for t in range(0, end, period_ms) for j, c in enumerate(cameras)]
    for t, cam in sorted(events, key=lambda e: e[0]):
        if cam is None:
            samples += collector.add_pose(t * MS, where(t), [0, 0, 0, 1])
        else:
            samples += collector.add_image(cam, t * MS, img_msg)
    return samples + collector.flush()


def _board_collector(results, **kw):
    target = BoardTarget(BOARD.points(), np.eye(4))
    dets = {c: RecordingDetector(results()) for c in ('c1', 'c2')}
    return SampleCollector(None, [0, 0, 0], ['c1', 'c2'], dets, board=target, **kw), dets


def _board_results(seed):
    rng = np.random.default_rng(seed)
    while True:
        yield [Detection(uv=np.array([300.0 + 40 * i, 200.0]) + rng.normal(0, 0.2, 2), id=i,
                         quality=1.0, radius_px=20.0) for i in range(BOARD.n_corners)]


def test_collector_caps_board_detections_per_dwell_and_camera():
    col, dets = _board_collector(lambda: _board_results(7))
    assert col.pooler.max_views == 3
    samples = _feed(col, ['c1', 'c2'])
    assert len(samples) == 2
    # 2 dwells x 3 views per camera; every other still frame skipped undecoded.
    assert [len(d.calls) for d in dets.values()] == [6, 6]
    assert col.counts['detections'] == 12
    assert col.counts['frames_skipped_dwell_full'] == col.counts['frames_still'] - 12 > 20
    # Each sample pools exactly the views the detector gave it, in order.
    for cam, d in dets.items():
        for k, s in enumerate(samples):
            views = np.array([[x.uv for x in call] for call in d.calls[3 * k:3 * k + 3]])
            obs = s.observations[cam]
            assert obs.n_frames == 3
            np.testing.assert_allclose(obs.uv, views.mean(axis=0), atol=1e-12)
            np.testing.assert_array_equal(obs.ids, np.arange(BOARD.n_corners))
    # Without the cap every still frame is searched; the dwells and poses are the same.
    free, free_dets = _board_collector(lambda: _board_results(7), max_views_per_dwell=0)
    free_samples = _feed(free, ['c1', 'c2'])
    assert free.counts['frames_still'] == col.counts['frames_still']
    assert free.counts['detections'] == free.counts['frames_still']
    assert 'frames_skipped_dwell_full' not in free.counts
    assert len(free_samples) == 2
    for s, f in zip(samples, free_samples):
        np.testing.assert_array_equal(s.pose, f.pose)
        assert s.observations['c1'].n_frames == 3 < f.observations['c1'].n_frames


def test_collector_cap_counts_only_frames_that_show_the_board():
    def results():
        gen = _board_results(3)
        while True:
            yield []                              # the board hidden in every other frame
            yield next(gen)
    col, dets = _board_collector(results, max_views_per_dwell=2)
    samples = _feed(col, ['c1', 'c2'], dwells=((0, 1000),))
    assert len(samples) == 1
    assert [len(d.calls) for d in dets.values()] == [4, 4]
    assert [sum(bool(c) for c in d.calls) for d in dets.values()] == [2, 2]
    assert col.counts['frames_no_marker'] == 4 and col.counts['detections'] == 4


def test_sphere_is_not_capped_by_default_or_when_set():
    def sphere_results():
        rng = np.random.default_rng(5)
        while True:
            yield [Detection(uv=np.array([320.0, 240.0]) + rng.normal(0, 0.1, 2), id=0,
                             quality=1.0, radius_px=6.0)]
    for kw in ({}, {'max_views_per_dwell': 3}):
        dets = {c: RecordingDetector(sphere_results()) for c in ('c1', 'c2')}
        col = SampleCollector(None, [0, 0, 0], ['c1', 'c2'], dets, **kw)
        assert col.pooler.max_views == 0
        # The fake detector gives one pixel at every dwell: a fixed spot, which the collector
        # drops from the second dwell on (test_frontend_static_spots.py); not what this tests.
        col.static_spots = None
        samples = _feed(col, ['c1', 'c2'])
        assert len(samples) == 2
        assert col.counts['detections'] == col.counts['frames_still'] > 30
        assert 'frames_skipped_dwell_full' not in col.counts
        assert sum(len(d.calls) for d in dets.values()) == col.counts['frames_still']
        assert all(s.observations['c1'].n_frames > 3 for s in samples)


class LitBallDetector:
    """A shaded-ball stand-in: a centre 0.4 px from its centroid, fitted only when asked."""

    def __init__(self):
        self.fits = self.calls = 0

    def detect(self, image, fit=True):
        self.calls += 1
        self.fits += fit
        centroid = np.array([320.4, 240.0])
        uv = np.array([320.0, 240.0]) if fit else np.full(2, np.nan)
        return [Detection(uv=uv, id=0, quality=1.0, radius_px=6.0, centroid=centroid)]


def test_a_shaded_ball_is_fitted_in_only_a_few_frames_per_dwell():
    dets = {c: LitBallDetector() for c in ('c1', 'c2')}
    col = SampleCollector(None, [0, 0, 0], ['c1', 'c2'], dets, max_fits_per_view=3)
    col.static_spots = None
    samples = _feed(col, ['c1', 'c2'])
    assert len(samples) == 2
    assert [d.fits for d in dets.values()] == [6, 6]          # 3 per dwell and camera
    assert sum(d.calls for d in dets.values()) == col.counts['frames_still']
    assert col.counts['frames_fit_skipped'] == col.counts['frames_still'] - 12
    for s in samples:
        o = s.observations['c1']
        assert o.n_frames > 3
        np.testing.assert_allclose(o.uv, [[320.0, 240.0]], atol=1e-9)
        np.testing.assert_allclose(o.centroid_uv, [[320.4, 240.0]], atol=1e-9)


def test_parameter_default_matches_the_collector_and_is_checked():
    p = BY_NAME['max_views_per_dwell']
    default = inspect.signature(SampleCollector).parameters['max_views_per_dwell'].default
    assert p.type == 'int' and p.default == default == 3
    assert check_value('max_views_per_dwell', 0) == 0
    with pytest.raises(ValueError, match='max_views_per_dwell'):
        check_value('max_views_per_dwell', -1)
    with pytest.raises(ValueError, match='max_views_per_dwell'):
        SampleCollector(None, [0, 0, 0], ['c'], {'c': None}, max_views_per_dwell=-2)


def test_collector_without_a_robot_model_takes_poses_not_joint_states():
    col = SampleCollector(None, [0, 0, 0.1], ['cam'], {'cam': object()})
    assert col.pose_input
    assert col.add_joint_state(0, ['j1'], [0.0]) == []
    assert col.counts['joint_state_unused'] == 1
    assert col.add_pose(0, [0, 0, 0], [0, 0, 0, 1]) == []
    assert col.add_pose(1, [0, 0, 0], [0, 0, 0, 5]) == []
    assert col.counts['poses'] == 2 and col.counts['pose_invalid'] == 1


def test_frames_of_another_size_or_absurdly_large_are_counted_and_skipped():
    col = SampleCollector(None, [0, 0, 0.1], ['cam'], {'cam': RecordingDetector(iter(
        lambda: [], None))})
    assert col._detect('cam', _image_msg(np.full((24, 32), 9, np.uint8))) == []
    assert col.image_sizes['cam'] == (32, 24)
    col._detect('cam', _image_msg(np.full((48, 64), 9, np.uint8)))
    assert col.counts['image_size_changed'] == 1 and col.image_sizes['cam'] == (32, 24)
    col._detect('cam', _image_msg(np.zeros((2000, 2500), np.uint8)))      # 5 MB
    assert col.counts['image_oversize'] == 1
    assert col.counts['detections'] + col.counts['frames_no_marker'] == 1


def test_a_detector_failing_on_a_frame_costs_that_frame_only():
    """A detector that raises on some frames: those are counted and said once, the rest pool."""
    class Flaky:
        def __init__(self):
            self.calls = 0
            self.rng = np.random.default_rng(6)

        def detect(self, image):
            self.calls += 1
            if self.calls % 7 == 3:
                raise ValueError('radius0 and sigma0 must be > 0, got 0.0, 0.6')
            return [Detection(uv=np.array([320.0, 240.0]) + self.rng.normal(0, 0.1, 2), id=0,
                              quality=1.0, radius_px=6.0)]
    messages = []
    col = SampleCollector(None, [0, 0, 0], ['c1', 'c2'], {c: Flaky() for c in ('c1', 'c2')},
                          log=messages.append)
    col.static_spots = None
    samples = _feed(col, ['c1', 'c2'])
    assert len(samples) == 2 and all(len(s.observations) == 2 for s in samples)
    failed = col.counts['detector_error']
    assert failed > 4 and col.counts['detections'] + failed == col.counts['frames_still']
    said = [m for m in messages if 'detector failed' in m]
    assert 1 <= len(said) < failed and 'ValueError' in said[0]


def test_why_few_samples_names_the_missing_joints_and_other_causes():
    from armcal_ros.frontend.collector import why_few_samples
    text = why_few_samples({'joint_states': 100, 'joint_state_missing_joint': 100,
                            'frames': 50}, ('shoulder_pan_joint', 'elbow_joint'),
                           ('joint_1', 'joint_2'))
    assert 'elbow_joint' in text and 'shoulder_pan_joint' in text and 'joint_1' in text
    assert "robot's URDF" in text
    assert 'image_topics' in why_few_samples({'joint_states': 100})
    assert 'clock' in why_few_samples({'joint_states': 100, 'frames': 50, 'frames_gap': 50})
    assert 'still' in why_few_samples({'joint_states': 100, 'frames': 50, 'frames_moving': 50})
    assert 'marker_type' in why_few_samples({'joint_states': 100, 'frames': 50,
                                             'frames_still': 20, 'frames_no_marker': 20})
    assert why_few_samples({'joint_states': 100, 'frames': 50, 'frames_still': 20,
                            'detections': 20}) == ''


def test_a_camera_silent_for_minutes_comes_back_into_the_samples():
    """Camera c2 sends nothing for five minutes while c1 and the arm go on; then it is back."""
    def sphere_results():
        while True:
            yield [Detection(uv=np.array([320.0, 240.0]), id=0, quality=1.0, radius_px=6.0)]
    dets = {c: RecordingDetector(sphere_results()) for c in ('c1', 'c2')}
    col = SampleCollector(None, [0, 0, 0], ['c1', 'c2'], dets)
    col.static_spots = None          # one pixel at every dwell: a fixed spot, not tested here
    img = _image_msg(np.full((24, 32), 128, np.uint8))
    dwells = [(0, 1000), (150_000, 151_000), (310_000, 311_000)]      # ms
    silent = (2_000, 300_000)                                         # c2 says nothing

    def where(t):
        for i, (a, b) in enumerate(dwells):
            if a <= t <= b:
                return np.array([0.1 * i, 0.0, 0.0])
        a = t / 100.0                                  # a circle at 0.5 m/s in between
        return np.array([0.5 + 0.05 * np.cos(a), 0.05 * np.sin(a), 0.0])
    samples = []
    for t in range(0, 312_000, 10):
        samples += col.add_pose(t * MS, where(t), [0, 0, 0, 1])
        if t % 50 == 0:
            samples += col.add_image('c1', (t + 3) * MS, img)
            if not silent[0] <= t <= silent[1]:
                samples += col.add_image('c2', (t + 4) * MS, img)
    samples += col.flush()
    assert len(samples) == 3
    assert [sorted(s.observations) for s in samples] == [['c1', 'c2'], ['c1'], ['c1', 'c2']]
    assert not [k for k in col.counts if k.startswith(('frames_stale', 'frames_gap',
                                                       'time_jump'))], col.counts


def test_a_camera_stamped_late_is_paired_at_its_exposure():
    """``stamp_latency_s`` moves a camera's frames back before pairing; unknown names refused."""
    with pytest.raises(ValueError, match='stamp_latency_s'):
        SampleCollector(None, (0, 0, 0), ['cam1'], {'cam1': object()},
                        stamp_latency_s={'cam9': 0.03})
    c = SampleCollector(None, (0, 0, 0), ['cam1'], {'cam1': object()},
                        stamp_latency_s={'cam1': 0.03})
    seen = []
    c.pairer.add_frame = lambda cam, stamp, msg: seen.append(stamp) or []
    c.add_image('cam1', 1_000_000_000, b'')
    assert seen == [970_000_000]
