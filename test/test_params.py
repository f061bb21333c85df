"""Parameter table: types, checks by name, parameter files as ROS 2 writes them."""
import pytest

from armcal_ros.params import check_all, check_value, defaults, load_params_file
from armcal_ros.settings import prior_settings, solver_settings


def test_defaults_pass_their_own_checks():
    values = defaults()
    for name, v in values.items():
        assert check_value(name, v) == v
    values['robot_description'] = '<robot name="x"/>'
    check_all(values)
    assert prior_settings(values).model == 'auto'
    # pixel_sigma 0 (the default): estimated, starting at 0.5 px; a number: used as given.
    assert solver_settings(values).pixel_sigma == 0.5
    assert solver_settings(values).estimate_noise is True
    given = solver_settings(dict(values, pixel_sigma=0.3))
    assert given.pixel_sigma == 0.3 and given.estimate_noise is False


@pytest.mark.parametrize('name,value,why', [
    ('pixel_sigma', -1.0, '>= 0'),
    ('pixel_sigma', 'big', 'expected double'),
    ('noise_model', 'magic', 'must be one of'),
    ('camera_names', ['cam 1'], 'A-Za-z0-9_'),
    ('camera_names', ['a', 'a'], 'duplicate'),
    ('marker_offset', [0.0, 1.0], '3 finite numbers'),
    ('min_samples', 0, '>= 1'),
    ('min_samples', 2.5, 'expected int'),
    ('free_distortion', ['k7'], 'unknown terms'),
    ('publish_tf', 1, 'expected bool'),
    ('pixel_sigma', 1e300, '<= 50'),
    ('pixel_sigma', float('nan'), 'finite'),
    ('point_sigma', float('inf'), 'finite'),
    ('marker_offset', [0.0, float('nan'), 0.0], 'finite'),
    ('max_samples', 10 ** 12, '<= 1e+07'),
    ('camera_info_names', ['front/rgb'], 'A-Za-z0-9_'),
])
def test_bad_values_are_refused_with_name_and_reason(name, value, why):
    with pytest.raises(ValueError) as err:
        check_value(name, value)
    assert name in str(err.value) and why in str(err.value)


def test_an_integer_is_a_valid_double():
    v = check_value('pixel_sigma', 1)
    assert v == 1.0 and isinstance(v, float)
    assert check_value('marker_offset', [0, 0, 1]) == [0.0, 0.0, 1.0]


def test_cross_parameter_rules():
    values = defaults()
    values['robot_description'] = '<robot name="x"/>'
    values['image_topics'] = ['/a']
    with pytest.raises(ValueError, match='camera_names and image_topics'):
        check_all(values)
    values = defaults()
    with pytest.raises(ValueError, match='robot_description'):
        check_all(values)
    for latency, why in (([0.01, 0.02], 'image_stamp_latency must be empty, one value or one '
                                        'per camera'),
                         ([2.0], 'image_stamp_latency must be within 1 s')):
        values = defaults()
        values['robot_description'] = '<robot name="x"/>'
        values['image_stamp_latency'] = latency
        with pytest.raises(ValueError, match=why):
            check_all(values)


def test_parameter_file_sections_unknown_names_and_relative_urdf(tmp_path):
    (tmp_path / 'robot.urdf').write_text('<robot name="r"/>')
    p = tmp_path / 'p.yaml'
    p.write_text('/**:\n  ros__parameters:\n    pixel_sigma: 0.7\n    min_samples: 5\n'
                 'armcal:\n  ros__parameters:\n    robot_description_file: robot.urdf\n'
                 '    min_samples: 8\n')
    v = load_params_file(p)
    assert v['pixel_sigma'] == 0.7 and v['min_samples'] == 8
    assert v['robot_description_file'] == str(tmp_path / 'robot.urdf')
    p.write_text('armcal:\n  ros__parameters:\n    robot_description_file: r.urdf\n'
                 '    pixle_sigma: 0.7\n    foo: 1\n')
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['foo', 'pixle_sigma'\]"):
        load_params_file(p)
    p.write_text('other_node:\n  ros__parameters:\n    a: 1\n')
    with pytest.raises(ValueError, match='no ros__parameters'):
        load_params_file(p)
