"""
ChArUco board detection on rendered boards: corner accuracy, partial views, numbering.

The boards are rendered by a 1280 x 960 camera with f = 1000 px; the detector searches only the
board's own markers of its dictionary, and must give the corners cv2's detector gives with the
whole dictionary.
"""

import os

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.frontend.detectors import CharucoBoard, CharucoDetector
from armcal_ros.frontend.detectors.base import aruco_dictionary
from helpers.board_scene import BOARD, render_board

DATA = os.path.join(os.path.dirname(__file__), '..', '..', 'shared', 'data',
                    'rct_test_set_charuco')
K = np.array([[1000.0, 0, 639.5], [0, 1000.0, 479.5], [0, 0, 1]])


def render(board, R, t, noise=2.0, seed=0):
    """Render ``board`` (opencv orientation) seen by camera K at pose (R, t)."""
    return render_board(board, R, t, K, (1280, 960), pps=60, margin=30, noise=noise, seed=seed)


def project(P, R, t):
    x = (K @ (R @ P.T + t[:, None])).T
    return x[:, :2] / x[:, 2:]


@pytest.mark.parametrize('tilt', [0.0, 30.0, 50.0])
def test_corner_accuracy_on_rendered_board(tilt):
    board = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250')
    R = Rotation.from_euler('xyz', [tilt, 10, 5], degrees=True).as_matrix()
    t = np.array([-0.1, -0.14, 0.6])
    uv, ids = CharucoDetector(board).detect_arrays(render(board, R, t))
    assert list(ids) == list(range(board.n_corners))
    err = np.linalg.norm(uv - project(board.points()[ids], R, t), axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.1
    assert err.max() < 0.3


def test_partial_view_gives_the_visible_corners_with_their_ids():
    board = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250')
    R = Rotation.from_euler('xyz', [15, -10, 0], degrees=True).as_matrix()
    t = np.array([-0.1, -0.14, 0.6])
    img = render(board, R, t)
    truth_all = project(board.points(), R, t)
    # Hide the lower half of the board (and some margin below its middle row of corners).
    cut = int(np.median(truth_all[:, 1])) + 10
    img[cut:, :] = 128
    det = CharucoDetector(board)
    uv, ids = det.detect_arrays(img)
    visible = np.flatnonzero(truth_all[:, 1] < cut - 25)
    assert 4 <= len(ids) < board.n_corners
    assert set(visible) <= set(ids)
    assert np.all(truth_all[ids, 1] < cut)
    err = np.linalg.norm(uv - truth_all[ids], axis=1)
    assert err.max() < 0.3
    dets = det.detect(img)
    assert [d.id for d in dets] == list(ids)
    # radius_px is half a square (60 px/square at this distance, give or take the tilt).
    assert 15 < dets[0].radius_px < 40


def test_no_board_and_too_few_corners():
    board = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250')
    det = CharucoDetector(board, min_corners=4)
    assert det.detect(np.full((480, 640), 128, np.uint8)) == []
    assert det.last_status == 'none'
    R, t = np.eye(3), np.array([-0.1, -0.14, 0.6])
    img = render(board, R, t)
    truth = project(board.points(), R, t)
    # Keep only the top-left square's neighbourhood: at most a couple of corners.
    img[:, int(truth[0, 0]) + 20:] = 128
    img[int(truth[0, 1]) + 20:, :] = 128
    assert CharucoDetector(board, min_corners=4).detect(img) == []


def test_legacy_numbering_is_the_mirrored_rows_in_a_half_turned_frame():
    new = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250')
    old = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250', legacy=True)
    R = Rotation.from_euler('xyz', [20, 0, 0], degrees=True).as_matrix()
    t = np.array([-0.1, -0.14, 0.6])
    img = render(new, R, t)
    uv_new, id_new = CharucoDetector(new).detect_arrays(img)
    uv_old, id_old = CharucoDetector(old).detect_arrays(img)
    j = np.arange(new.n_corners)
    expect = (5 - j // 4) * 4 + j % 4          # legacy ids: the rows of corners reversed
    assert list(old.ids_from_opencv(j)) == list(expect)
    by_old = dict(zip(id_old, uv_old))
    for k, i in enumerate(id_new):
        assert np.allclose(by_old[expect[i]], uv_new[k], atol=1e-6)
    # Same physical corner: p_old = (x, rows * s - y, 0), a half turn about x plus a shift.
    p_new, p_old = new.points()[j], old.points()[expect]
    assert np.allclose(p_old[:, 0], p_new[:, 0])
    assert np.allclose(p_old[:, 1], 7 * 0.04 - p_new[:, 1])


def test_legacy_square_pattern_for_even_rows():
    old = CharucoBoard(6, 5, 0.04, 0.02, 'DICT_6X6_250', legacy=True)
    new = CharucoBoard(6, 5, 0.04, 0.02, 'DICT_6X6_250')
    img = render(old, np.eye(3), np.array([-0.1, -0.12, 0.6]))
    assert len(CharucoDetector(old).detect_arrays(img)[1]) == old.n_corners
    assert len(CharucoDetector(new).detect_arrays(img)[1]) == 0


def test_board_validation_and_dictionary_codes():
    assert CharucoBoard(7, 5, 0.036, 0.018, 10).dictionary == 'DICT_6X6_250'
    with pytest.raises(ValueError, match='marker_size'):
        CharucoBoard(7, 5, 0.03, 0.03)
    with pytest.raises(ValueError, match='rows'):
        CharucoBoard(1, 5, 0.03, 0.02)
    with pytest.raises(ValueError, match='dictionary'):
        CharucoBoard(7, 5, 0.03, 0.02, 'DICT_NOPE')
    with pytest.raises(ValueError, match='markers'):
        CharucoBoard(12, 12, 0.03, 0.02, 'DICT_4X4_50')
    pts = CharucoBoard(4, 3, 0.05, 0.03).points()
    assert pts.shape == (6, 3)
    assert np.allclose(pts[3], [0.10, 0.10, 0.0])
    assert np.allclose(pts[4], [0.05, 0.15, 0.0])


@pytest.mark.skipif(not os.path.isdir(DATA), reason='real data ../shared/data not present')
def test_real_image_detection():
    img = cv2.imread(os.path.join(DATA, 'images', '0.png'), cv2.IMREAD_GRAYSCALE)
    board = CharucoBoard(7, 5, 0.036195, 0.018256, 10, legacy=True)
    uv, ids = CharucoDetector(board).detect_arrays(img)
    assert len(ids) >= 20
    # The committed fixture was detected the same way.
    from armcal_ros.io.rct_import import load_views
    _, uvs, fids, _, _ = load_views(os.path.join(os.path.dirname(__file__), 'data',
                                                 'rct_charuco', 'corners.json'))
    assert list(fids[0]) == list(ids)
    assert np.abs(uvs[0] - uv).max() < 0.01


def _full_dictionary_detector(board):
    """cv2's ChArUco detector over the whole dictionary, with CharucoDetector's parameters."""
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
        # The foreign marker, an unidentified candidate for the board-only dictionary, can
        # nudge cv2's refinement.
        assert np.abs(uv - full).max() < 0.02
    else:
        np.testing.assert_array_equal(uv, full)
    # Both as accurate against the true projections.
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
