"""
Board detection work per dwell: the views cap, and the board-only dictionary's same corners.

A board needs one view per camera and dwell, so :class:`SampleCollector` searches at most
``max_views_per_dwell`` still frames that show it per camera and dwell; a sphere is never capped.
"""

import inspect

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.frontend.detectors import CharucoBoard, CharucoDetector, Detection
from armcal_ros.frontend.detectors.base import aruco_dictionary
from armcal_ros.frontend.image_decode import encode_raw_image
from armcal_ros.frontend.pairing import DwellPooler, PairedFrame, PairStatus
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.params import BY_NAME, check_value
from armcal_ros.frontend.collector import SampleCollector
from test_charuco import project, render

BOARD = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250')
MS = 1_000_000


def _full_dictionary_detector(board):
    """cv2's detector as before the speed-up: the whole dictionary, same parameters."""
    params = cv2.aruco.CharucoParameters()
    params.minMarkers = 1
    params.tryRefineMarkers = True
    dparams = cv2.aruco.DetectorParameters()
    dparams.minMarkerDistanceRate = 0.0
    return cv2.aruco.CharucoDetector(board.cv_board(), params, dparams)


def _paste_marker(img, marker_id, top_left, side=90):
    """Paste a marker of BOARD's dictionary (white quiet zone around it) into ``img``."""
    tag = cv2.aruco.generateImageMarker(aruco_dictionary(BOARD.dictionary), marker_id, side)
    tag = cv2.copyMakeBorder(tag, 15, 15, 15, 15, cv2.BORDER_CONSTANT, value=255)
    r, c = top_left
    img[r:r + tag.shape[0], c:c + tag.shape[1]] = cv2.GaussianBlur(tag, (0, 0), 0.7)
    return img


@pytest.mark.parametrize('tilt, legacy, foreign', [
    (0.0, False, False), (35.0, False, True), (50.0, True, False), (50.0, True, True)])
def test_board_only_dictionary_keeps_the_corners(tilt, legacy, foreign):
    board = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250', legacy=legacy)
    R = Rotation.from_euler('xyz', [tilt, -10, 5], degrees=True).as_matrix()
    t = np.array([-0.1, -0.14, 0.6])
    img = render(board, R, t, noise=2.0, seed=3)
    if foreign:
        # A marker of the same dictionary that is not on the board (id 200) next to it.
        img = _paste_marker(img, 200, (800, 1100))
        _, found, _ = cv2.aruco.ArucoDetector(
            aruco_dictionary(board.dictionary)).detectMarkers(img)
        assert 200 in found.ravel()
    uv, ids = CharucoDetector(board).detect_arrays(img)
    corners, cv_ids, _, _ = _full_dictionary_detector(board).detectBoard(img)
    order = np.argsort(board.ids_from_opencv(cv_ids))
    np.testing.assert_array_equal(ids, board.ids_from_opencv(cv_ids)[order])
    full = corners.reshape(-1, 2)[order]
    if foreign:
        # The foreign marker, now an unidentified candidate, can nudge cv2's refinement.
        assert np.abs(uv - full).max() < 0.02
    else:
        np.testing.assert_array_equal(uv, full)
    # As accurate as before against the true projections.
    assert list(ids) == list(range(board.n_corners))
    # The texture is drawn in opencv numbering; the legacy renumbering is its own inverse.
    truth = project(board.points(), R, t)[board.ids_from_opencv(ids)]
    for found_uv in (uv, full):
        err = np.linalg.norm(found_uv - truth, axis=1)
        assert np.sqrt(np.mean(err ** 2)) < 0.1 and err.max() < 0.3


def test_corner_spacing_is_half_a_square_on_partial_views():
    R = Rotation.from_euler('xyz', [0, 0, 0], degrees=True).as_matrix()
    t = np.array([-0.1, -0.14, 0.6])
    img = render(BOARD, R, t)
    truth = project(BOARD.points(), R, t)
    img[int(np.median(truth[:, 1])) + 10:, :] = 128
    dets = CharucoDetector(BOARD).detect(img)
    # 0.04 m at 0.6 m with f = 1000 px: 66.7 px between neighbouring corners.
    assert 4 <= len(dets) < BOARD.n_corners
    assert abs(dets[0].radius_px - 0.5 * 1000 * 0.04 / 0.6) < 1.0


def _frame(camera, stamp_ms, point=(0.0, 0.0, 0.0)):
    return PairedFrame(camera, stamp_ms * MS, None, PairStatus.STILL, q=np.array(point, float),
                       point=np.array(point, float), speed=0.0)


def _dets(rng, n_ids=3):
    return [Detection(uv=np.array([100.0 + 50 * i, 200.0]) + rng.normal(0, 0.3, 2), id=i,
                      quality=1.0, radius_px=10.0) for i in range(n_ids)]


def _identity_fk(Q):
    return np.asarray(Q, float)


def test_pooler_cap_counts_views_per_camera_and_pools_the_first_ones():
    rng = np.random.default_rng(0)
    capped = DwellPooler(_identity_fk, min_frames=1, max_views=3)
    reference = DwellPooler(_identity_fk, min_frames=1)
    needed = {'a': 0, 'b': 0}
    for k in range(12):
        cam = 'ab'[k % 2]
        f = _frame(cam, 10 * k)
        dets = _dets(rng) if k != 2 else []      # camera a's second frame shows nothing
        wants = capped.needs_detection(f)
        needed[cam] += wants
        assert capped.add(f, dets if wants else ()) == []
        # The reference sees every frame, with detections only where the capped one looked.
        reference.add(f, dets if wants else ())
    # Camera a needed 4 searches (one found nothing), b 3; the rest were skipped.
    assert needed == {'a': 4, 'b': 3}
    [s] = capped.flush()
    [r] = reference.flush()
    for cam in 'ab':
        assert s.observations[cam].n_frames == 3
        np.testing.assert_array_equal(s.observations[cam].uv, r.observations[cam].uv)
        assert s.observations[cam].spread_px == r.observations[cam].spread_px
        assert s.observations[cam].stamp_ns == r.observations[cam].stamp_ns
    np.testing.assert_array_equal(s.q, r.q)
    assert s.stamp_ns == r.stamp_ns


def test_pooler_cap_ignores_late_detections_and_restarts_with_a_new_dwell():
    rng = np.random.default_rng(1)
    pooler = DwellPooler(_identity_fk, min_frames=1, max_views=2)
    first = [_dets(rng) for _ in range(4)]
    for k, d in enumerate(first):
        pooler.add(_frame('a', 10 * k), d)           # a caller that detects anyway
    far = _frame('a', 50, point=(0.01, 0.0, 0.0))
    assert pooler.needs_detection(far)                # a new dwell: search again
    assert not pooler.needs_detection(_frame('a', 50))
    assert pooler.needs_detection(_frame('a', 50_000))    # after a gap: a new dwell
    assert pooler.needs_detection(_frame('b', 50))         # another camera
    moving = PairedFrame('a', 50 * MS, None, PairStatus.MOVING, q=np.zeros(3),
                         point=np.zeros(3), speed=1.0)
    assert pooler.needs_detection(moving)
    [s] = pooler.add(far, _dets(rng))
    expected = np.mean([[d.uv for d in dets] for dets in first[:2]], axis=0)
    np.testing.assert_allclose(s.observations['a'].uv, expected, atol=1e-12)
    assert s.observations['a'].n_frames == 2
    assert len(pooler.flush()[0].observations['a'].ids) == 3


def test_pooler_cap_validation():
    assert DwellPooler(_identity_fk).max_views == 0
    for bad in (-1, 1.5, True, '3'):
        with pytest.raises(ValueError, match='max_views'):
            DwellPooler(_identity_fk, max_views=bad)
    with pytest.raises(ValueError, match=r'max_views .* >= min_frames \(2\)'):
        DwellPooler(_identity_fk, min_frames=2, max_views=1)


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
        samples = _feed(col, ['c1', 'c2'])
        assert len(samples) == 2
        assert col.counts['detections'] == col.counts['frames_still'] > 30
        assert 'frames_skipped_dwell_full' not in col.counts
        assert sum(len(d.calls) for d in dets.values()) == col.counts['frames_still']
        assert all(s.observations['c1'].n_frames > 3 for s in samples)


def test_parameter_default_matches_the_collector_and_is_checked():
    p = BY_NAME['max_views_per_dwell']
    default = inspect.signature(SampleCollector).parameters['max_views_per_dwell'].default
    assert p.type == 'int' and p.default == default == 3
    assert check_value('max_views_per_dwell', 0) == 0
    with pytest.raises(ValueError, match='max_views_per_dwell'):
        check_value('max_views_per_dwell', -1)
    with pytest.raises(ValueError, match='max_views_per_dwell'):
        SampleCollector(None, [0, 0, 0], ['c'], {'c': None}, max_views_per_dwell=-2)
