"""The match by projection's compiled pass (frontend/matching_kernels.py: a grid of the keypoints) against the
whole-array formulation it replaced (a k-d tree's pair list, stable sorts), on frames built for ties: descriptors
that differ from a few shared ones by a bit or two, so that distances tie within a point's candidates and between
the points that want one keypoint. A different tie rule (a later pair in the tree's listing, a higher map point) or
a test moved to the wrong side of a bound changes the matches, and with them the poses."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from frontend.matching import search_by_projection
from slam.core.camera import PinholeCamera
from slam.core.descriptors import hamming
from slam.core.frame import FeatureFrame, MapPoints

CAMERA = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
SCALES = 1.2 ** np.arange(8)


def _first_per_group(groups, keys):
    order = np.lexsort((keys, groups))
    if len(order) == 0:
        return order
    first = np.r_[True, groups[order][1:] != groups[order][:-1]]
    return order[first]


def _best_two(groups, keys):
    order = np.lexsort((keys, groups))
    if len(order) == 0:
        return order, order.copy()
    g = groups[order]
    is_first = np.r_[True, g[1:] != g[:-1]]
    first_pos = np.flatnonzero(is_first)
    second_pos = first_pos + 1
    has_second = second_pos < len(order)
    has_second[has_second] &= ~is_first[second_pos[has_second]]
    second = np.full(len(first_pos), -1)
    second[has_second] = order[second_pos[has_second]]
    return order[first_pos], second


def _reference(frame, points, T_cw, radius, max_distance, ratio, eligible, max_level_gap=1):
    """``search_by_projection`` before the kernel (sorts over whole arrays)."""
    m = len(points)
    kop, dist = np.full(m, -1), np.full(m, -1)
    pc = points.xyz @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv, z = CAMERA.project(pc)
    visible = (z > CAMERA.min_depth) & CAMERA.in_image(np.nan_to_num(uv, nan=-1.0))
    vis_idx, kp_idx = np.flatnonzero(visible), np.flatnonzero(eligible)
    has_octave = len(points.octaves) == m
    point_scale = frame.scale_factors[np.clip(points.octaves, 0, len(frame.scale_factors) - 1)] if has_octave \
        else np.ones(m)
    pairs = cKDTree(uv[vis_idx]).sparse_distance_matrix(
        cKDTree(frame.uv[kp_idx]), radius * point_scale[vis_idx].max(), output_type="ndarray")
    pi, ki, dist_px = vis_idx[pairs["i"]], kp_idx[pairs["j"]], pairs["v"]
    ok = dist_px <= radius * point_scale[pi]
    if has_octave:
        ok &= np.abs(frame.octaves[ki] - points.octaves[pi]) <= max_level_gap
    pi, ki = pi[ok], ki[ok]
    if len(pi) == 0:
        return kop, dist
    ham = hamming(points.descriptors[pi], frame.descriptors[ki])
    best, second = _best_two(pi, ham)
    accept = ham[best] <= max_distance
    ambiguous = second >= 0
    ambiguous[ambiguous] &= frame.octaves[ki[second[ambiguous]]] == frame.octaves[ki[best[ambiguous]]]
    accept[ambiguous] &= ham[best][ambiguous] <= ratio * ham[second[ambiguous]]
    best = best[accept]
    winners = best[_first_per_group(ki[best], ham[best])]
    kop[pi[winners]] = ki[winners]
    dist[pi[winners]] = ham[winners]
    return kop, dist


def _scene(seed: int, n_kp: int = 400, n_points: int = 500, with_octaves: bool = True):
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (6, 32), dtype=np.uint8)

    def near(n):       # a shared descriptor with 0-2 bits flipped: many equal distances
        desc = base[rng.integers(0, len(base), n)].copy()
        for row in range(n):
            for _ in range(rng.integers(0, 3)):
                desc[row, rng.integers(32)] ^= np.uint8(1 << rng.integers(8))
        return desc

    uv = np.c_[rng.uniform(20, 620, n_kp), rng.uniform(20, 460, n_kp)]
    frame = FeatureFrame(0, 0.0, uv, uv, rng.integers(0, 4, n_kp), near(n_kp), np.ones(n_kp),
                         np.full(n_kp, np.nan), np.zeros(n_kp), SCALES)
    # points near keypoints (several per keypoint) and some anywhere; a few behind the camera
    anchor = rng.integers(0, n_kp, n_points)
    proj = uv[anchor] + rng.normal(0, 3, (n_points, 2))
    proj[: n_points // 5] = np.c_[rng.uniform(0, 640, n_points // 5), rng.uniform(0, 480, n_points // 5)]
    z = rng.uniform(1, 4, n_points)
    z[:5] = -1.0
    xyz = np.c_[(proj[:, 0] - 320) / 500 * z, (proj[:, 1] - 240) / 500 * z, z]
    octaves = rng.integers(0, 4, n_points) if with_octaves else np.zeros(0, int)
    points = MapPoints(np.arange(n_points), xyz, near(n_points), octaves)
    eligible = rng.random(n_kp) > 0.1
    return frame, points, eligible


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("radius, max_distance, ratio", [(8.0, 100, 1.0), (15.0, 3, 0.8), (4.0, 50, 0.5)])
def test_projection_matches_are_those_of_the_sorting_formulation(seed, radius, max_distance, ratio):
    frame, points, eligible = _scene(seed, with_octaves=seed % 3 != 2)
    T_cw = np.eye(4)
    result = search_by_projection(frame, points, T_cw, CAMERA, radius, max_distance, ratio, eligible)
    kop, dist = _reference(frame, points, T_cw, radius, max_distance, ratio, eligible)
    assert (kop >= 0).sum() > 20          # the scene matches something
    np.testing.assert_array_equal(result.keypoint_of_point, kop)
    np.testing.assert_array_equal(result.distance, dist)
    assert result.keypoint_of_point.dtype == np.int64 and result.distance.dtype == np.int64
    matched = kop[kop >= 0]
    assert len(np.unique(matched)) == len(matched)           # one map point per keypoint


@pytest.mark.parametrize("seed", range(3))
def test_keypoints_beyond_the_image_border_are_found_from_points_near_it(seed):
    """Undistorted keypoints may lie a few pixels outside the image (the grid keeps them in its border cells):
    points projected near the border still find them, as the k-d tree does, also with a wide search."""
    frame, points, eligible = _scene(seed)
    rng = np.random.default_rng(100 + seed)
    uv = frame.uv.copy()
    out = rng.random(len(uv)) < 0.3
    uv[out, 0] = np.where(rng.random(out.sum()) < 0.5, rng.uniform(-12, 0, out.sum()), rng.uniform(640, 652, out.sum()))
    frame = FeatureFrame(0, 0.0, uv, uv, frame.octaves, frame.descriptors, frame.depths, frame.u_right,
                         frame.dynamic_prob, SCALES)
    xyz = points.xyz.copy()        # a third of the points projected inside the image within 3 px of such a keypoint
    near = rng.random(len(xyz)) < 0.33
    near[:5] = False               # (behind the camera)
    anchor = rng.choice(np.flatnonzero(out), near.sum())
    u = np.clip(uv[anchor, 0] + rng.uniform(-3, 3, near.sum()), 0, 639.9)
    v = uv[anchor, 1] + rng.uniform(-2, 2, near.sum())
    xyz[near, 0] = (u - 320) / 500 * xyz[near, 2]
    xyz[near, 1] = (v - 240) / 500 * xyz[near, 2]
    points = MapPoints(points.ids, xyz, points.descriptors, points.octaves)
    for radius in (4.0, 30.0):
        result = search_by_projection(frame, points, np.eye(4), CAMERA, radius, 100, 1.0, eligible)
        kop, dist = _reference(frame, points, np.eye(4), radius, 100, 1.0, eligible)
        assert (kop[near] >= 0).sum() > 10 if radius > 4 else (kop[near] >= 0).any()
        np.testing.assert_array_equal(result.keypoint_of_point, kop)
        np.testing.assert_array_equal(result.distance, dist)
