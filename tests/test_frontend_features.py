"""Tests for the front end's features on synthetic RGB-D data: ORB extraction, descriptor distances and
matching."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from frontend.matching import match_brute_force, search_by_projection
from slam.core.descriptors import hamming as hamming_pairs
from frontend.orb_extractor import OrbExtractor, features_per_level
from slam.core.camera import PinholeCamera
from slam.core.config import load_config
from slam.datasets import SyntheticSequence
from slam.core.frame import FeatureFrame, MapPoints
from slam.core.geometry import invert, transform_points


def test_default_camera_matches_the_synthetic_one(default_config):
    seq_intrinsics = SyntheticSequence(n_frames=1).intrinsics
    cam = default_config.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == seq_intrinsics
    assert (cam.width, cam.height) == (640, 480)
    assert not any(cam.distortion)


# --- ORB extraction ------------------------------------------------------------------------------


def test_extractor_returns_about_n_features_on_every_level(orbit_features, default_config):
    cfg = default_config.orb
    quota = features_per_level(cfg.n_features, cfg.scale_factor, cfg.n_levels)
    assert quota.sum() == cfg.n_features
    for frame in orbit_features:
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


@pytest.mark.parametrize("masked", [False, True])
def test_extractor_describes_only_the_kept_corners_with_the_same_bits(orbit_sequence, default_config, default_camera,
                                                                      masked):
    """extract() detects, keeps the grid's share and describes only those; the result must be the rows of
    the kept corners of one detectAndCompute over all of them (the former path), masked or not."""
    from frontend.orb_extractor import distribute_on_grid
    frames, _ = orbit_sequence
    extractor = OrbExtractor(default_config.orb, default_camera)
    for f in frames[:3]:
        gray = cv2.cvtColor(f.rgb, cv2.COLOR_BGR2GRAY)
        mask = None
        if masked:
            mask = np.zeros(gray.shape, np.uint8)
            mask[:, gray.shape[1] // 3:] = 255
        frame = extractor.extract(gray, f.depth, mask=mask)
        keypoints, descriptors = extractor._orb.detectAndCompute(gray, mask)
        xy = np.array([k.pt for k in keypoints])
        octave = np.array([k.octave for k in keypoints])
        keep = distribute_on_grid(xy, np.array([k.response for k in keypoints]), octave, extractor.scale_factors,
                                  extractor.quota, default_config.orb.cell_size)
        assert len(keep) > 0.9 * default_config.orb.n_features * (2 / 3 if masked else 1)
        np.testing.assert_array_equal(frame.descriptors, descriptors[keep])
        np.testing.assert_array_equal(frame.uv_raw, xy[keep])
        np.testing.assert_array_equal(frame.octaves, octave[keep])
        if masked:
            assert (frame.uv_raw[:, 0] >= gray.shape[1] // 3 - 1).all()


def test_features_are_spread_over_the_image(orbit_features, default_camera):
    for frame in orbit_features:
        counts, _, _ = np.histogram2d(frame.uv_raw[:, 0], frame.uv_raw[:, 1], bins=(4, 4),
                                      range=((0, default_camera.width), (0, default_camera.height)))
        assert counts.min() >= 20, counts
        # No cell hoards the features the way plain OpenCV ORB (strongest corners only) does on this
        # scene: there the fullest cell holds ~15% and the cell counts vary by ~55% (std / mean).
        assert counts.max() <= 0.12 * len(frame), counts
        assert counts.std() / counts.mean() < 0.4, counts


def test_feature_depths_come_from_the_depth_map(orbit_sequence, orbit_features, default_camera):
    frames, _ = orbit_sequence
    for frame, rgbd in zip(orbit_features, frames):
        cols = np.rint(frame.uv_raw[:, 0]).astype(int)
        rows = np.rint(frame.uv_raw[:, 1]).astype(int)
        np.testing.assert_array_equal(frame.depths, rgbd.depth[rows, cols].astype(float))
        assert (frame.depths > 0).all()  # the synthetic room has depth everywhere
        # No distortion: ideal and raw coordinates coincide.
        np.testing.assert_allclose(frame.uv, frame.uv_raw)
        np.testing.assert_allclose(frame.u_right, default_camera.right_u(frame.uv[:, 0], frame.depths))
        usable = (frame.depths > default_camera.min_depth) & (frame.depths < default_camera.max_depth)
        np.testing.assert_array_equal(frame.has_depth, usable)
        assert usable.mean() > 0.95


def test_extractor_undistorts_with_a_distorted_camera(orbit_sequence):
    frames, _ = orbit_sequence
    cfg = load_config("tum_fr1", overrides={"orb.n_features": 300})
    cam = PinholeCamera.from_config(cfg.camera)
    frame = OrbExtractor(cfg.orb, cam).extract(cv2.cvtColor(frames[0].rgb, cv2.COLOR_BGR2GRAY), frames[0].depth)
    assert 0.95 * 300 <= len(frame) <= 300
    np.testing.assert_allclose(frame.uv, cam.undistort_points(frame.uv_raw))
    assert np.abs(frame.uv - frame.uv_raw).max() > 1.0


def test_extractor_on_a_blank_image_returns_an_empty_frame(default_config, default_camera):
    frame = OrbExtractor(default_config.orb, default_camera).extract(np.full((480, 640), 128, np.uint8), np.ones((480, 640), np.float32))
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


def test_search_by_projection_with_the_true_pose(orbit_features, orbit_sequence, default_camera, default_config):
    _, gt = orbit_sequence
    f0, f1 = orbit_features[0], orbit_features[1]
    points = frame_as_map_points(f0, gt[0], default_camera)
    T_cw1 = invert(gt[1])
    radius = default_config.tracking.local_map_search_radius
    matches = search_by_projection(f1, points, T_cw1, default_camera, radius, default_config.tracking.max_descriptor_distance,
                                   default_config.tracking.match_ratio, np.ones(len(f1), bool))
    kp = matches.keypoint_of_point
    matched = kp >= 0
    assert matches.visible.mean() > 0.9
    assert matched.sum() >= 0.5 * matches.visible.sum()
    assert not (matched & ~matches.visible).any()
    # Every keypoint is used at most once.
    assert len(np.unique(kp[matched])) == matched.sum()
    # Matched keypoints lie near the point's projection (ORB localises to ~1 px per pyramid scale).
    projected, _ = default_camera.project(transform_points(T_cw1, points.xyz))
    offset = np.linalg.norm(f1.uv[kp[matched]] - projected[matched], axis=1)
    scale = f0.scale_factors[points.octaves[matched]]
    assert (offset <= radius * scale + 1e-9).all()
    assert np.median(offset) < 1.5
    assert np.mean(offset < 3.0 * scale) > 0.9
    # The reported distance is the Hamming distance of the pair, within the limit.
    np.testing.assert_array_equal(matches.distance[matched], hamming_pairs(points.descriptors[matched],
                                                                           f1.descriptors[kp[matched]]))
    assert (matches.distance[matched] <= default_config.tracking.max_descriptor_distance).all()
    assert (matches.distance[~matched] == -1).all()
    # Neighbouring pyramid levels only.
    assert (np.abs(f1.octaves[kp[matched]] - points.octaves[matched]) <= 1).all()


def test_search_by_projection_into_the_same_frame_finds_every_point(orbit_features, orbit_sequence, default_camera):
    _, gt = orbit_sequence
    f0 = orbit_features[0]
    points = frame_as_map_points(f0, gt[0], default_camera)
    matches = search_by_projection(f0, points, invert(gt[0]), default_camera, 4.0, 100, 0.8, np.ones(len(f0), bool))
    np.testing.assert_array_equal(matches.keypoint_of_point, np.arange(len(f0)))
    np.testing.assert_array_equal(matches.distance, 0)


def test_search_by_projection_uses_each_keypoint_once_with_duplicate_points(orbit_features, orbit_sequence, default_camera):
    _, gt = orbit_sequence
    f0, f1 = orbit_features[0], orbit_features[1]
    points = frame_as_map_points(f0, gt[0], default_camera)
    doubled = MapPoints.concat([points, points])   # two identical candidates for every keypoint
    matches = search_by_projection(f1, doubled, invert(gt[1]), default_camera, 8.0, 100, 1.0, np.ones(len(f1), bool))
    kp = matches.keypoint_of_point[matches.keypoint_of_point >= 0]
    assert len(kp) > 200
    assert len(np.unique(kp)) == len(kp)


def test_search_by_projection_respects_eligibility(orbit_features, orbit_sequence, default_camera):
    _, gt = orbit_sequence
    f0, f1 = orbit_features[0], orbit_features[1]
    points = frame_as_map_points(f0, gt[0], default_camera)
    rng = np.random.default_rng(1)
    eligible = rng.random(len(f1)) < 0.5
    matches = search_by_projection(f1, points, invert(gt[1]), default_camera, 4.0, 100, 0.8, eligible)
    kp = matches.keypoint_of_point[matches.keypoint_of_point >= 0]
    assert len(kp) > 100
    assert eligible[kp].all()
    none = search_by_projection(f1, points, invert(gt[1]), default_camera, 4.0, 100, 0.8, np.zeros(len(f1), bool))
    assert (none.keypoint_of_point == -1).all()


def test_search_by_projection_skips_points_behind_the_camera(orbit_features, orbit_sequence, default_camera):
    _, gt = orbit_sequence
    f0 = orbit_features[0]
    points = frame_as_map_points(f0, gt[0], default_camera)
    # Turn the camera around (rotate 180 degrees about its y axis): nothing is in front any more.
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    matches = search_by_projection(f0, points, flip @ invert(gt[0]), default_camera, 4.0, 100, 0.8, np.ones(len(f0), bool))
    assert not matches.visible.any()
    assert (matches.keypoint_of_point == -1).all()


def test_match_brute_force_unique_and_geometrically_right(orbit_features, orbit_sequence, default_camera):
    _, gt = orbit_sequence
    f0, f1 = orbit_features[0], orbit_features[1]
    qi, ti = match_brute_force(f1.descriptors, f0.descriptors, 0.8, 100)
    assert len(qi) > 300
    assert len(np.unique(ti)) == len(ti)
    assert len(np.unique(qi)) == len(qi)
    assert (hamming_pairs(f1.descriptors[qi], f0.descriptors[ti]) <= 100).all()
    # Most descriptor-only matches are the same scene point: the frame-0 point lands on the frame-1 keypoint.
    xyz = transform_points(gt[0], default_camera.backproject(f0.uv[ti], f0.depths[ti]))
    projected, _ = default_camera.project(transform_points(invert(gt[1]), xyz))
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
