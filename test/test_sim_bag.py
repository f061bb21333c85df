"""Bags written by the simulator: rosbag2 readers and rclpy read them; ground truth is complete."""

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

from armcal_ros.cli import main
from armcal_ros.io.bag import image_to_array, iter_messages
from armcal_ros.io.calib_files import read_cameras
from armcal_ros.sim.cell import simulate_cell, SimSettings
from armcal_ros.sim.output import read_ground_truth, write_sim_bag


@pytest.fixture(scope='module')
def short_cell():
    return simulate_cell('geometric', seed=11, settings=SimSettings(duration=3.0))


def test_mcap_bag_opens_with_anyreader_and_deserialises_with_rclpy(short_cell, tmp_path,
                                                                   monkeypatch):
    monkeypatch.setenv('ROS_LOG_DIR', str(tmp_path / 'log'))
    path = tmp_path / 'bag'
    counts = write_sim_bag(short_cell, path)
    assert counts['/joint_states'] == len(short_cell.joint_stamps_ns)
    assert sum(counts[f'/{c.name}/image_raw'] for c in short_cell.cameras) == \
        len(short_cell.frames)
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['storage_identifier'] == 'mcap' and meta['version'] == 9
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image, JointState
    seen = {'js': 0, 'img': 0}
    last_log = 0
    with AnyReader([path]) as reader:
        assert {c.topic for c in reader.connections} == {'/joint_states', '/cam1/image_raw',
                                                         '/cam2/image_raw', '/cam3/image_raw'}
        for conn, t, raw in reader.messages():
            assert t >= last_log
            last_log = t
            if conn.msgtype == 'sensor_msgs/msg/JointState':
                msg = deserialize_message(raw, JointState)
                assert list(msg.name) == short_cell.joint_names
                seen['js'] += 1
            else:
                msg = deserialize_message(raw, Image)
                assert msg.encoding == 'mono8' and (msg.width, msg.height) == (640, 480)
                assert msg.header.frame_id == conn.topic.split('/')[1] + '_optical_frame'
                seen['img'] += 1
                if seen['img'] == 1:
                    k = 0
                    f = short_cell.frames
                    stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                    assert stamp == f.stamp_ns[k]
                    img = np.frombuffer(bytes(msg.data), np.uint8).reshape(480, 640)
                    np.testing.assert_array_equal(img, short_cell.render(k))
    assert seen['js'] == len(short_cell.joint_stamps_ns) and seen['img'] == len(short_cell.frames)


def test_ground_truth_files(short_cell, tmp_path):
    path = tmp_path / 'bag'
    write_sim_bag(short_cell, path)
    gt = path / 'ground_truth'
    base, cams = read_cameras(gt)
    assert base == 'base_link' and [c.name for c in cams] == ['cam1', 'cam2', 'cam3']
    X = short_cell.dwells.true_marker
    for a, b in zip(cams, short_cell.cameras):
        np.testing.assert_allclose(a.project(X), b.project(X), atol=1e-8)
    truth = read_ground_truth(gt)
    np.testing.assert_allclose(truth['dwell_true'], X)
    np.testing.assert_allclose(truth['dwell_nominal'], short_cell.dwells.nominal_marker)
    np.testing.assert_array_equal(truth['frame_stamp_ns'], short_cell.frames.stamp_ns)
    assert list(truth['joint_names']) == short_cell.chain.joint_names
    assert truth['scenario']['scenario'] == 'geometric' and truth['scenario']['seed'] == 11
    errors = yaml.safe_load((gt / 'robot_errors.yaml').read_text())
    e = np.array(list(errors['geometric_errors'].values()))
    np.testing.assert_allclose(e, short_cell.robot.errors)


@pytest.mark.parametrize('storage,compressed,encoding', [
    ('sqlite3', None, 'mono8'), ('mcap', 'png', 'mono8'), ('mcap', 'jpeg', 'rgb8'),
    ('mcap', None, 'bgr8')])
def test_storage_compression_and_colour_options(tmp_path, storage, compressed, encoding):
    path = tmp_path / 'bag'
    sub = simulate_cell('geometric', seed=11,
                        settings=SimSettings(duration=2.5, camera_rate=4.0, joint_rate=50.0))
    write_sim_bag(sub, path, storage=storage, compressed=compressed, encoding=encoding,
                  ground_truth=False)
    suffix = '.db3' if storage == 'sqlite3' else '.mcap'
    assert (path / ('bag' + suffix)).exists()
    f = sub.frames
    k = 0
    n_img = 0
    for topic, msgtype, t, msg in iter_messages(path):
        if 'cam' not in topic:
            continue
        if compressed:
            assert topic.endswith('/image_raw/compressed')
            assert msg.format.startswith(f'{encoding}; {compressed} compressed')
        img, enc = image_to_array(msgtype, msg)
        ref = sub.render(k, encoding)
        if compressed == 'jpeg':
            ref = ref[..., ::-1] if encoding == 'rgb8' else ref      # decoded as bgr8
            assert np.abs(img.astype(int) - ref).max() < 40
        else:
            assert enc == encoding
            np.testing.assert_array_equal(img, ref)
        k += 1
        n_img += 1
    assert n_img == len(f)


def test_cli_simulate(tmp_path, capsys):
    out = tmp_path / 'cli_bag'
    assert main(['simulate', '--output', str(out), '--scenario', 'gp-prior', '--seed', '4',
                 '--duration', '3', '--quiet']) == 0
    assert (out / 'metadata.yaml').exists() and (out / 'ground_truth' / 'cam2.yaml').exists()
    scen = yaml.safe_load((out / 'ground_truth' / 'scenario.yaml').read_text())
    assert scen['scenario'] == 'gp-prior' and scen['seed'] == 4
    assert main(['simulate', '--output', str(out), '--duration', '3']) == 2
    assert 'exists' in capsys.readouterr().err


def test_driver_style_frame_ids_reach_the_bag_and_the_offline_outputs(short_cell, tmp_path):
    """Images in ``<camera>_color_optical_frame``: the frames the offline calibrator names."""
    from armcal_ros.offline import collect_samples
    from armcal_ros.settings import load_settings
    from helpers.params_files import PUMA_URDF, write_params
    path = tmp_path / 'bag'
    write_sim_bag(short_cell, path, frame_id_format='{camera}_color_optical_frame')
    frames = {m.header.frame_id for topic, _, _, m in iter_messages(path)
              if topic.endswith('image_raw')}
    assert frames == {f'cam{k}_color_optical_frame' for k in (1, 2, 3)}
    settings = load_settings(write_params(tmp_path / 'p.yaml', {},
                                          robot_description_file=PUMA_URDF,
                                          marker_link='marker'))
    front = collect_samples(str(path), settings)
    assert front.frame_ids == {f'cam{k}': f'cam{k}_color_optical_frame' for k in (1, 2, 3)}
    with pytest.raises(ValueError, match='frame_id_format'):
        write_sim_bag(short_cell, tmp_path / 'bad', frame_id_format='cam_optical_frame')
