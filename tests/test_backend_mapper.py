"""LocalMapper driven directly, with no front end: FeatureFrames built from a SyntheticSequence's
rendered depth, inserted as keyframes (landmarks created from depth, promoted into the graph once
shared, covisibility counted, single-view landmarks culled).

Nothing here imports ``frontend``: the back end's public API must be usable by another pipeline.
"""
from __future__ import annotations

import numpy as np
import pytest

from backend.local_mapping import LocalMapper
from slam.core.camera import PinholeCamera
from slam.core.config import BackendConfig, KeyframeConfig
from slam.datasets import SyntheticSequence
from slam.core.frame import FeatureFrame
from slam.core.geometry import invert, pose_distance, transform_points


# --- LocalMapper on frames built from a synthetic sequence --------------------------------------------

KF_FRAMES = (0, 6, 12, 18)


class MapperRun:
    """Four keyframes of SyntheticSequence(seed=3) inserted into a LocalMapper, with snapshots.

    Frame 0: a pixel grid with rendered depth, plus 10 features without depth and 10 marked dynamic.
    Frame 6: every other kf-0 landmark that is visible and unoccluded, plus a fresh grid.
    Frames 12 and 18: only the visible landmarks created at keyframe 1 (nothing new).
    """

    def __init__(self):
        self.seq = SyntheticSequence(n_frames=max(KF_FRAMES) + 1, seed=3)
        self._depths: dict[int, np.ndarray] = {}
        fx, fy, cx, cy = self.seq.intrinsics
        self.camera = PinholeCamera(fx, fy, cx, cy, self.seq.width, self.seq.height)
        self.cfg, self.kf_cfg = BackendConfig(), KeyframeConfig()
        self.mapper = LocalMapper(self.cfg, self.kf_cfg, self.camera, dynamic_threshold=0.5)
        self.ts, self.gt = self.seq.groundtruth()
        self.rng = np.random.default_rng(0)
        self.insertions, self.bad_after, self.graph_landmarks_after = [], [], []

        # keyframe 0
        uv, z = self._grid(0, offset=0)
        n_grid = len(uv)
        no_depth_uv = uv[:10] + 3.0
        dyn_uv = uv[10:20] + 5.0
        dyn_z = self._depth_at(0, dyn_uv)
        uv0 = np.vstack([uv, no_depth_uv, dyn_uv])
        z0 = np.r_[z, np.zeros(10), dyn_z]
        dyn0 = np.r_[np.zeros(n_grid + 10), np.full(10, 0.9)]
        self.frame0 = (uv0, z0, dyn0, n_grid)
        self._insert(0, uv0, z0, np.full(len(uv0), -1, np.int64), dyn0)
        self.kf0_lm_of_kp = self.mapper.map.keyframes[0].landmark_of_keypoint.copy()
        self.kf0_landmarks = np.unique(self.kf0_lm_of_kp[self.kf0_lm_of_kp >= 0])

        # keyframe 1: half of the visible kf-0 landmarks, plus new features
        ids, uv_m, z_m = self._visible(6, self.kf0_landmarks)
        ids, uv_m, z_m = ids[::2], uv_m[::2], z_m[::2]
        self.shared_01 = ids
        uv_new, z_new = self._grid(6, offset=17)
        uv1, z1 = np.vstack([uv_m, uv_new]), np.r_[z_m, z_new]
        lm1 = np.r_[ids, np.full(len(uv_new), -1)].astype(np.int64)
        self._insert(6, uv1, z1, lm1)
        lm_of_kp1 = self.mapper.map.keyframes[1].landmark_of_keypoint
        self.kf1_new = np.setdiff1d(lm_of_kp1[lm_of_kp1 >= 0], ids)

        # keyframes 2 and 3: only landmarks created at keyframe 1
        for i in KF_FRAMES[2:]:
            ids, uv_m, z_m = self._visible(i, self.kf1_new)
            self._insert(i, uv_m, z_m, ids.astype(np.int64))

    def _depth_at(self, i: int, uv: np.ndarray) -> np.ndarray:
        depth = self.depth(i)
        return depth[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)].astype(float)

    def depth(self, i: int) -> np.ndarray:
        if i not in self._depths:
            self._depths[i] = self.seq.render(self.gt[i], float(self.ts[i]))[1]
        return self._depths[i]

    def _grid(self, i: int, offset: int, step: int = 37) -> tuple[np.ndarray, np.ndarray]:
        us, vs = np.meshgrid(np.arange(20 + offset, self.seq.width - 20, step),
                             np.arange(20 + offset, self.seq.height - 20, step))
        uv = np.stack([us.ravel(), vs.ravel()], 1).astype(float)
        return uv, self._depth_at(i, uv)

    def _visible(self, i: int, ids: np.ndarray):
        """Landmarks (true world points) projected into frame i, kept where in view and unoccluded."""
        T_cw = invert(self.gt[i])
        Xc = transform_points(T_cw, self.true_xyz(ids))
        uv, z = self.camera.project(Xc)
        ok = self.camera.in_image(uv, margin=20) & (z > 0.3)
        ok[ok] &= np.abs(self._depth_at(i, uv[ok]) - z[ok]) < 0.02
        return ids[ok], uv[ok], z[ok]

    def true_xyz(self, ids: np.ndarray) -> np.ndarray:
        """World points of landmarks from the keypoint that created them (independent of the map's estimate)."""
        lm = self.mapper.map.landmarks
        out = np.zeros((len(ids), 3))
        for n, j in enumerate(ids):
            kf = int(lm.anchor_kf[j])
            rec = self.mapper.map.keyframes[kf]
            kp = int(np.flatnonzero(rec.landmark_of_keypoint == j)[0])
            local = self.camera.backproject(rec.features.uv[kp:kp + 1], rec.features.depths[kp:kp + 1])
            out[n] = transform_points(self.gt[KF_FRAMES[kf]], local)[0]
        return out

    def _insert(self, i: int, uv: np.ndarray, z: np.ndarray, lm_of_kp: np.ndarray, dyn=None) -> None:
        n = len(uv)
        frame = FeatureFrame(index=i, timestamp=float(self.ts[i]), uv_raw=uv.copy(), uv=uv.copy(),
                             octaves=np.zeros(n, int), descriptors=self.rng.integers(0, 256, (n, 32), dtype=np.uint8),
                             depths=np.asarray(z, float), u_right=self.camera.right_u(uv[:, 0], np.asarray(z, float)),
                             dynamic_prob=np.zeros(n) if dyn is None else dyn,
                             scale_factors=1.2 ** np.arange(8))
        self.insertions.append(self.mapper.insert_keyframe(frame, self.gt[i].copy(), lm_of_kp))
        self.bad_after.append(self.mapper.map.landmarks.bad.copy())
        self.graph_landmarks_after.append(self.mapper.graph.landmark_positions()[0].copy())


@pytest.fixture(scope="module")
def mapper_run() -> MapperRun:
    return MapperRun()


def test_local_mapper_creates_landmarks_from_depth(mapper_run):
    run = mapper_run
    uv0, z0, dyn0, n_grid = run.frame0
    cam = run.camera
    ins0 = run.insertions[0]
    assert ins0.kf_id == 0 and ins0.promoted_landmarks == 0 and ins0.culled_landmarks == 0
    # Candidates: valid depth and static; all close ones are taken (at least min_new_landmarks).
    candidate = (z0 > cam.min_depth) & (z0 < cam.max_depth) & (dyn0 < 0.5)
    n_close = int((candidate & (z0 < cam.close_depth)).sum())
    expected = min(max(n_close, min(run.kf_cfg.min_new_landmarks, int(candidate.sum()))),
                   run.kf_cfg.max_new_landmarks)
    assert 50 < expected < int(candidate.sum())  # the scene has close and far points
    assert ins0.new_landmarks == expected == len(run.kf0_landmarks)
    created_kp = np.flatnonzero(run.kf0_lm_of_kp >= 0)
    assert not np.isin(created_kp, np.arange(n_grid, len(uv0))).any(), "no landmark from no-depth/dynamic features"
    assert z0[created_kp].max() <= np.sort(z0[candidate])[expected - 1] + 1e-9, "the closest are taken first"
    lm = run.mapper.map.landmarks
    ids = run.kf0_lm_of_kp[created_kp]
    local = cam.backproject(uv0[created_kp], z0[created_kp])
    np.testing.assert_allclose(lm.local_xyz[ids], local, atol=1e-9)
    np.testing.assert_array_equal(lm.anchor_kf[ids], 0)
    # World positions: the true pose applied to the depth back-projection (kf 0 is not moved).
    np.testing.assert_allclose(lm.xyz[ids[~lm.in_graph[ids]]],
                               transform_points(run.gt[0], local[~lm.in_graph[ids]]), atol=1e-3)


def test_local_mapper_promotes_shared_landmarks_and_counts_covisibility(mapper_run):
    run = mapper_run
    ins1 = run.insertions[1]
    n_shared = len(run.shared_01)
    assert n_shared > 30
    assert ins1.promoted_landmarks == n_shared
    assert ins1.new_landmarks == len(run.kf1_new) > 0
    cov = run.mapper.map.covisibility
    assert cov[0, 1] == cov[1, 0] == n_shared
    lm = run.mapper.map.landmarks
    assert lm.in_graph[run.shared_01].all()
    assert set(run.graph_landmarks_after[0]) == set()
    assert set(run.graph_landmarks_after[1]) == set(run.shared_01), "only landmarks seen twice are variables"
    # Exact observations: the graph keeps the true keyframe poses and landmark positions.
    np.testing.assert_allclose(lm.xyz[run.shared_01], run.true_xyz(run.shared_01), atol=0.01)
    for kf, i in enumerate(KF_FRAMES):
        assert pose_distance(run.mapper.map.kf_T_wc[kf], run.gt[i])[0] < 1e-3
    # covisible_keyframes / keyframes_observing agree with the counts
    assert list(run.mapper.map.covisible_keyframes(0, min_shared=1)) == [1]
    kfs, counts = run.mapper.map.keyframes_observing(run.shared_01)
    assert list(kfs) == [0, 1] and list(counts) == [n_shared, n_shared]
    # Later keyframes share only keyframe-1 landmarks: none with keyframe 0.
    assert cov[0, 2] == cov[0, 3] == 0
    assert cov[1, 2] > 0 and cov[2, 3] > 0


def test_local_mapper_culls_single_view_landmarks_after_cull_after_keyframes(mapper_run):
    run = mapper_run
    assert run.cfg.cull_after_keyframes == 3 and run.cfg.cull_min_observations == 2
    single_kf0 = np.setdiff1d(run.kf0_landmarks, run.shared_01)
    assert len(single_kf0) > 0
    # Alive while younger than cull_after_keyframes keyframes ...
    for k in range(run.cfg.cull_after_keyframes):
        assert not run.bad_after[k][single_kf0].any(), f"culled too early, at keyframe {k}"
        assert run.insertions[k].culled_landmarks == 0
    # ... culled at keyframe 3, as nobody else saw them.
    bad3 = run.bad_after[3]
    assert bad3[single_kf0].all()
    assert not bad3[run.shared_01].any(), "landmarks seen by two keyframes stay"
    assert not bad3[run.kf1_new].any(), "keyframe-1 landmarks are only 2 keyframes old"
    assert run.insertions[3].culled_landmarks == len(single_kf0) == int(bad3.sum())
    # Culled landmarks disappear from what tracking is offered.
    pts = run.mapper.map.map_points(np.arange(len(run.mapper.map.landmarks)))
    assert not np.isin(pts.ids, single_kf0).any()


def test_move_rigidly_moves_keyframes_and_the_landmarks_made_in_them_only(mapper_run):
    """A loop's query side moved at once (``LoopCloser.correct_neighbourhood``): the keyframes and the
    landmarks created in them, in the graph or anchored; an older landmark they re-observe stays where the
    older map has it. The graph's values are not touched. Moved back afterwards (a shared fixture)."""
    from scipy.spatial.transform import Rotation

    slam_map = mapper_run.mapper.map
    lm = slam_map.landmarks
    correction = np.eye(4)
    correction[:3, :3] = Rotation.from_euler("z", 5, degrees=True).as_matrix()
    correction[:3, 3] = [0.1, -0.05, 0.02]
    poses, xyz = slam_map.kf_T_wc.copy(), lm.xyz.copy()
    graph_before = mapper_run.mapper.graph.landmark_positions()[1].copy()
    made_late = np.isin(lm.anchor_kf, [1, 2, 3]) & ~lm.bad
    seen_late_made_early = np.intersect1d(slam_map.landmarks_of_keyframes(np.array([1])),
                                          np.flatnonzero(lm.anchor_kf < 1))
    assert made_late.any() and (made_late & lm.in_graph).any() and len(seen_late_made_early)
    mapper_run.mapper.move_rigidly(np.array([1, 2, 3]), correction)
    try:
        np.testing.assert_allclose(slam_map.kf_T_wc[[1, 2, 3]], correction @ poses[[1, 2, 3]], atol=1e-12)
        np.testing.assert_array_equal(slam_map.kf_T_wc[[0]], poses[[0]])
        np.testing.assert_allclose(lm.xyz[made_late], xyz[made_late] @ correction[:3, :3].T + correction[:3, 3],
                                   atol=1e-9)
        np.testing.assert_array_equal(lm.xyz[seen_late_made_early], xyz[seen_late_made_early])
        np.testing.assert_array_equal(mapper_run.mapper.graph.landmark_positions()[1], graph_before)
    finally:
        mapper_run.mapper.move_rigidly(np.array([1, 2, 3]), np.linalg.inv(correction))
    np.testing.assert_allclose(slam_map.kf_T_wc, poses, atol=1e-12)
