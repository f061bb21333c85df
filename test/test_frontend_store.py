"""Tests for samples and the sample store (point and board samples)."""

import json
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.frontend.samples import BoardTarget, Observation, Sample
from armcal_ros.frontend.store import AddResult, FILE_NAME, SampleStore
from helpers.board_scene import BOARD


def obs(uv=(100.0, 200.0), n_frames=5, spread=0.05, ids=(0,), stamp=7):
    return Observation(uv=np.reshape(uv, (-1, 2)), ids=ids, n_frames=n_frames,
                       spread_px=spread, stamp_ns=stamp)


def sample(point, cams=('cam1',), n_frames=5, q=None, **kw):
    return Sample(point_nominal=point, observations={c: obs(n_frames=n_frames) for c in cams},
                  q=q, **kw)


def test_validation():
    with pytest.raises(ValueError, match='point_nominal'):
        Sample(point_nominal=[0, 0])
    with pytest.raises(ValueError, match='ids'):
        Observation(uv=np.zeros((2, 2)), ids=[0])
    with pytest.raises(ValueError, match='pose'):
        Sample(point_nominal=[0, 0, 0], pose=np.eye(3))
    with pytest.raises(ValueError, match='max_samples'):
        SampleStore(max_samples=0)
    with pytest.raises(ValueError, match='same_point_tolerance'):
        SampleStore(min_sample_spacing=0.001, same_point_tolerance=0.01)
    with pytest.raises(ValueError, match='no observations'):
        SampleStore().add(Sample(point_nominal=[0, 0, 0]))


def test_add_assigns_ids_and_keeps_distinct_points():
    store = SampleStore(min_sample_spacing=0.005)
    for k in range(5):
        assert store.add(sample([0.01 * k, 0, 0])) is AddResult.ADDED
    assert len(store) == 5 and sorted(s.id for s in store) == [0, 1, 2, 3, 4]


def test_same_point_merges_observations_keeping_the_better():
    store = SampleStore(min_sample_spacing=0.005, same_point_tolerance=0.0005)
    store.add(sample([0, 0, 0], cams=('cam1', 'cam2'), n_frames=3))
    better = Sample(point_nominal=[0.0002, 0, 0],
                    observations={'cam2': obs(uv=(1, 2), n_frames=9), 'cam3': obs()})
    assert store.add(better) is AddResult.MERGED
    (s,) = store.samples
    assert set(s.observations) == {'cam1', 'cam2', 'cam3'}
    np.testing.assert_allclose(s.observations['cam2'].uv, [[1, 2]])
    np.testing.assert_allclose(s.point_nominal, 0.0)          # the stored point is kept
    worse = Sample(point_nominal=[0, 0.0001, 0], observations={'cam2': obs(n_frames=1)})
    assert store.add(worse) is AddResult.MERGED
    assert store.samples[0].observations['cam2'].n_frames == 9


def test_within_spacing_keeps_the_better_sample_without_mixing_points():
    store = SampleStore(min_sample_spacing=0.005, same_point_tolerance=0.0005)
    store.add(sample([0, 0, 0], cams=('cam1',)))
    assert store.add(sample([0.003, 0, 0], cams=('cam1',), n_frames=2)) is AddResult.DROPPED
    assert store.add(sample([0.003, 0, 0], cams=('cam1', 'cam2'))) is AddResult.REPLACED
    (s,) = store.samples
    np.testing.assert_allclose(s.point_nominal, [0.003, 0, 0])
    assert set(s.observations) == {'cam1', 'cam2'}
    assert store.counts[AddResult.DROPPED] == 1 and store.counts[AddResult.REPLACED] == 1


def test_bounded_size_keeps_spatial_diversity():
    store = SampleStore(max_samples=20, min_sample_spacing=0.001)
    rng = np.random.default_rng(0)
    # A cluster around one place, then points spread over a 1 m cube.
    for p in rng.normal(0, 0.01, (20, 3)):
        store.add(sample(p))
    assert len(store) == 20
    spread = rng.uniform(-0.5, 0.5, (40, 3))
    for p in spread:
        store.add(sample(p))
    assert len(store) == 20 and store.evicted > 0
    pts = store.arrays().points
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 9
    # FIFO would have kept only the last 20 spread points; the diversity rule keeps a set whose
    # smallest spacing is far larger than the cluster's 1 cm.
    assert d.min() > 0.1
    # Nearest-neighbour bookkeeping (in storage order) stays exact through evictions.
    pts = np.array([s.point_nominal for s in store._samples])
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 9
    np.testing.assert_allclose(store._nn_dist[:len(pts)], d.min(axis=1))


def test_remove_and_nearest_neighbours_stay_consistent():
    store = SampleStore(max_samples=50, min_sample_spacing=0.0)
    rng = np.random.default_rng(5)
    for p in rng.uniform(0, 1, (30, 3)):
        store.add(sample(p))
    for sid in (3, 17, 29, 0):
        assert store.remove(sid)
    assert not store.remove(3)
    pts = np.array([s.point_nominal for s in store._samples])
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 9
    np.testing.assert_allclose(store._nn_dist[:len(pts)], d.min(axis=1))


def test_solver_arrays():
    store = SampleStore()
    store.add(Sample(point_nominal=[0, 0, 1], observations={
        'cam2': obs(uv=(1, 2)), 'cam1': obs(uv=(3, 4))}))
    store.add(Sample(point_nominal=[0, 1, 1], observations={
        'cam3': obs(uv=[[5, 6], [7, 8]], ids=(4, 9), n_frames=2)}))
    a = store.arrays()
    assert a.camera_names == ('cam2', 'cam1', 'cam3')
    np.testing.assert_allclose(a.points, [[0, 0, 1], [0, 1, 1]])
    np.testing.assert_array_equal(a.camera_index, [0, 1, 2, 2])
    np.testing.assert_array_equal(a.point_index, [0, 0, 1, 1])
    np.testing.assert_allclose(a.uv, [[1, 2], [3, 4], [5, 6], [7, 8]])
    np.testing.assert_array_equal(a.target_ids, [0, 0, 4, 9])
    np.testing.assert_array_equal(a.n_frames, [5, 5, 2, 2])
    b = store.arrays(camera_names=['cam1', 'cam9'])
    np.testing.assert_array_equal(b.camera_index, [0])
    np.testing.assert_allclose(b.uv, [[3, 4]])
    empty = SampleStore().arrays()
    assert empty.points.shape == (0, 3) and empty.uv.shape == (0, 2)


def test_save_load_round_trip_and_resume(tmp_path):
    store = SampleStore(max_samples=100, min_sample_spacing=0.002, joint_names=('a', 'b'))
    rng = np.random.default_rng(2)
    for k in range(12):
        cams = ('cam1', 'cam2') if k % 3 else ('cam3',)
        s = Sample(point_nominal=rng.uniform(0, 1, 3),
                   observations={c: obs(uv=rng.uniform(0, 640, (k % 2 + 1, 2)),
                                        ids=np.arange(k % 2 + 1), n_frames=k + 1,
                                        spread=0.01 * k, stamp=1000 * k) for c in cams},
                   stamp_ns=10 ** 9 + k, q=rng.normal(size=2),
                   pose=np.eye(4) if k == 4 else None)
        if k % 4 == 1:               # a shaded-sphere view: its centroid kept beside it
            o = next(iter(s.observations.values()))
            o.centroid_uv, o.centroid_spread_px = o.uv + 0.3, 0.002 * k
        store.add(s)
    store.remove(5)
    assert np.count_nonzero(np.isfinite(store.arrays().centroid_uv[:, 0])) > 2
    path = store.save(str(tmp_path))
    assert path == os.path.join(str(tmp_path), FILE_NAME)
    assert os.listdir(tmp_path) == [FILE_NAME]               # no temporary file left
    loaded = SampleStore.load(str(tmp_path), joint_names=('a', 'b'))
    assert loaded.max_samples == 100 and loaded.min_sample_spacing == 0.002
    assert len(loaded) == len(store) == 11
    a, b = store.arrays(), loaded.arrays()
    for field in ('points', 'sample_ids', 'camera_index', 'point_index', 'uv', 'target_ids',
                  'n_frames', 'spread_px', 'centroid_uv', 'centroid_spread_px'):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert a.camera_names == b.camera_names
    by_id = {s.id: s for s in loaded}
    for s in store:
        t = by_id[s.id]
        np.testing.assert_array_equal(s.q, t.q)
        assert s.stamp_ns == t.stamp_ns
        assert (s.pose is None) == (t.pose is None)
        for c, o in s.observations.items():
            assert t.observations[c].stamp_ns == o.stamp_ns
    # Resume: new samples continue the id sequence.
    loaded.add(sample([5.0, 5.0, 5.0]))
    assert max(s.id for s in loaded) == 12
    with pytest.raises(ValueError, match='joint_names'):
        SampleStore.load(str(tmp_path), joint_names=('x', 'y'))


def test_save_is_atomic_on_failure(tmp_path, monkeypatch):
    store = SampleStore()
    store.add(sample([0, 0, 0]))
    store.save(str(tmp_path))
    store.add(sample([1, 0, 0]))

    def boom(*args, **kwargs):
        raise OSError('disk full')
    monkeypatch.setattr(os, 'replace', boom)
    with pytest.raises(OSError, match='disk full'):
        store.save(str(tmp_path))
    monkeypatch.undo()
    assert os.listdir(tmp_path) == [FILE_NAME]
    assert len(SampleStore.load(str(tmp_path))) == 1         # the previous file is intact


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        SampleStore.load(str(tmp_path))
    store = SampleStore()
    store.add(sample([0, 0, 0]))
    store.save(str(tmp_path))
    with pytest.raises(ValueError, match='bogus'):
        SampleStore.load(str(tmp_path), bogus=1)
    smaller = SampleStore.load(str(tmp_path), max_samples=5, min_sample_spacing=0.0001)
    assert smaller.max_samples == 5 and len(smaller) == 1
    assert smaller.same_point_tolerance == 0.0001            # clamped to the new spacing


def _board_sample(pose, ref_link):
    ref = ref_link @ pose[:3, :3].T + pose[:3, 3]
    return Sample(point_nominal=ref.mean(axis=0), pose=pose, reference_points=ref,
                  observations={'cam': Observation(np.zeros((3, 2)), [0, 1, 2])})


def test_store_tells_turned_board_views_apart():
    ref = BoardTarget(BOARD.points(), np.eye(4)).reference_points_in_link()
    ref = ref - ref.mean(axis=0)                    # centred: a turn keeps the centre
    store = SampleStore(min_sample_spacing=0.005)
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_rotvec([0, 0, 0.2]).as_matrix()
    assert store.add(_board_sample(np.eye(4), ref)) is AddResult.ADDED
    assert store.add(_board_sample(turned, ref)) is AddResult.ADDED
    assert store.add(_board_sample(turned, ref)) is AddResult.MERGED
    point = Sample(point_nominal=[1, 0, 0],
                   observations={'cam': Observation(np.zeros((1, 2)), [0])})
    with pytest.raises(ValueError, match='one kind of target'):
        store.add(point)


def test_version_1_store_files_still_load(tmp_path):
    store = SampleStore()
    for k in range(3):
        store.add(Sample(point_nominal=[0.1 * k, 0, 0], q=[k, 0.0],
                         observations={'cam': Observation([[10.0 * k, 5.0]], [0])}))
    store.save(tmp_path)
    path = tmp_path / FILE_NAME
    with np.load(path) as z:
        data = {k: z[k] for k in z.files if k not in ('has_reference', 'reference_points')}
    meta = json.loads(str(data['meta']))
    meta['version'] = 1
    data['meta'] = np.array(json.dumps(meta))
    np.savez_compressed(path, **data)
    back = SampleStore.load(tmp_path)
    assert len(back) == 3 and all(s.reference_points is None for s in back)
    np.testing.assert_allclose(sorted(s.point_nominal[0] for s in back), [0, 0.1, 0.2])


def test_a_moved_cameras_retired_views_return_as_its_earlier_self_on_the_points_held():
    store = SampleStore(min_sample_spacing=0.01)
    for k in range(6):
        store.add(Sample(point_nominal=[0.05 * k, 0, 0],
                         observations={'cam1': obs(stamp=100 * k),
                                       'cam2': obs(uv=(10.0 * k, 5.0), stamp=100 * k)},
                         stamp_ns=100 * k))
    store.add(Sample(point_nominal=[0, 0.5, 0], observations={'cam2': obs(stamp=50)},
                     stamp_ns=50))
    store.retire(300, epoch=1, camera='cam2')
    store.retire(0, epoch=2, camera='cam1')              # nothing that old: no entry
    # The cam2-only sample went with its view: three of the four retired are on held points.
    assert store.retired_views() == {('cam2', 1): 3}
    arrays = store.arrays(['cam1', 'cam2'], epochs={'cam2#1': ('cam2', 1)})
    assert arrays.camera_names == ('cam1', 'cam2', 'cam2#1')
    assert len(arrays.points) == 6
    rows = np.flatnonzero(arrays.camera_index == 2)
    np.testing.assert_allclose(arrays.uv[rows, 0], [0.0, 10.0, 20.0])
    np.testing.assert_allclose(arrays.points[arrays.point_index[rows], 0], [0.0, 0.05, 0.1])
    # Views from a time on (a disagreement reported before the change was declared) left out.
    assert store.retired_views(until_ns={('cam2', 1): 150}) == {('cam2', 1): 2}
    cut = store.arrays(['cam1', 'cam2'], epochs={'cam2#1': ('cam2', 1)},
                       until_ns={('cam2', 1): 150})
    np.testing.assert_allclose(cut.uv[cut.camera_index == 2, 0], [0.0, 10.0])
    back = arrays.without_cameras(['cam2#1'])
    plain = store.arrays(['cam1', 'cam2'])
    assert back.camera_names == plain.camera_names
    for key in ('camera_index', 'point_index', 'uv', 'n_frames', 'spread_px'):
        np.testing.assert_array_equal(getattr(back, key), getattr(plain, key))


def test_retired_observations_leave_the_solver_view_and_survive_a_restart(tmp_path):
    store = SampleStore(min_sample_spacing=0.01)
    for k in range(6):
        store.add(Sample(point_nominal=[0.05 * k, 0, 0], q=np.full(3, 0.1 * k),
                         observations={'cam1': obs(stamp=100 * k), 'cam2': obs(stamp=100 * k)},
                         stamp_ns=100 * k))
    store.add(Sample(point_nominal=[0, 0.5, 0], observations={'cam2': obs(stamp=50)},
                     stamp_ns=50))
    assert store.first_stamp_ns() == 0
    assert store.retire(300, epoch=1, camera='cam2') == 4       # stamps 0, 50, 100, 200
    assert store.first_stamp_ns() == 0                          # a retired view still counts
    assert store.views_per_camera() == {'cam1': 6, 'cam2': 3}
    arrays = store.arrays(['cam1', 'cam2'])
    assert len(store) == 6                   # the cam2-only sample went with its observation
    assert sum(arrays.camera_index == 1) == 3 and sum(arrays.camera_index == 0) == 6
    assert [e for e, _ in store.retired] == [1] * 4
    store.save(str(tmp_path))
    back = SampleStore.load(str(tmp_path))
    assert len(back) == 6 and len(back.retired) == 4
    assert sorted(s.stamp_ns for _, s in back.retired) == [0, 50, 100, 200]
    assert all(list(s.observations) == ['cam2'] for _, s in back.retired)
    assert back.retired[0][1].q is not None
    # every camera (an arm change): cam1's three oldest go too
    assert back.retire(300, epoch=2) == 3
    assert len(back) == 3


def test_forgetting_drops_old_views_for_good_and_keeps_the_sessions_origin(tmp_path):
    store = SampleStore(min_sample_spacing=0.01)
    for k in range(6):
        store.add(Sample(point_nominal=[0.05 * k, 0, 0],
                         observations={'cam1': obs(stamp=1000 + 100 * k),
                                       'cam2': obs(stamp=1000 + 100 * k + 50)},
                         stamp_ns=1000 + 100 * k))
    store.retire(1300, epoch=1, camera='cam2')          # cam2 at 1050, 1150, 1250
    # Views before 1200 go, held or retired: cam1 1000, 1100 and cam2 1050, 1150.
    assert store.forget(1200) == 4
    assert len(store) == 4 and store.views_per_camera() == {'cam1': 4, 'cam2': 3}
    assert [(e, s.observations['cam2'].stamp_ns) for e, s in store.retired] == [(1, 1250)]
    # The origin of the times said stays the first view given, through a restart too.
    assert store.first_stamp_ns() == 1000
    store.save(str(tmp_path))
    assert SampleStore.load(str(tmp_path)).first_stamp_ns() == 1000
    # A file written before the origin was saved: the earliest view it holds.
    path = tmp_path / FILE_NAME
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    meta = json.loads(str(data['meta']))
    del meta['origin_ns']
    data['meta'] = np.array(json.dumps(meta))
    np.savez_compressed(path, **data)
    assert SampleStore.load(str(tmp_path)).first_stamp_ns() == 1200
