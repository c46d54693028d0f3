"""Tests for the front end's tracking on synthetic RGB-D data: the keyframe policy, and tracking through
the System facade."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import ORBIT_FRAMES as N_FRAMES
from frontend.dynamic import StaticWorld
from frontend.keyframe_policy import KeyframeEvidence, close_point_counts, keyframe_distances, need_keyframe
from frontend.tracker import Tracker, TrackingState
from slam.core.config import KeyframeConfig
from slam.core.frame import FeatureFrame
from slam.core.geometry import invert, so3_log
from slam.runtime.system import System


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


def test_close_point_counts(orbit_features, default_camera):
    frame = orbit_features[0]
    rng = np.random.default_rng(3)
    lm = np.where(rng.random(len(frame)) < 0.4, np.arange(len(frame)), -1)
    dyn = frame.dynamic_prob.copy()
    dyn[:100] = 0.9
    frame_d = FeatureFrame(frame.index, frame.timestamp, frame.uv_raw, frame.uv, frame.octaves, frame.descriptors,
                           frame.depths, frame.u_right, dyn, frame.scale_factors)
    close = frame.has_depth & (frame.depths < default_camera.close_depth) & (dyn < 0.5)
    tracked, untracked = close_point_counts(frame_d, lm, default_camera.close_depth, 0.5)
    assert tracked == int((close & (lm >= 0)).sum())
    assert untracked == int((close & (lm < 0)).sum())
    assert tracked + untracked == int(close.sum()) > 0


# --- tracking through the System facade ----------------------------------------------------------


def aligned_ground_truth(gt: np.ndarray) -> np.ndarray:
    """Ground-truth T_wc expressed in the frame of the first camera (the system starts at identity)."""
    return invert(gt[0])[None] @ gt


def test_tracker_follows_the_orbit(orbit_sequence, default_config):
    frames, gt = orbit_sequence
    reference = aligned_ground_truth(gt)
    system = System(default_config)
    outputs = [system.process(f.rgb, f.depth, f.timestamp) for f in frames]
    assert [o.state for o in outputs] == [TrackingState.OK] * N_FRAMES
    assert outputs[0].is_keyframe
    t_err, r_err = [], []
    for o, T_ref in zip(outputs, reference):
        D = invert(T_ref) @ o.T_wc
        t_err.append(np.linalg.norm(o.T_wc[:3, 3] - T_ref[:3, 3]))
        r_err.append(np.degrees(np.linalg.norm(so3_log(D[:3, :3]))))
        assert o.n_features >= 950
        assert o.n_tracked >= default_config.tracking.min_tracked_inliers
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


class DynamicAt(StaticWorld):
    """A dynamic filter that marks every feature of the given frame indices dynamic (no pixel mask, so
    no static refill: the frame must be lost); the rest of the DynamicFilter protocol is the null filter's."""

    name = "test_all_dynamic"

    def __init__(self, indices):
        self.indices = set(indices)

    def process(self, frame: FeatureFrame, rgb, gray, depth, predicted_T_cw, last_T_cw) -> np.ndarray:
        return np.full(len(frame), 1.0 if frame.index in self.indices else 0.0)


def test_all_dynamic_frame_is_lost_not_given_a_pose(orbit_sequence, default_config):
    frames, gt = orbit_sequence
    reference = aligned_ground_truth(gt)
    lost_at = 8
    system = System(default_config, dynamic_filter=DynamicAt({lost_at}))
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


def test_a_pose_the_inliers_barely_fix_is_lost_not_reported(orbit_sequence, default_config):
    """tracking.max_pose_sigma_m: the points-only uncertainty of the pose decides, not only the inlier
    count. A full view of the generated room fixes the position to millimetres; with the limit set below
    that, every frame after the first is LOST and gets no pose."""
    frames, _ = orbit_sequence
    sigmas = []
    tracker_track = Tracker.track

    def track(self, frame, source):
        result = tracker_track(self, frame, source)
        sigmas.append(result.pose_sigma_t)
        return result

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Tracker, "track", track)
        system = System(default_config.model_copy(deep=True), dynamic_filter=DynamicAt(set()))
        tracked = [system.process(f.rgb, f.depth, f.timestamp, index=f.index) for f in frames[:6]]
    assert all(o.state == TrackingState.OK for o in tracked)
    assert all(0.0001 < s < 0.005 for s in sigmas), sigmas
    strict = default_config.model_copy(deep=True)
    strict.tracking.max_pose_sigma_m = 0.00005
    system = System(strict, dynamic_filter=DynamicAt(set()))
    outputs = [system.process(f.rgb, f.depth, f.timestamp, index=f.index) for f in frames[:6]]
    assert outputs[0].is_keyframe
    assert all(o.state == TrackingState.LOST and o.T_wc is None for o in outputs[1:])


def test_all_dynamic_first_frame_does_not_initialise(orbit_sequence, default_config):
    frames, _ = orbit_sequence
    system = System(default_config, dynamic_filter=DynamicAt({0}))
    first = system.process(frames[0].rgb, frames[0].depth, frames[0].timestamp, index=0)
    assert first.state == TrackingState.NOT_INITIALIZED
    assert first.T_wc is None
    assert system.num_keyframes == 0
    second = system.process(frames[1].rgb, frames[1].depth, frames[1].timestamp, index=1)
    assert second.state == TrackingState.OK and second.is_keyframe
