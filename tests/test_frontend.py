"""Tests for the front end on synthetic RGB-D data: ORB extraction, matching, keyframe policy, tracking."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontend.keyframe_policy import KeyframeEvidence, close_point_counts, keyframe_distances, need_keyframe
from frontend.matching import hamming_pairs, match_brute_force, search_by_projection
from frontend.orb_extractor import OrbExtractor, features_per_level
from frontend.tracker import Tracker, TrackingState
from slam.core.camera import PinholeCamera
from slam.core.config import KeyframeConfig, load_config
from slam.datasets import SyntheticSequence
from slam.core.frame import FeatureFrame, MapPoints
from slam.core.geometry import invert, so3_log, transform_points
from slam.runtime.system import System

N_FRAMES = 30


@pytest.fixture(scope="module")
def sequence():
    """The first frames of the seeded orbit sequence, rendered once: (frames, T_wc ground truth)."""
    seq = SyntheticSequence(n_frames=N_FRAMES, path="orbit", seed=0)
    _, gt = seq.groundtruth()
    return list(seq), gt


@pytest.fixture(scope="module")
def config():
    return load_config()


@pytest.fixture(scope="module")
def camera(config):
    return PinholeCamera.from_config(config.camera)


@pytest.fixture(scope="module")
def features(sequence, config, camera) -> list[FeatureFrame]:
    frames, _ = sequence
    extractor = OrbExtractor(config.orb, camera)
    return [extractor.extract(cv2.cvtColor(f.rgb, cv2.COLOR_BGR2GRAY), f.depth, f.index, f.timestamp)
            for f in frames[:3]]


def test_default_camera_matches_the_synthetic_one(config):
    seq_intrinsics = SyntheticSequence(n_frames=1).intrinsics
    cam = config.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == seq_intrinsics
    assert (cam.width, cam.height) == (640, 480)
    assert not any(cam.distortion)


# --- ORB extraction ------------------------------------------------------------------------------


def test_extractor_returns_about_n_features_on_every_level(features, config):
    cfg = config.orb
    quota = features_per_level(cfg.n_features, cfg.scale_factor, cfg.n_levels)
    assert quota.sum() == cfg.n_features
    for frame in features:
        n = len(frame)
        assert 0.95 * cfg.n_features <= n <= cfg.n_features
        per_level = np.bincount(frame.octaves, minlength=cfg.n_levels)
        assert len(per_level) == cfg.n_levels
        assert (per_level <= quota).all()
        assert (per_level > 0).all()
        np.testing.assert_allclose(frame.scale_factors, cfg.scale_factor ** np.arange(cfg.n_levels))
        assert frame.descriptors.shape == (n, 32) and frame.descriptors.dtype == np.uint8
        assert frame.uv.shape == frame.uv_raw.shape == (n, 2)
        assert frame.octaves.shape == frame.depths.shape == frame.u_right.shape == frame.dynamic_prob.shape == (n,)
        assert (frame.dynamic_prob == 0).all()


def test_features_are_spread_over_the_image(features, camera):
    for frame in features:
        counts, _, _ = np.histogram2d(frame.uv_raw[:, 0], frame.uv_raw[:, 1], bins=(4, 4),
                                      range=((0, camera.width), (0, camera.height)))
        assert counts.min() >= 20, counts
        # No cell hoards the features the way plain OpenCV ORB (strongest corners only) does on this
        # scene: there the fullest cell holds ~15% and the cell counts vary by ~55% (std / mean).
        assert counts.max() <= 0.12 * len(frame), counts
        assert counts.std() / counts.mean() < 0.4, counts


def test_feature_depths_come_from_the_depth_map(sequence, features, camera):
    frames, _ = sequence
    for frame, rgbd in zip(features, frames):
        cols = np.rint(frame.uv_raw[:, 0]).astype(int)
        rows = np.rint(frame.uv_raw[:, 1]).astype(int)
        np.testing.assert_array_equal(frame.depths, rgbd.depth[rows, cols].astype(float))
        assert (frame.depths > 0).all()  # the synthetic room has depth everywhere
        # No distortion: ideal and raw coordinates coincide.
        np.testing.assert_allclose(frame.uv, frame.uv_raw)
        np.testing.assert_allclose(frame.u_right, camera.right_u(frame.uv[:, 0], frame.depths))
        usable = (frame.depths > camera.min_depth) & (frame.depths < camera.max_depth)
        np.testing.assert_array_equal(frame.has_depth, usable)
        assert usable.mean() > 0.95


def test_extractor_undistorts_with_a_distorted_camera(sequence):
    frames, _ = sequence
    cfg = load_config("tum_fr1", overrides={"orb.n_features": 300})
    cam = PinholeCamera.from_config(cfg.camera)
    frame = OrbExtractor(cfg.orb, cam).extract(cv2.cvtColor(frames[0].rgb, cv2.COLOR_BGR2GRAY), frames[0].depth)
    assert 0.95 * 300 <= len(frame) <= 300
    np.testing.assert_allclose(frame.uv, cam.undistort_points(frame.uv_raw))
    assert np.abs(frame.uv - frame.uv_raw).max() > 1.0


def test_extractor_on_a_blank_image_returns_an_empty_frame(config, camera):
    frame = OrbExtractor(config.orb, camera).extract(np.full((480, 640), 128, np.uint8), np.ones((480, 640), np.float32))
    assert len(frame) == 0
    assert frame.descriptors.shape == (0, 32)


@pytest.mark.parametrize("n, scale, levels", [(1000, 1.2, 8), (2000, 1.2, 8), (500, 1.5, 4), (1500, 1.1, 12),
                                              (100, 2.0, 3), (1, 1.2, 8), (7, 1.2, 8)])
def test_features_per_level_sums_to_n_features(n, scale, levels):
    counts = features_per_level(n, scale, levels)
    assert len(counts) == levels
    assert counts.sum() == n
    assert (counts >= 0).all()
    assert (np.diff(counts[1:]) <= 0).all()  # coarser levels get no more than finer ones


def test_features_per_level_sums_for_tiny_budgets():
    assert features_per_level(6, 1.1, 8).sum() == 6


# --- descriptor distances and matching -----------------------------------------------------------


def test_hamming_pairs_equals_bitwise_reference():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    reference = np.unpackbits(a ^ b, axis=1).sum(axis=1)
    np.testing.assert_array_equal(hamming_pairs(a, b), reference)
    np.testing.assert_array_equal(hamming_pairs(a, a), 0)
    np.testing.assert_array_equal(hamming_pairs(a, ~a), 256)
    one_bit = a.copy()
    one_bit[:, 31] ^= 0x80
    np.testing.assert_array_equal(hamming_pairs(a, one_bit), 1)
    # Against OpenCV's own Hamming norm, pair by pair.
    for i in range(0, 500, 50):
        assert hamming_pairs(a[i:i + 1], b[i:i + 1])[0] == cv2.norm(a[i], b[i], cv2.NORM_HAMMING)


def frame_as_map_points(frame: FeatureFrame, T_wc: np.ndarray, camera: PinholeCamera) -> MapPoints:
    """Back-project a frame's features with their depth into world coordinates."""
    xyz = transform_points(T_wc, camera.backproject(frame.uv, frame.depths))
    return MapPoints(np.arange(len(frame), dtype=np.int64), xyz, frame.descriptors.copy(), frame.octaves.copy())


def test_search_by_projection_with_the_true_pose(features, sequence, camera, config):
    _, gt = sequence
    f0, f1 = features[0], features[1]
    points = frame_as_map_points(f0, gt[0], camera)
    T_cw1 = invert(gt[1])
    radius = config.tracking.local_map_search_radius
    matches = search_by_projection(f1, points, T_cw1, camera, radius, config.tracking.max_descriptor_distance,
                                   config.tracking.match_ratio, np.ones(len(f1), bool))
    kp = matches.keypoint_of_point
    matched = kp >= 0
    assert matches.visible.mean() > 0.9
    assert matched.sum() >= 0.5 * matches.visible.sum()
    assert not (matched & ~matches.visible).any()
    # Every keypoint is used at most once.
    assert len(np.unique(kp[matched])) == matched.sum()
    # Matched keypoints lie near the point's projection (ORB localises to ~1 px per pyramid scale).
    projected, _ = camera.project(transform_points(T_cw1, points.xyz))
    offset = np.linalg.norm(f1.uv[kp[matched]] - projected[matched], axis=1)
    scale = f0.scale_factors[points.octaves[matched]]
    assert (offset <= radius * scale + 1e-9).all()
    assert np.median(offset) < 1.5
    assert np.mean(offset < 3.0 * scale) > 0.9
    # The reported distance is the Hamming distance of the pair, within the limit.
    np.testing.assert_array_equal(matches.distance[matched], hamming_pairs(points.descriptors[matched],
                                                                           f1.descriptors[kp[matched]]))
    assert (matches.distance[matched] <= config.tracking.max_descriptor_distance).all()
    assert (matches.distance[~matched] == -1).all()
    # Neighbouring pyramid levels only.
    assert (np.abs(f1.octaves[kp[matched]] - points.octaves[matched]) <= 1).all()


def test_search_by_projection_into_the_same_frame_finds_every_point(features, sequence, camera):
    _, gt = sequence
    f0 = features[0]
    points = frame_as_map_points(f0, gt[0], camera)
    matches = search_by_projection(f0, points, invert(gt[0]), camera, 4.0, 100, 0.8, np.ones(len(f0), bool))
    np.testing.assert_array_equal(matches.keypoint_of_point, np.arange(len(f0)))
    np.testing.assert_array_equal(matches.distance, 0)


def test_search_by_projection_uses_each_keypoint_once_with_duplicate_points(features, sequence, camera):
    _, gt = sequence
    f0, f1 = features[0], features[1]
    points = frame_as_map_points(f0, gt[0], camera)
    doubled = MapPoints.concat([points, points])   # two identical candidates for every keypoint
    matches = search_by_projection(f1, doubled, invert(gt[1]), camera, 8.0, 100, 1.0, np.ones(len(f1), bool))
    kp = matches.keypoint_of_point[matches.keypoint_of_point >= 0]
    assert len(kp) > 200
    assert len(np.unique(kp)) == len(kp)


def test_search_by_projection_respects_eligibility(features, sequence, camera):
    _, gt = sequence
    f0, f1 = features[0], features[1]
    points = frame_as_map_points(f0, gt[0], camera)
    rng = np.random.default_rng(1)
    eligible = rng.random(len(f1)) < 0.5
    matches = search_by_projection(f1, points, invert(gt[1]), camera, 4.0, 100, 0.8, eligible)
    kp = matches.keypoint_of_point[matches.keypoint_of_point >= 0]
    assert len(kp) > 100
    assert eligible[kp].all()
    none = search_by_projection(f1, points, invert(gt[1]), camera, 4.0, 100, 0.8, np.zeros(len(f1), bool))
    assert (none.keypoint_of_point == -1).all()


def test_search_by_projection_skips_points_behind_the_camera(features, sequence, camera):
    _, gt = sequence
    f0 = features[0]
    points = frame_as_map_points(f0, gt[0], camera)
    # Turn the camera around (rotate 180 degrees about its y axis): nothing is in front any more.
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    matches = search_by_projection(f0, points, flip @ invert(gt[0]), camera, 4.0, 100, 0.8, np.ones(len(f0), bool))
    assert not matches.visible.any()
    assert (matches.keypoint_of_point == -1).all()


def test_match_brute_force_unique_and_geometrically_right(features, sequence, camera):
    _, gt = sequence
    f0, f1 = features[0], features[1]
    qi, ti = match_brute_force(f1.descriptors, f0.descriptors, 0.8, 100)
    assert len(qi) > 300
    assert len(np.unique(ti)) == len(ti)
    assert len(np.unique(qi)) == len(qi)
    assert (hamming_pairs(f1.descriptors[qi], f0.descriptors[ti]) <= 100).all()
    # Most descriptor-only matches are the same scene point: the frame-0 point lands on the frame-1 keypoint.
    xyz = transform_points(gt[0], camera.backproject(f0.uv[ti], f0.depths[ti]))
    projected, _ = camera.project(transform_points(invert(gt[1]), xyz))
    assert np.mean(np.linalg.norm(projected - f1.uv[qi], axis=1) < 5.0) > 0.9


def test_match_brute_force_unique_train_with_duplicated_queries():
    rng = np.random.default_rng(2)
    train = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    query = np.concatenate([train[:100], train[:100]])   # every train row wanted twice
    qi, ti = match_brute_force(query, train, 0.8, 100)
    assert len(ti) == 100
    assert len(np.unique(ti)) == len(ti)
    np.testing.assert_array_equal(query[qi], train[ti])
    assert match_brute_force(query[:1], train, 0.8, 100)[0].shape == (0,)


# --- keyframe policy -----------------------------------------------------------------------------


def evidence(**kw) -> KeyframeEvidence:
    base = dict(frames_since_keyframe=1, tracked_landmarks=200, reference_landmarks=200, tracked_close=300,
                untracked_close=0, motion_t=0.0, motion_deg=0.0)
    base.update(kw)
    return KeyframeEvidence(**base)


def test_need_keyframe_rules():
    cfg = KeyframeConfig()
    assert cfg.min_frames == 0 and cfg.max_frames == 5 and cfg.tracked_ratio == 0.75
    # Tracking as well as the reference, recent, not moved: no keyframe.
    assert not need_keyframe(cfg, evidence())
    # Weak tracking: fewer than 75% of the reference's landmarks.
    assert need_keyframe(cfg, evidence(tracked_landmarks=149))
    assert not need_keyframe(cfg, evidence(tracked_landmarks=151))
    # Few close points tracked and many new ones available.
    assert need_keyframe(cfg, evidence(tracked_close=50, untracked_close=100))
    assert not need_keyframe(cfg, evidence(tracked_close=50, untracked_close=10))
    assert not need_keyframe(cfg, evidence(tracked_close=150, untracked_close=100))
    # Timed out without motion: no keyframe; with translation or rotation: keyframe.
    assert not need_keyframe(cfg, evidence(frames_since_keyframe=50))
    assert not need_keyframe(cfg, evidence(frames_since_keyframe=50, motion_t=0.01, motion_deg=1.0))
    assert need_keyframe(cfg, evidence(frames_since_keyframe=5, motion_t=0.05))
    assert need_keyframe(cfg, evidence(frames_since_keyframe=5, motion_deg=3.0))
    # Moved but not timed out: no keyframe.
    assert not need_keyframe(cfg, evidence(frames_since_keyframe=4, motion_t=0.05, motion_deg=3.0))
    # Default motion (unknown) counts as moved.
    assert need_keyframe(cfg, KeyframeEvidence(5, 200, 200, 300, 0))
    # Due and moved, but passing an older keyframe (nearer than half the way to the last one): no
    # keyframe; weak tracking still makes one there.
    assert not need_keyframe(cfg, evidence(frames_since_keyframe=5, motion_t=0.05, nearest_ratio=0.4))
    assert need_keyframe(cfg, evidence(frames_since_keyframe=5, motion_t=0.05, nearest_ratio=0.6))
    assert need_keyframe(cfg, evidence(frames_since_keyframe=5, motion_t=0.05, nearest_ratio=0.4, tracked_landmarks=100))
    assert need_keyframe(cfg.model_copy(update={"revisit_ratio": 0.0}),
                         evidence(frames_since_keyframe=5, motion_t=0.05, nearest_ratio=0.0))


def test_keyframe_distances_in_units_of_the_motion_thresholds():
    def pose(x: float, yaw_deg: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
        T[0, 3] = x
        return T

    keyframes = np.stack([pose(0.0, 0.0), pose(0.1, 0.0), pose(0.0, 10.0), pose(0.01, 1.0)])
    d = keyframe_distances(keyframes, pose(0.0, 0.0), 0.02, 2.0)
    np.testing.assert_allclose(d, [0.0, 5.0, 5.0, 0.5], atol=1e-6)   # 10 cm / 2 cm; 10 deg / 2 deg; max(0.5, 0.5)


@pytest.mark.parametrize("tracked", [0, 5, 15])
def test_need_keyframe_never_with_15_or_fewer_tracked(tracked):
    cfg = KeyframeConfig()
    assert not need_keyframe(cfg, evidence(tracked_landmarks=tracked, reference_landmarks=500))
    assert not need_keyframe(cfg, evidence(tracked_landmarks=tracked, frames_since_keyframe=100, motion_t=1.0))
    assert not need_keyframe(cfg, evidence(tracked_landmarks=tracked, tracked_close=0, untracked_close=500))
    assert need_keyframe(cfg, evidence(tracked_landmarks=16, reference_landmarks=500))


def test_need_keyframe_min_frames():
    cfg = KeyframeConfig(min_frames=3)
    assert not need_keyframe(cfg, evidence(frames_since_keyframe=2, tracked_landmarks=20, reference_landmarks=500))
    assert need_keyframe(cfg, evidence(frames_since_keyframe=3, tracked_landmarks=20, reference_landmarks=500))


def test_close_point_counts(features, camera):
    frame = features[0]
    rng = np.random.default_rng(3)
    lm = np.where(rng.random(len(frame)) < 0.4, np.arange(len(frame)), -1)
    dyn = frame.dynamic_prob.copy()
    dyn[:100] = 0.9
    frame_d = FeatureFrame(frame.index, frame.timestamp, frame.uv_raw, frame.uv, frame.octaves, frame.descriptors,
                           frame.depths, frame.u_right, dyn, frame.scale_factors)
    close = frame.has_depth & (frame.depths < camera.close_depth) & (dyn < 0.5)
    tracked, untracked = close_point_counts(frame_d, lm, camera.close_depth, 0.5)
    assert tracked == int((close & (lm >= 0)).sum())
    assert untracked == int((close & (lm < 0)).sum())
    assert tracked + untracked == int(close.sum()) > 0


# --- tracking through the System facade ----------------------------------------------------------


def aligned_ground_truth(gt: np.ndarray) -> np.ndarray:
    """Ground-truth T_wc expressed in the frame of the first camera (the system starts at identity)."""
    return invert(gt[0])[None] @ gt


def test_tracker_follows_the_orbit(sequence, config):
    frames, gt = sequence
    reference = aligned_ground_truth(gt)
    system = System(config)
    outputs = [system.process(f.rgb, f.depth, f.timestamp) for f in frames]
    assert [o.state for o in outputs] == [TrackingState.OK] * N_FRAMES
    assert outputs[0].is_keyframe
    t_err, r_err = [], []
    for o, T_ref in zip(outputs, reference):
        D = invert(T_ref) @ o.T_wc
        t_err.append(np.linalg.norm(o.T_wc[:3, 3] - T_ref[:3, 3]))
        r_err.append(np.degrees(np.linalg.norm(so3_log(D[:3, :3]))))
        assert o.n_features >= 950
        assert o.n_tracked >= config.tracking.min_tracked_inliers
    assert max(t_err) < 0.01, np.round(t_err, 4)
    assert np.mean(t_err) < 0.006
    assert max(r_err) < 0.5, np.round(r_err, 3)
    # The camera moved for real (so the error bound is meaningful).
    assert np.linalg.norm(reference[-1][:3, 3]) > 0.1
    # Keyframes were made along the way, and the trajectory follows them.
    assert 2 <= system.num_keyframes <= N_FRAMES // 2
    stamps, poses, tracked = system.trajectory()
    assert tracked.all()
    np.testing.assert_allclose(stamps, [f.timestamp for f in frames])
    assert np.linalg.norm(poses[:, :3, 3] - reference[:, :3, 3], axis=1).max() < 0.01


class DynamicAt:
    """A dynamic filter that marks every feature of the given frame indices dynamic (no pixel mask, so
    no static refill: the frame must be lost)."""

    name = "test_all_dynamic"
    stats = None
    last_mask = None

    def __init__(self, indices):
        self.indices = set(indices)

    def begin_frame(self, rgb, gray, depth, timestamp, predicted_T_cw, last_T_cw) -> None:
        pass

    def process(self, frame: FeatureFrame, rgb, gray, depth, predicted_T_cw, last_T_cw) -> np.ndarray:
        return np.full(len(frame), 1.0 if frame.index in self.indices else 0.0)

    def end_frame(self, T_cw, is_keyframe) -> None:
        pass

    def close(self) -> None:
        pass


def test_all_dynamic_frame_is_lost_not_given_a_pose(sequence, config):
    frames, gt = sequence
    reference = aligned_ground_truth(gt)
    lost_at = 8
    system = System(config, dynamic_filter=DynamicAt({lost_at}))
    outputs = [system.process(f.rgb, f.depth, f.timestamp, index=f.index) for f in frames[:12]]
    lost = outputs[lost_at]
    assert lost.state == TrackingState.LOST
    assert lost.T_wc is None
    assert lost.n_tracked == 0
    assert not lost.is_keyframe
    for i, o in enumerate(outputs):
        if i == lost_at:
            continue
        assert o.state == TrackingState.OK, i
        assert np.linalg.norm(o.T_wc[:3, 3] - reference[i][:3, 3]) < 0.01, i
    _, poses, tracked = system.trajectory()
    assert not tracked[lost_at] and tracked[np.arange(12) != lost_at].all()
    assert np.isnan(poses[lost_at]).all()


def test_a_pose_the_inliers_barely_fix_is_lost_not_reported(sequence, config):
    """tracking.max_pose_sigma_m: the points-only uncertainty of the pose decides, not only the inlier
    count. A full view of the generated room fixes the position to millimetres; with the limit set below
    that, every frame after the first is LOST and gets no pose."""
    frames, _ = sequence
    sigmas = []
    tracker_track = Tracker.track

    def track(self, frame, source):
        result = tracker_track(self, frame, source)
        sigmas.append(result.pose_sigma_t)
        return result

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Tracker, "track", track)
        system = System(config.model_copy(deep=True), dynamic_filter=DynamicAt(set()))
        tracked = [system.process(f.rgb, f.depth, f.timestamp, index=f.index) for f in frames[:6]]
    assert all(o.state == TrackingState.OK for o in tracked)
    assert all(0.0001 < s < 0.005 for s in sigmas), sigmas
    strict = config.model_copy(deep=True)
    strict.tracking.max_pose_sigma_m = 0.00005
    system = System(strict, dynamic_filter=DynamicAt(set()))
    outputs = [system.process(f.rgb, f.depth, f.timestamp, index=f.index) for f in frames[:6]]
    assert outputs[0].is_keyframe
    assert all(o.state == TrackingState.LOST and o.T_wc is None for o in outputs[1:])


def test_all_dynamic_first_frame_does_not_initialise(sequence, config):
    frames, _ = sequence
    system = System(config, dynamic_filter=DynamicAt({0}))
    first = system.process(frames[0].rgb, frames[0].depth, frames[0].timestamp, index=0)
    assert first.state == TrackingState.NOT_INITIALIZED
    assert first.T_wc is None
    assert system.num_keyframes == 0
    second = system.process(frames[1].rgb, frames[1].depth, frames[1].timestamp, index=1)
    assert second.state == TrackingState.OK and second.is_keyframe


def test_search_by_projection_when_every_candidate_fails_the_level_check():
    """Candidates inside the radius but all on distant pyramid levels: no match, no crash."""
    from slam.core.camera import PinholeCamera
    from frontend.matching import search_by_projection

    camera = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
    scales = 1.2 ** np.arange(8)
    frame = FeatureFrame(0, 0.0, np.array([[320.0, 240.0]]), np.array([[320.0, 240.0]]), np.array([7]),
                         np.zeros((1, 32), np.uint8), np.array([2.0]), np.array([np.nan]), np.zeros(1), scales)
    points = MapPoints(np.array([5]), np.array([[0.0, 0.0, 2.0]]), np.zeros((1, 32), np.uint8), np.array([0]))
    m = search_by_projection(frame, points, np.eye(4), camera, 15.0, 100, 0.8, np.ones(1, bool))
    assert m.keypoint_of_point.tolist() == [-1] and m.visible.tolist() == [True]


def test_search_by_projection_when_no_candidate_is_close_enough_in_descriptor_space():
    from slam.core.camera import PinholeCamera
    from frontend.matching import search_by_projection

    camera = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
    frame = FeatureFrame(0, 0.0, np.array([[320.0, 240.0]]), np.array([[320.0, 240.0]]), np.array([0]),
                         np.zeros((1, 32), np.uint8), np.array([2.0]), np.array([np.nan]), np.zeros(1),
                         1.2 ** np.arange(8))
    points = MapPoints(np.array([5]), np.array([[0.0, 0.0, 2.0]]), np.full((1, 32), 255, np.uint8), np.array([0]))
    m = search_by_projection(frame, points, np.eye(4), camera, 15.0, 50, 0.8, np.ones(1, bool))
    assert m.keypoint_of_point.tolist() == [-1]
