"""make_detector: the detector of each marker type, its parameters checked by name."""
import pytest

from armcal_ros.frontend.detectors import (ArucoDetector, CharucoDetector, make_detector,
                                           SphereDetector)


@pytest.mark.parametrize('params,name', [
    (dict(min_radius_px=-1), 'min_radius_px'), (dict(max_radius_px=1.0), 'max_radius_px'),
    (dict(min_roundness=1.5), 'min_roundness'), (dict(ambiguity_ratio='x'), 'ambiguity_ratio'),
    (dict(blur_sigma_px=0.1), 'blur_sigma_px'), (dict(max_candidates=1), 'max_candidates'),
    (dict(bogus=3), 'bogus')])
def test_make_detector_validates_parameters(params, name):
    with pytest.raises(ValueError, match=name):
        make_detector('sphere', **params)


def test_make_detector_types():
    assert isinstance(make_detector('sphere', min_radius_px=2), SphereDetector)
    assert isinstance(make_detector('ArUco', dictionary='4x4_50', marker_id=3), ArucoDetector)
    with pytest.raises(ValueError, match='marker_type'):
        make_detector('hexagon')
    with pytest.raises(ValueError, match='dictionary'):
        make_detector('aruco', dictionary='DICT_NOPE')
    with pytest.raises(ValueError, match='marker_id'):
        make_detector('aruco', dictionary='DICT_4X4_50', marker_id=50)


def test_make_detector_builds_charuco():
    det = make_detector('charuco', rows=7, cols=5, square_size=0.04, marker_size=0.02,
                        dictionary='DICT_6X6_250', legacy=True)
    assert isinstance(det, CharucoDetector) and det.board.legacy
    with pytest.raises(ValueError, match='unknown charuco detector parameter'):
        make_detector('charuco', rows=7, cols=5, square_size=0.04, marker_size=0.02, nope=1)
