"""The ArUco detector on rendered tags: the centre from the diagonals, 16-bit and colour images."""

import cv2
import numpy as np
import pytest

from armcal_ros.frontend.detectors import ArucoDetector, diagonal_intersection

SHAPE = (480, 640)


@pytest.fixture
def rng():
    return np.random.default_rng(42)


def test_diagonal_intersection_is_the_projective_centre():
    # A strongly foreshortened square: the corner mean is off, the diagonals are not.
    H = np.array([[1.0, 0.2, 100.0], [0.1, 0.9, 80.0], [0.002, 0.001, 1.0]])
    square = np.array([[0, 0], [100, 0], [100, 100], [0, 100]], float)
    quad = cv2.perspectiveTransform(square[None], H)[0]
    centre = cv2.perspectiveTransform(np.array([[[50.0, 50.0]]]), H)[0, 0]
    np.testing.assert_allclose(diagonal_intersection(quad), centre, atol=1e-9)
    assert np.linalg.norm(quad.mean(axis=0) - centre) > 1.0
    assert diagonal_intersection(np.zeros((4, 2))) is None


def _render_tag(rng, tag_id, H_low, dictionary=cv2.aruco.DICT_4X4_50, side=60, ss=4,
                noise=2.0):
    """Render tag ``tag_id`` (with a white quiet zone) through homography ``H_low``."""
    d = cv2.aruco.getPredefinedDictionary(dictionary)
    tag = cv2.aruco.generateImageMarker(d, tag_id, side * ss, borderBits=1)
    pad = side * ss // 3
    src = cv2.copyMakeBorder(tag, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    # Pixel-centre convention: src pixel (i, j) centre at (j, i); the tag spans
    # [pad - 0.5, pad + side*ss - 0.5] so its centre is pad + (side*ss - 1) / 2.
    c_src = pad + (side * ss - 1) / 2.0
    # Work at ss x resolution then area-downsample: low-res pixel x <-> high-res ss x + (ss-1)/2.
    S = np.array([[ss, 0, (ss - 1) / 2.0], [0, ss, (ss - 1) / 2.0], [0, 0, 1]])
    Sinv = np.linalg.inv(S)
    to_src = np.diag([ss, ss, 1.0])            # tag coords in "low-res tag pixels" -> src
    H_hi = S @ H_low @ np.linalg.inv(to_src)
    hi = cv2.warpPerspective(src, H_hi, (SHAPE[1] * ss, SHAPE[0] * ss), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=90)
    low = cv2.resize(hi, (SHAPE[1], SHAPE[0]), interpolation=cv2.INTER_AREA).astype(float)
    img = np.clip(np.round(0.2 * 255 + 0.6 * low + rng.normal(0, noise, low.shape)), 0, 255)
    centre_hi = H_hi @ np.array([c_src, c_src, 1.0])
    centre = Sinv @ centre_hi
    return img.astype(np.uint8), centre[:2] / centre[2]


@pytest.mark.parametrize('tilt', [0.0, 0.4, 0.8])
def test_aruco_centre_on_warped_tag(rng, tilt):
    errors = []
    for k in range(5):
        # Homography of a plane tilted about the vertical axis, seen by f = 600 px.
        # An 8 cm tag at 0.8 m: about 60 px across when facing the camera.
        f, z, side, tag_m = 600.0, 0.8, 60, 0.08
        R = cv2.Rodrigues(np.array([0.1 * k - 0.2, tilt, 0.05 * k]))[0]
        scale = tag_m / side                   # metres per "tag pixel"
        K = np.array([[f, 0, 300.0 + 10 * k], [0, f, 240.0], [0, 0, 1]])
        A = np.column_stack([R[:, 0] * scale, R[:, 1] * scale,
                             np.array([0.0, 0.0, z]) - R @ np.array([tag_m / 2, tag_m / 2, 0])])
        H = K @ A
        H /= H[2, 2]
        img, centre = _render_tag(rng, 7, H, side=side)
        dets = ArucoDetector('DICT_4X4_50').detect(img)
        assert [d.id for d in dets] == [7]
        errors.append(np.linalg.norm(dets[0].uv - centre))
        assert ArucoDetector('DICT_4X4_50', marker_id=3).detect(img) == []
    assert max(errors) < 0.3


def test_aruco_on_16_bit_and_colour(rng):
    H = np.array([[1.0, 0.0, 200.0], [0.0, 1.0, 150.0], [0.0, 0.0, 1.0]])
    img, centre = _render_tag(rng, 2, H)
    for image in (img.astype(np.uint16) * 257, cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)):
        dets = ArucoDetector('DICT_4X4_50').detect(image)
        assert len(dets) == 1 and np.linalg.norm(dets[0].uv - centre) < 0.3
    assert ArucoDetector('DICT_4X4_50').detect(np.zeros(SHAPE, np.uint8)) == []
