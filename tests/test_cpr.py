"""CPR-SLAM's sub-point-cloud correlation (frontend/dynamic/cpr.py) on small synthetic inputs.

The scene is rendered here by ray casting in numpy (a room of planes, two static boxes and a floating box
that moves 7.5 cm per frame, so 15 cm between the current frame and its reference sigma = 2 frames back),
so the test does not depend on the synthetic-sequence generator.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest

from frontend.dynamic.base import DynamicContext
from frontend.dynamic.cpr import (CprMethod, build_cloud, cluster, mad_threshold, mls_smooth, refine_mask,
                                  sample_grid, soft_probability, sub_poses, voxel_filter, _smallest_eigvec)
from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import CprConfig
from slam.core.frame import FeatureFrame

W, H = 640, 480
CAMERA = PinholeCamera(525.0, 525.0, 319.5, 239.5, W, H)

# world = camera frame of frame 0 (x right, y down, z forward)
PLANES = [  # (normal, offset, texture seed): n . x = c
    (np.array([0.0, 0.0, 1.0]), 4.5, 1),     # back wall
    (np.array([0.0, 1.0, 0.0]), 1.0, 2),     # floor
    (np.array([0.0, 1.0, 0.0]), -1.6, 3),    # ceiling
    (np.array([1.0, 0.0, 0.0]), -2.6, 4),    # left wall
    (np.array([1.0, 0.0, 0.0]), 2.6, 5),     # right wall
]
STATIC_BOXES = [  # (centre, half sizes, yaw deg, texture seed)
    (np.array([-1.2, 0.6, 3.0]), np.array([0.3, 0.4, 0.3]), 25.0, 6),
    (np.array([1.3, 0.5, 3.4]), np.array([0.4, 0.5, 0.3]), -30.0, 7),
    (np.array([-0.9, -0.8, 3.8]), np.array([0.35, 0.25, 0.2]), 40.0, 9),
    (np.array([1.7, -0.9, 3.3]), np.array([0.25, 0.2, 0.25]), -20.0, 10),
    (np.array([0.1, 0.75, 3.9]), np.array([0.5, 0.25, 0.3]), 10.0, 11),
]
MOVER_START, MOVER_HALF, MOVER_YAW = np.array([0.1, -0.1, 1.9]), np.array([0.3, 0.75, 0.2]), 35.0
MOVER_STEP = np.array([0.05, 0.0, -0.06])    # per frame: 15.6 cm between a frame and its reference


def _rot_y(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def camera_T_cw(i: int) -> np.ndarray:
    """Slight camera motion: 0.3 deg yaw and 6 mm per frame."""
    T_wc = np.eye(4)
    T_wc[:3, :3] = _rot_y(0.3 * i)
    T_wc[:3, 3] = [0.005 * i, 0.0, 0.003 * i]
    T_cw = np.eye(4)
    T_cw[:3, :3] = T_wc[:3, :3].T
    T_cw[:3, 3] = -T_wc[:3, :3].T @ T_wc[:3, 3]
    return T_cw


def _texture(p: np.ndarray, seed: int) -> np.ndarray:
    f = 3.0 + seed
    return 0.5 + 0.2 * np.sin(f * p[..., 0] + seed) * np.cos(f * p[..., 1] - seed) + 0.2 * np.sin(f * p[..., 2])


@functools.lru_cache(maxsize=16)
def render(i: int, moving: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth m, grey uint8, mover pixel mask) of frame i (cached: treat as read-only)."""
    T_cw = camera_T_cw(i)
    R_wc, o = T_cw[:3, :3].T, -T_cw[:3, :3].T @ T_cw[:3, 3]
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    d = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u)], -1) @ R_wc.T
    best = np.full((H, W), np.inf)
    seed_map = np.zeros((H, W), int)
    local = np.zeros((H, W, 3))                  # hit point in the primitive's frame (texture coordinates)
    for n, c, seed in PLANES:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - n @ o) / (d @ n)
        t = np.where(t > 0, t, np.inf)
        closer = t < best
        best[closer], seed_map[closer] = t[closer], seed
        local[closer] = o + t[closer][:, None] * d[closer]
    mover = MOVER_START + (MOVER_STEP * i if moving else 0.0)
    for centre, half, yaw, seed in STATIC_BOXES + [(mover, MOVER_HALF, MOVER_YAW, 8)]:
        rb = _rot_y(yaw)
        ob, db = rb.T @ (o - centre), d @ rb           # ray in the box frame
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (-half - ob) / db, (half - ob) / db
        tmin = np.max(np.minimum(t0, t1), axis=-1)
        tmax = np.min(np.maximum(t0, t1), axis=-1)
        t = np.where((tmax >= tmin) & (tmin > 0), tmin, np.inf)
        closer = t < best
        best[closer], seed_map[closer] = t[closer], seed
        local[closer] = ob + t[closer][:, None] * db[closer]
    grey = np.zeros((H, W))
    for seed in np.unique(seed_map):
        sel = seed_map == seed
        grey[sel] = _texture(local[sel], seed)
    depth = np.where(np.isfinite(best), best, 0.0).astype(np.float32)   # ray z component is 1: t = depth
    return depth, np.clip(grey * 255, 0, 255).astype(np.uint8), seed_map == 8


def make_frame(i: int, step: int = 8) -> FeatureFrame:
    uv = np.stack(np.meshgrid(np.arange(4, W, step), np.arange(4, H, step)), -1).reshape(-1, 2).astype(float)
    n = len(uv)
    return FeatureFrame(i, i / 30.0, uv, uv.copy(), np.zeros(n, int), np.zeros((n, 32), np.uint8), np.ones(n),
                        np.zeros(n), np.zeros(n), np.ones(8))


def context(i: int, moving: bool = True) -> tuple[DynamicContext, np.ndarray]:
    depth, grey, mover = render(i, moving)
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    return DynamicContext(make_frame(i), rgb, grey, depth, CAMERA, None, camera_T_cw(i),
                          camera_T_cw(i - 1) if i else None), mover


def run_sequence(method: CprMethod, n: int, moving: bool = True):
    outs = []
    for i in range(n):
        ctx, mover = context(i, moving)
        out = method.process(ctx)
        method.end_frame(ctx, out, camera_T_cw(i), is_keyframe=(i == 0))
        outs.append((ctx, out, mover))
    return outs


@pytest.fixture(scope="module")
def moving_run():
    return run_sequence(CprMethod(CprConfig()), 3)


# --- the whole method ------------------------------------------------------------------------------------


def test_protocol_and_abstention(moving_run):
    method = CprMethod(CprConfig())
    assert method.name == "cpr" and method.needs_detector is False
    for ctx, out, _ in moving_run[:2]:            # sigma = 2: no reference yet
        assert out.prob.shape == (len(ctx.frame),) and np.all(np.isnan(out.prob))
    ctx, out, _ = moving_run[2]
    assert out.prob.shape == (len(ctx.frame),) and np.all(np.isfinite(out.prob))
    assert out.mask.shape == (H, W) and out.mask.dtype == np.float32


def test_moving_box_flagged_static_scene_not(moving_run):
    ctx, out, mover = moving_run[2]
    flagged = out.mask >= 0.5
    assert flagged[mover].mean() > 0.8, "the moving box must be masked"
    valid_static = (~mover) & (ctx.depth > 0)
    assert flagged[valid_static].mean() < 0.08, "the static planes and boxes must stay unmasked"
    r, eps = np.asarray(out.info["scores"]), out.info["threshold"]
    assert 1 <= out.info["dynamic_clusters"] <= 3
    assert np.nanmax(r) > 3 * np.nanmedian(r)                  # the box's sub-pose misaligns the cloud
    assert np.sum(r > eps) == out.info["dynamic_clusters"]
    # keypoints: 1 on the box, 0 on most of the static scene
    uv = np.rint(ctx.frame.uv_raw).astype(int)
    on_box = mover[uv[:, 1], uv[:, 0]]
    assert np.mean(out.prob[on_box] >= 0.5) > 0.8
    assert np.mean(out.prob[~on_box] >= 0.5) < 0.1


def test_score_ratio_guard():
    """The paper's threshold always flags the tail of R; even on exact data a static sub-cloud's sub-pose
    drifts ~1 cm, which moves R of the whole cloud by up to ~60 %. The optional guard R > ratio * median(R)
    removes those while a real mover (R ~ 3.5x the median here) still passes."""
    cfg = CprConfig(min_score_ratio=2.0)
    _, out, _ = run_sequence(CprMethod(cfg), 3, moving=False)[2]
    assert out.info["dynamic_clusters"] == 0
    assert np.all(out.prob == 0.0)
    ctx, out, mover = run_sequence(CprMethod(cfg), 3)[2]
    assert out.info["dynamic_clusters"] == 1
    assert (out.mask >= 0.5)[mover].mean() > 0.8


def test_deterministic(moving_run):
    again = run_sequence(CprMethod(CprConfig()), 3)
    for (_, a, _), (_, b, _) in zip(moving_run, again):
        np.testing.assert_array_equal(a.prob, b.prob)
    np.testing.assert_array_equal(moving_run[2][1].mask, again[2][1].mask)
    np.testing.assert_array_equal(moving_run[2][1].info["scores"], again[2][1].info["scores"])


def test_missing_end_frame_and_lost_pose_are_tolerated():
    method = CprMethod(CprConfig())
    for i in range(4):
        ctx, _ = context(i)
        out = method.process(ctx)
        if i == 1:
            method.end_frame(ctx, out, None, False)   # lost: reference pose unknown -> identity guess
        # frames 0 and 2: no end_frame at all
    assert np.all(np.isfinite(out.prob))


# --- the paper's building blocks -------------------------------------------------------------------------


def test_mad_threshold_formula():
    r = np.array([1.0, 2.0, 3.0, 4.0, 100.0])
    # mean 22, median 3, |R - 3| = 2 1 0 1 97 -> median 1
    assert mad_threshold(r) == pytest.approx(22.0 + 1.4826)
    assert mad_threshold(r, 2.0) == pytest.approx(24.0)
    assert np.flatnonzero(r > mad_threshold(r)).tolist() == [4]


def test_keyframe_refinement_weights():
    n_hist = 6
    hist = [np.zeros((1, 4), np.uint8) for _ in range(n_hist)]
    for k in range(5):
        hist[k][0, 0] = 1          # pixel 0: flagged in 5 of the last 6 masks
    hist[2][0, 1] = 1              # pixel 1: flagged once
    for k in range(4):
        hist[k][0, 3] = 1          # pixel 3: flagged in 4 of 6 and in the current frame
    current = np.array([[0, 0, 1, 1]], np.uint8)   # pixel 2: only in the current frame
    history = [(m, 2.0) for m in hist]              # ordinary frames: rho = 2; current: rho = 3
    refined, fraction = refine_mask(history, current, 3.0, 0.6)
    # total weight 6*2 + 3 = 15, threshold 0.6 * 15 = 9
    assert refined[0].tolist() == [1, 0, 0, 1]
    np.testing.assert_allclose(fraction[0], [10 / 15, 2 / 15, 3 / 15, 11 / 15], rtol=1e-6)
    # with equal rho the threshold is Eq. 19's tau (N + 1) rho
    same = [(m, 3.0) for m in hist]
    refined, fraction = refine_mask(same, current, 3.0, 0.6)
    weight = fraction * 3.0 * (n_hist + 1)
    np.testing.assert_array_equal(refined, (weight > 0.6 * (n_hist + 1) * 3.0).astype(np.uint8))
    # keyframe masks weigh more: flagged in 3 keyframe masks (9) + current (3) = 12 > 0.6 * (3*3 + 3*2 + 3)
    # = 10.8, while flagged in 3 ordinary-frame masks (6) + current (3) = 9 is not
    on, off = np.ones((1, 1), np.uint8), np.zeros((1, 1), np.uint8)
    kf_first = [(on, 3.0)] * 3 + [(off, 2.0)] * 3
    frames_first = [(off, 3.0)] * 3 + [(on, 2.0)] * 3
    assert refine_mask(kf_first, on, 3.0, 0.6)[0][0, 0] == 1
    assert refine_mask(frames_first, on, 3.0, 0.6)[0][0, 0] == 0


def test_soft_probability_is_half_at_tau():
    refined = np.array([[1, 0, 0]], np.uint8)
    frac = np.array([[0.9, 0.6, 0.3]], np.float32)
    p = soft_probability(refined, frac, 0.6)
    assert p[0, 0] == 1.0 and p[0, 1] < 0.5 and p[0, 2] == pytest.approx(0.25)


def test_refinement_runs_in_the_method_after_the_window():
    cfg = CprConfig(refine=True, refine_window=2)
    outs = run_sequence(CprMethod(cfg), 5)
    ctx, out, mover = outs[4]
    assert out.info["ms_refine"] >= 0.0
    flagged = out.mask >= 0.5
    assert flagged[mover].mean() > 0.7      # a box moving for several frames stays masked


def test_voxel_filter_centroids_and_mean_intensity():
    xyz = np.array([[0.01, 0.01, 0.01], [0.03, 0.02, 0.04], [0.02, 0.04, 0.03],   # voxel (0,0,0)
                    [0.06, 0.01, 0.01], [0.09, 0.04, 0.02]])                        # voxel (1,0,0)
    inten = np.array([0.1, 0.2, 0.6, 1.0, 0.5])
    cen, mean_i, inverse = voxel_filter(xyz, inten, 0.05)
    assert len(cen) == 2
    a, b = inverse[0], inverse[3]
    assert inverse.tolist() == [a, a, a, b, b] and a != b
    np.testing.assert_allclose(cen[a], xyz[:3].mean(0))
    np.testing.assert_allclose(cen[b], xyz[3:].mean(0))
    assert mean_i[a] == pytest.approx(0.3) and mean_i[b] == pytest.approx(0.75)


def test_mls_flattens_a_noisy_plane():
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.arange(0, 1.0, 0.05), np.arange(0, 1.0, 0.05)), -1).reshape(-1, 2)
    xyz = np.column_stack([g + 0.025, 2.0 + rng.normal(0, 0.01, len(g))])
    smooth, keep, normals = mls_smooth(xyz, 0.1, 0.05)
    assert keep.all()
    inner = np.all((g > 0.1) & (g < 0.85), axis=1)
    assert np.std(smooth[inner, 2]) < 0.5 * np.std(xyz[inner, 2])
    assert np.all(np.abs(normals[inner, 2]) > 0.95)
    lonely = mls_smooth(np.array([[0.0, 0, 0], [1.0, 1, 1], [2.0, 2, 2]]), 0.1, 0.05)[1]
    assert not lonely.any()


def test_closed_form_eigenvector_matches_eigh():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(200, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2)
    vec, ok = _smallest_eigvec(cov)
    ref = np.linalg.eigh(cov)[1][:, :, 0]
    assert ok.all()
    np.testing.assert_allclose(np.abs(np.einsum("na,na->n", vec, ref)), 1.0, atol=1e-6)


def test_sub_poses_recover_a_rigid_motion():
    cfg = CprConfig()
    depth, grey, _ = render(0, moving=False)
    pix, rays = sample_grid(CAMERA, H, W, cfg.sample_step)
    ref = build_cloud(depth, grey, pix, rays, cfg).target()
    depth2, grey2, _ = render(2, moving=False)
    cur = build_cloud(depth2, grey2, pix, rays, cfg)
    true = camera_T_cw(0) @ np.linalg.inv(camera_T_cw(2))        # current camera -> reference camera
    labels = cluster(cur.xyz, cfg.clusters, cfg.seed)
    poses, valid = sub_poses(cur.xyz, cur.intensity, labels, cfg.clusters, ref, np.eye(4), cfg)
    assert valid.all()

    def point_error(T: np.ndarray, j: int) -> float:   # mean displacement error over the sub-cloud
        p = cur.xyz[labels == j]
        return float(np.mean(np.linalg.norm(p @ (T[:3, :3] - true[:3, :3]).T + T[:3, 3] - true[:3, 3], axis=1)))

    before = np.median([point_error(np.eye(4), j) for j in range(cfg.clusters)])
    after = np.median([point_error(poses[j], j) for j in range(cfg.clusters)])
    assert before > 0.03                   # the camera moved 1.2 cm and 0.6 deg: ~4 cm at the points
    assert after < 0.5 * before and after < 0.02


def test_kmeans_is_seeded():
    xyz = np.random.default_rng(2).random((500, 3))
    np.testing.assert_array_equal(cluster(xyz, 10, 0), cluster(xyz, 10, 0))


def test_boxes_of_the_shared_synthetic_sequence():
    """The project's generator with flying, tumbling boxes (ground-truth ``dynamic_mask``)."""
    import cv2

    from slam.datasets import SyntheticSequence
    from slam.core.geometry import invert

    try:
        seq = SyntheticSequence(n_frames=120, movers="boxes", seed=0)
    except TypeError:
        pytest.skip("SyntheticSequence has no movers")
    cam = PinholeCamera(*seq.intrinsics, seq.width, seq.height)
    _, T_wc = seq.groundtruth()
    method = CprMethod(CprConfig())
    recall, false_pos = [], []
    for i in range(6):
        f = seq.frame(i)
        ctx = DynamicContext(make_frame(i), f.rgb, cv2.cvtColor(f.rgb, cv2.COLOR_BGR2GRAY), f.depth, cam, None,
                             invert(T_wc[i]), None)
        out = method.process(ctx)
        method.end_frame(ctx, out, invert(T_wc[i]), False)
        if out.mask is None or f.dynamic_mask.sum() < 500:
            continue
        flagged = out.mask >= 0.5
        recall.append(flagged[f.dynamic_mask].mean())
        false_pos.append(flagged[~f.dynamic_mask & (f.depth > 0)].mean())
    assert len(recall) >= 3
    assert min(recall) > 0.9
    assert np.mean(false_pos) < 0.25     # the paper's threshold always takes the tail of R (see the module)
