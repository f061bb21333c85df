"""
Bounded, spatially de-duplicated store of samples, saved atomically so a restart resumes.

Policy (memory and solve time are bounded by the workspace, not by the session's length):

- a new sample within ``same_point_tolerance`` of a stored one is the *same* 3D point (the
  arm came back, or a parked arm produced several dwells): their observations are merged,
  keeping per camera the better one (more frames, then less spread);
- a new sample within ``min_sample_spacing`` of a stored one (but not the same point) is
  redundant: the better of the two samples (more cameras, more frames, less spread) is kept
  and the other dropped.  Observations are never moved between different 3D points, which
  would bias the adjustment by up to the spacing;
- when ``max_samples`` are stored, a sample farther from its nearest neighbour than the
  closest stored pair is from each other replaces the worse of that pair; otherwise it is
  dropped.  This greedily keeps the stored points spread over the workspace (it maximises
  the smallest spacing) rather than keeping the most recent ones, which would all come from
  wherever the operator happens to be working.

A camera that moved (or a changed arm) starts a new *epoch*: :meth:`SampleStore.retire` moves its
observations from before the change out of the samples into ``retired``, tagged with the epoch,
where they are kept (and saved); :meth:`SampleStore.arrays` gives them back on request as a camera
of another name (the camera as it was).  A sample left with no observation goes with them.
:meth:`SampleStore.forget` drops observations older than a time, retired ones included, for
good: forgetting for slow drift keeps memory and the saved file bounded over any session.

"Distance" between two samples is that of their nominal points; for an extended target (a
board) it is the largest distance between corresponding reference points
(:meth:`~armcal_ros.frontend.samples.Sample.key_points`), so two views of a board from the same
place but turned are different samples.  One store holds one kind of target.
"""

from dataclasses import dataclass, replace
import enum
import json
import os
import tempfile
from typing import List, Optional, Tuple

import numpy as np

from .samples import Observation, Sample

FORMAT_VERSION = 3
#: Versions :meth:`SampleStore.load` reads (1: point targets only, no reference points; 2: no
#: retired observations).
READABLE_VERSIONS = (1, 2, 3)
FILE_NAME = 'samples.npz'
# Two dwells whose nominal points are closer than this are the same place (robot repeatability
# is ~0.1 mm; encoder noise is far smaller).
DEFAULT_SAME_POINT_TOLERANCE = 0.0005


class AddResult(enum.Enum):
    """What :meth:`SampleStore.add` did with a sample."""

    ADDED = 'added'
    MERGED = 'merged'          # same point: observations merged into the stored sample
    REPLACED = 'replaced'      # within spacing and better: took the stored sample's place
    DROPPED = 'dropped'        # within spacing and not better, or the store is full


@dataclass
class SolverArrays:
    """
    A store's content as flat arrays for the adjustment.

    ``points`` (N, 3) nominal 3D points (metres), ``sample_ids`` (N,); per observation (M):
    ``camera_index`` into ``camera_names``, ``point_index`` into ``points``, ``uv`` (M, 2),
    ``target_ids`` (M,), ``n_frames`` (M,), ``spread_px`` (M,) (the observation's spread,
    repeated for each of its K points); ``centroid_uv`` (M, 2) and ``centroid_spread_px``
    (M,) the intensity centroids beside fitted centres (:class:`Observation`), NaN where an
    observation has none.
    """

    points: np.ndarray
    sample_ids: np.ndarray
    camera_names: tuple
    camera_index: np.ndarray
    point_index: np.ndarray
    uv: np.ndarray
    target_ids: np.ndarray
    n_frames: np.ndarray
    spread_px: np.ndarray
    centroid_uv: Optional[np.ndarray] = None
    centroid_spread_px: Optional[np.ndarray] = None

    def __post_init__(self):
        m = self.uv.shape[0]
        if self.centroid_uv is None:
            self.centroid_uv = np.full((m, 2), np.nan)
        if self.centroid_spread_px is None:
            self.centroid_spread_px = np.full(m, np.nan)

    def without_cameras(self, names):
        """Return these arrays without the observations of the cameras ``names`` (points kept)."""
        drop = set(names)
        keep = [c for c, n in enumerate(self.camera_names) if n not in drop]
        index = -np.ones(len(self.camera_names), np.intp)
        index[keep] = np.arange(len(keep))
        rows = index[self.camera_index] >= 0
        per_observation = ('point_index', 'uv', 'target_ids', 'n_frames', 'spread_px',
                           'centroid_uv', 'centroid_spread_px')
        return replace(self, camera_names=tuple(self.camera_names[c] for c in keep),
                       camera_index=index[self.camera_index[rows]],
                       **{k: getattr(self, k)[rows] for k in per_observation})


class SampleStore:
    """
    Samples keyed by id with bounded size and a minimum spacing (see the module policy).

    ``same_point_tolerance`` defaults to min(0.5 mm, ``min_sample_spacing``).
    ``joint_names`` (optional) is recorded with the samples so that a saved store is not
    resumed against a different robot.
    """

    def __init__(self, max_samples=2000, min_sample_spacing=0.005, same_point_tolerance=None,
                 joint_names=None):
        if int(max_samples) != max_samples or max_samples < 1:
            raise ValueError(f'max_samples must be a positive integer, got {max_samples!r}')
        self.max_samples = int(max_samples)
        self.min_sample_spacing = float(min_sample_spacing)
        if not self.min_sample_spacing >= 0:
            raise ValueError(f'min_sample_spacing must be >= 0 (m), got {min_sample_spacing}')
        if same_point_tolerance is None:
            same_point_tolerance = min(DEFAULT_SAME_POINT_TOLERANCE, self.min_sample_spacing)
        self.same_point_tolerance = float(same_point_tolerance)
        if not 0 <= self.same_point_tolerance <= max(self.min_sample_spacing, 0.0):
            raise ValueError(f'same_point_tolerance must be in [0, min_sample_spacing], '
                             f'got {same_point_tolerance}')
        self.joint_names = None if joint_names is None else tuple(joint_names)
        self._samples = []
        self._keys = None             # (max_samples + 1, R, 3), allocated by the first sample
        self._nn_dist = np.zeros(self.max_samples + 1)
        self._nn_idx = np.zeros(self.max_samples + 1, np.intp)
        self._next_id = 0
        self.revision = 0          # incremented on every change
        self.counts = {r: 0 for r in AddResult}
        self.evicted = 0
        #: (epoch, sample) of observations retired by a change (:meth:`retire`).
        self.retired: List[Tuple[int, Sample]] = []
        self._origin_ns = None                   # the earliest stamp ever given (first_stamp_ns)

    def __len__(self):
        return len(self._samples)

    def __iter__(self):
        return iter(list(self._samples))

    @property
    def samples(self):
        """Return a copy of the list of stored samples."""
        return list(self._samples)

    @property
    def camera_names(self):
        """Cameras with at least one observation, in order of first appearance by sample id."""
        names = []
        for s in sorted(self._samples, key=lambda s: s.id):
            for name in s.observations:
                if name not in names:
                    names.append(name)
        return tuple(names)

    def first_stamp_ns(self):
        """
        Return the earliest observation stamp the store was ever given (0: none).

        The origin of the times in change summaries ("t = 95 s"): it stays when the views
        it came from are retired, forgotten or replaced, and is saved with the samples.
        """
        return 0 if self._origin_ns is None else self._origin_ns

    def _note_origin(self, stamps):
        stamps = [int(t) for t in stamps]
        if stamps:
            first = min(stamps)
            self._origin_ns = first if self._origin_ns is None else min(self._origin_ns, first)

    def views_per_camera(self):
        """Return camera name -> the number of stored samples that camera saw."""
        out = {}
        for smp in self._samples:
            for name in smp.observations:
                out[name] = out.get(name, 0) + 1
        return out

    def retired_views(self, until_ns=None):
        """
        Return (camera, epoch) -> its retired observations on samples still held.

        ``until_ns`` ((camera, epoch) -> ns) counts only those stamped before that time.
        """
        held = {smp.id for smp in self._samples}
        until_ns = until_ns or {}
        out = {}
        for tag, smp in self.retired:
            if smp.id in held:
                for name, o in smp.observations.items():
                    if o.stamp_ns < until_ns.get((name, tag), np.inf):
                        out[(name, tag)] = out.get((name, tag), 0) + 1
        return out

    def retired_since(self, camera, epoch, since_ns):
        """
        Return how many of ``camera``'s views retired as ``epoch`` are from ``since_ns`` on.

        Every retired view counts, on samples held or not (unlike :meth:`retired_views`): the
        count is of the views the change monitor tested, not of those a solve can use.
        """
        return sum(1 for tag, smp in self.retired if tag == epoch and camera in smp.observations
                   and smp.observations[camera].stamp_ns >= since_ns)

    def clear(self):
        """Remove every sample (ids keep increasing)."""
        self._samples = []
        self._keys = None
        self.revision += 1

    def _distances(self, keys, n):
        """Return the distances (n,) of the first n stored samples from ``keys`` (R, 3)."""
        return np.linalg.norm(self._keys[:n] - keys, axis=2).max(axis=1)

    # -- adding -------------------------------------------------------------------------

    def add(self, sample):
        """Add ``sample`` under the module's policy; return an :class:`AddResult`."""
        if not isinstance(sample, Sample):
            raise ValueError(f'sample must be a Sample, got {type(sample).__name__}')
        if not sample.observations:
            raise ValueError('sample has no observations')
        keys = sample.key_points()
        if self._keys is not None and keys.shape != self._keys.shape[1:]:
            raise ValueError(f'sample has {len(keys)} reference points, the stored ones '
                             f'{self._keys.shape[1]}: one store holds one kind of target')
        self._note_origin(o.stamp_ns for o in sample.observations.values())
        result = self._add(sample)
        self.counts[result] += 1
        if result is not AddResult.DROPPED:
            self.revision += 1
        return result

    def _add(self, sample):
        n = len(self._samples)
        keys = sample.key_points()
        if n:
            d = self._distances(keys, n)
            j = int(np.argmin(d))
            dist = float(d[j])
            if dist <= self.same_point_tolerance:
                self._merge_into(self._samples[j], sample)
                return AddResult.MERGED
            if dist < self.min_sample_spacing:
                if sample.rank() > self._samples[j].rank():
                    self._remove_at(j)
                    self._insert(sample)
                    return AddResult.REPLACED
                return AddResult.DROPPED
            if n >= self.max_samples:
                i = int(np.argmin(self._nn_dist[:n]))
                if dist <= self._nn_dist[i]:
                    return AddResult.DROPPED
                k = int(self._nn_idx[i])
                worse = i if self._samples[i].rank() < self._samples[k].rank() else k
                self._remove_at(worse)
                self.evicted += 1
        self._insert(sample)
        return AddResult.ADDED

    @staticmethod
    def _merge_into(kept, new):
        for name, obs in new.observations.items():
            old = kept.observations.get(name)
            if old is None or obs.better_than(old):
                kept.observations[name] = obs

    def _insert(self, sample):
        if sample.id < 0:
            sample.id = self._next_id
        self._next_id = max(self._next_id, sample.id + 1)
        n = len(self._samples)
        keys = sample.key_points()
        if self._keys is None:
            self._keys = np.zeros((self.max_samples + 1,) + keys.shape)
        self._samples.append(sample)
        self._keys[n] = keys
        if n == 0:
            self._nn_dist[0], self._nn_idx[0] = np.inf, 0
            return
        d = self._distances(keys, n)
        j = int(np.argmin(d))
        self._nn_dist[n], self._nn_idx[n] = d[j], j
        closer = d < self._nn_dist[:n]
        self._nn_dist[:n][closer] = d[closer]
        self._nn_idx[:n][closer] = n

    def _remove_at(self, r):
        n = len(self._samples)
        last = n - 1
        affected = np.flatnonzero(self._nn_idx[:n] == r)
        self._samples[r] = self._samples[last]
        self._keys[r] = self._keys[last]
        self._nn_dist[r] = self._nn_dist[last]
        self._nn_idx[r] = self._nn_idx[last]
        self._samples.pop()
        n = last
        self._nn_idx[:n][self._nn_idx[:n] == last] = r
        affected = {int(a if a != last else r) for a in affected if a != r}
        for a in affected:
            if a >= n:
                continue
            self._nn_dist[a], self._nn_idx[a] = self._nearest(a, n)

    def _nearest(self, a, n):
        if n <= 1:
            return np.inf, a
        d = self._distances(self._keys[a], n)
        d[a] = np.inf
        j = int(np.argmin(d))
        return d[j], j

    def remove(self, sample_id):
        """Remove the sample with ``sample_id``; return True if it was stored."""
        for r, s in enumerate(self._samples):
            if s.id == sample_id:
                self._remove_at(r)
                self.revision += 1
                return True
        return False

    def retire(self, before_ns, epoch, camera: Optional[str] = None):
        """
        Retire the observations of ``camera`` (every camera if None) stamped before ``before_ns``.

        They move to :attr:`retired` tagged with ``epoch``; a sample left without observations
        is removed.  Returns the number of observations retired.
        """
        taken = self._take_before(before_ns, camera)
        self.retired += [(int(epoch), smp) for smp in taken]
        return sum(len(smp.observations) for smp in taken)

    def forget(self, before_ns):
        """
        Drop every observation stamped before ``before_ns``, retired ones included.

        Unlike :meth:`retire` nothing is kept: what is forgotten is never solved again, and
        keeping it would grow the store (and its file) by every view of a long session.  A
        sample (or retired entry) left without observations goes.  Returns how many
        observations were dropped.
        """
        dropped = sum(len(smp.observations) for smp in self._take_before(before_ns))
        kept = []
        for tag, smp in self.retired:
            new = {name: o for name, o in smp.observations.items() if o.stamp_ns >= before_ns}
            dropped += len(smp.observations) - len(new)
            if new:
                kept.append((tag, smp if len(new) == len(smp.observations)
                             else replace(smp, observations=new, q=smp.q, pose=smp.pose)))
        self.retired = kept
        if dropped:
            self.revision += 1
        return dropped

    def _take_before(self, before_ns, camera=None):
        """
        Take ``camera``'s observations (every camera's if None) stamped before ``before_ns``.

        Returns them as copies of their samples holding only those observations; a sample
        left without observations is removed.
        """
        taken = []
        for smp in list(self._samples):
            old = {name: o for name, o in smp.observations.items()
                   if (camera is None or name == camera) and o.stamp_ns < before_ns}
            if not old:
                continue
            taken.append(replace(smp, observations=old, q=smp.q, pose=smp.pose))
            for name in old:
                del smp.observations[name]
            if not smp.observations:
                self.remove(smp.id)
        if taken:
            self.revision += 1
        return taken

    # -- solver view ----------------------------------------------------------------------

    def arrays(self, camera_names=None, epochs=None, until_ns=None):
        """
        Return :class:`SolverArrays` in sample-id order (point targets: one 3-D point each).

        A board sample's corners are separate 3-D points; the engine builds their problem
        from the samples' link poses instead.
        ``camera_names`` fixes the camera indexing (observations of other cameras are left
        out); by default every camera seen, in order of first appearance.  ``epochs`` maps
        further names to (camera, epoch): that camera's observations retired with that epoch
        tag, as a camera of that name after ``camera_names`` (the camera as it was before a
        change).  Only those on samples still held are included: the points stay the
        samples'; with ``until_ns`` ((camera, epoch) -> ns, as :meth:`retired_views`) only
        those stamped before that time.
        """
        names = self.camera_names if camera_names is None else tuple(camera_names)
        epochs = dict(epochs or {})
        names = names + tuple(e for e in epochs if e not in names)
        cam_index = {name: i for i, name in enumerate(names)}
        samples = sorted(self._samples, key=lambda s: s.id)
        old = {}
        if epochs:
            tags = {(cam, int(tag)): name for name, (cam, tag) in epochs.items()}
            until_ns = until_ns or {}
            for tag, smp in self.retired:
                for cam, o in smp.observations.items():
                    name = tags.get((cam, tag))
                    if name is not None and o.stamp_ns < until_ns.get((cam, tag), np.inf):
                        old.setdefault(smp.id, []).append((name, o))
        cam, pidx, uv, tid, nfr, spr, cuv, cspr = [], [], [], [], [], [], [], []
        for i, s in enumerate(samples):
            for name, obs in list(s.observations.items()) + old.get(s.id, []):
                c = cam_index.get(name)
                if c is None:
                    continue
                k = obs.uv.shape[0]
                cam.append(np.full(k, c))
                pidx.append(np.full(k, i))
                uv.append(obs.uv)
                tid.append(obs.ids)
                nfr.append(np.full(k, obs.n_frames))
                spr.append(np.full(k, obs.spread_px))
                if obs.centroid_uv is None:
                    cuv.append(np.full((k, 2), np.nan))
                    cspr.append(np.full(k, np.nan))
                else:
                    cuv.append(obs.centroid_uv)
                    cspr.append(np.full(k, obs.centroid_spread_px))

        def cat(parts, dtype, shape=(0,)):
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

        return SolverArrays(
            points=(np.array([s.point_nominal for s in samples]) if samples
                    else np.zeros((0, 3))),
            sample_ids=np.array([s.id for s in samples], dtype=np.int64),
            camera_names=names,
            camera_index=cat(cam, np.intp), point_index=cat(pidx, np.intp),
            uv=cat(uv, float, (0, 2)), target_ids=cat(tid, np.int64),
            n_frames=cat(nfr, np.int64), spread_px=cat(spr, float),
            centroid_uv=cat(cuv, float, (0, 2)), centroid_spread_px=cat(cspr, float))

    # -- persistence ----------------------------------------------------------------------

    def save(self, directory):
        """
        Write ``<directory>/samples.npz`` atomically (temporary file, fsync, os.replace).

        A crash while saving leaves the previous file intact.  Returns the path.
        """
        os.makedirs(directory, exist_ok=True)
        path = os.path.join(directory, FILE_NAME)
        arrays = self._to_arrays()
        fd, tmp = tempfile.mkstemp(prefix='.samples-', suffix='.tmp', dir=directory)
        try:
            with os.fdopen(fd, 'wb') as f:
                np.savez_compressed(f, **arrays)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return path

    def _to_arrays(self):
        names = list(self.camera_names)
        for _, smp in self.retired:
            names += [n for n in smp.observations if n not in names]
        meta = dict(version=FORMAT_VERSION, camera_names=names,
                    joint_names=None if self.joint_names is None else list(self.joint_names),
                    max_samples=self.max_samples, min_sample_spacing=self.min_sample_spacing,
                    same_point_tolerance=self.same_point_tolerance, next_id=self._next_id,
                    origin_ns=self._origin_ns)
        out = dict(meta=np.array(json.dumps(meta)))
        out.update(_arrays_of(sorted(self._samples, key=lambda s: s.id), names))
        retired = _arrays_of([smp for _, smp in self.retired], names)
        out.update({'retired_' + k: v for k, v in retired.items()})
        out['retired_epoch'] = np.array([e for e, _ in self.retired], dtype=np.int64)
        return out

    @classmethod
    def load(cls, directory, joint_names=None, **overrides):
        """
        Read ``<directory>/samples.npz`` written by :meth:`save`.

        ``joint_names``, if given, must match the saved ones (ValueError otherwise: joint
        angles from another robot would be meaningless).  ``overrides`` replace the saved
        ``max_samples`` / ``min_sample_spacing`` / ``same_point_tolerance``; samples are then
        re-added under the new policy.  Raises FileNotFoundError when there is no file.
        """
        path = os.path.join(directory, FILE_NAME)
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data['meta']))
            if meta.get('version') not in READABLE_VERSIONS:
                raise ValueError(f'{path}: unsupported sample store version '
                                 f'{meta.get("version")!r} (readable: {READABLE_VERSIONS})')
            arrays = {k: data[k] for k in data.files if k != 'meta'}
        saved_joints = meta.get('joint_names')
        if joint_names is not None and saved_joints is not None \
                and tuple(saved_joints) != tuple(joint_names):
            raise ValueError(f'{path}: saved joint_names {saved_joints} differ from '
                             f'{list(joint_names)}')
        params = dict(max_samples=meta['max_samples'],
                      min_sample_spacing=meta['min_sample_spacing'],
                      same_point_tolerance=meta['same_point_tolerance'])
        unknown = set(overrides) - set(params)
        if unknown:
            raise ValueError(f'unknown store parameter(s) {sorted(unknown)}')
        params.update(overrides)
        if 'same_point_tolerance' not in overrides:
            params['same_point_tolerance'] = min(params['same_point_tolerance'],
                                                 params['min_sample_spacing'])
        store = cls(joint_names=joint_names if joint_names is not None else saved_joints,
                    **params)
        names = meta['camera_names']
        for sample in _samples_of(arrays, names):
            store.add(sample)
        if 'retired_epoch' in arrays:
            retired = _samples_of({k[len('retired_'):]: v for k, v in arrays.items()
                                   if k.startswith('retired_')}, names)
            store.retired = list(zip((int(e) for e in arrays['retired_epoch']), retired))
            store._note_origin(o.stamp_ns for _, smp in store.retired
                               for o in smp.observations.values())
        if meta.get('origin_ns') is not None:
            store._note_origin([meta['origin_ns']])
        store._next_id = max(store._next_id, int(meta.get('next_id', 0)))
        store.counts = {r: 0 for r in AddResult}
        return store


def _arrays_of(samples, names):
    """Flat arrays of ``samples`` (in the given order); observations index into ``names``."""
    cam_index = {name: i for i, name in enumerate(names)}
    nq = {len(s.q) for s in samples if s.q is not None}
    if len(nq) > 1:
        raise ValueError(f'samples have joint vectors of different lengths {sorted(nq)}')
    nq = nq.pop() if nq else 0
    n = len(samples)
    nr = {len(s.reference_points) for s in samples if s.reference_points is not None}
    nr = nr.pop() if nr else 0           # one store holds one kind of target (see add)
    ref = np.full((n, nr, 3), np.nan)
    q = np.full((n, nq), np.nan)
    pose = np.full((n, 4, 4), np.nan)
    obs_rows, uv, ids, cuv = [], [], [], []
    offset = 0
    for i, s in enumerate(samples):
        if s.q is not None:
            q[i] = s.q
        if s.pose is not None:
            pose[i] = s.pose
        if s.reference_points is not None:
            ref[i] = s.reference_points
        for name, o in s.observations.items():
            obs_rows.append((i, cam_index[name], o.n_frames, o.stamp_ns, offset))
            uv.append(o.uv)
            ids.append(o.ids)
            cuv.append(np.full(o.uv.shape, np.nan) if o.centroid_uv is None else o.centroid_uv)
            offset += o.uv.shape[0]
    obs = np.array(obs_rows, dtype=np.int64).reshape(-1, 5)
    spread = np.array([o.spread_px for s in samples for o in s.observations.values()])
    cspread = np.array([np.nan if o.centroid_uv is None else o.centroid_spread_px
                        for s in samples for o in s.observations.values()])
    return dict(
        sample_id=np.array([s.id for s in samples], dtype=np.int64),
        stamp_ns=np.array([s.stamp_ns for s in samples], dtype=np.int64),
        point=np.array([s.point_nominal for s in samples]).reshape(n, 3),
        has_q=np.array([s.q is not None for s in samples], dtype=bool),
        q=q,
        has_pose=np.array([s.pose is not None for s in samples], dtype=bool),
        pose=pose,
        has_reference=np.array([s.reference_points is not None for s in samples], dtype=bool),
        reference_points=ref,
        obs=obs, obs_spread=spread.reshape(-1), obs_centroid_spread=cspread.reshape(-1),
        uv=np.concatenate(uv) if uv else np.zeros((0, 2)),
        centroid_uv=np.concatenate(cuv) if cuv else np.zeros((0, 2)),
        ids=np.concatenate(ids) if ids else np.zeros(0, np.int64))


def _samples_of(arrays, names):
    """Return the samples of :func:`_arrays_of`'s ``arrays`` (those with observations)."""
    obs = arrays['obs']
    n_points = arrays['uv'].shape[0]
    per_sample = {}
    ends = np.append(obs[1:, 4], n_points)
    # Stores written before centroids were kept have neither array.
    cuv = arrays.get('centroid_uv', np.full((n_points, 2), np.nan))
    cspread = arrays.get('obs_centroid_spread', np.full(len(obs), np.nan))
    for row, end, spread, cs in zip(obs, ends, arrays['obs_spread'], cspread):
        i, c, n_frames, stamp, off = (int(v) for v in row)
        end = int(end)
        has_centroid = bool(np.all(np.isfinite(cuv[off:end])))
        per_sample.setdefault(i, {})[names[c]] = Observation(
            uv=arrays['uv'][off:end], ids=arrays['ids'][off:end], n_frames=n_frames,
            spread_px=float(spread), stamp_ns=stamp,
            centroid_uv=cuv[off:end] if has_centroid else None,
            centroid_spread_px=float(cs) if has_centroid else 0.0)
    n = arrays['sample_id'].shape[0]
    has_ref = arrays.get('has_reference', np.zeros(n, bool))
    out = []
    for i in range(n):
        if i not in per_sample:
            continue
        out.append(Sample(point_nominal=arrays['point'][i], observations=per_sample[i],
                          stamp_ns=int(arrays['stamp_ns'][i]),
                          q=arrays['q'][i].copy() if arrays['has_q'][i] else None,
                          pose=arrays['pose'][i].copy() if arrays['has_pose'][i] else None,
                          id=int(arrays['sample_id'][i]),
                          reference_points=(arrays['reference_points'][i].copy()
                                            if has_ref[i] else None)))
    return out
