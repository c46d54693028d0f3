"""The whole-array helpers of the cpr method (frontend/dynamic/cpr_cloud.py, cpr_icp.py, cpr.py) against
plain per-point / per-segment reference implementations on random input.

Most comparisons are bit-for-bit: the vectorised code repeats the reference arithmetic operation for
operation, which is what keeps the method's masks unchanged by the speed-ups.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from frontend.dynamic.cpr import samples_to_mask
from frontend.dynamic.cpr_cloud import Cloud, mls_smooth, voxel_filter
from frontend.dynamic.cpr_icp import _Rows, correlation_scores, robust_scale
from slam.core.dynamic_config import CprConfig


@pytest.mark.parametrize("lengths", [[150] * 10, [150, 37, 0, 150, 1, 2, 90, 0, 150, 11], [151, 4, 0, 150, 3, 1],
                                     [1], [2, 1, 0]])   # even and odd widths: every row's middle in one column
def test_segment_medians_are_numpy_medians(lengths):
    rng = np.random.default_rng(len(lengths) + sum(lengths))
    starts = np.concatenate([[0], np.cumsum(lengths)])
    values = rng.gamma(2.0, 0.02, starts[-1])
    ties = values[1::7].copy()
    values[:7 * len(ties):7] = ties                          # exact ties, as distances to one point give
    rows = _Rows(starts)
    med, scale = rows.medians(values), rows.robust_scales(values, 0.01)
    for j, (a, b) in enumerate(zip(starts[:-1], starts[1:])):
        if a == b:
            assert np.isnan(med[j])
            continue
        assert med[j] == np.median(values[a:b])              # bit for bit
        assert scale[j] == robust_scale(values[a:b], 0.01)


@pytest.mark.parametrize("kind", ["gamma", "grey_levels", "heavy_tail", "two_values", "extremes"])
def test_compiled_median_and_scale_are_numpy_bit_for_bit(kind):
    """The sub-pose ICP's robust scales (bucketed order statistics, cpr_icp_kernels) give np.median's values
    to the bit: odd and even counts, exact ties (grey-level residuals), tails metres beyond the bulk, all
    equal, zeros and the smallest subnormal beside huge values."""
    from frontend.dynamic import cpr_icp_kernels as kernels

    rng = np.random.default_rng(7)
    work, counts = np.empty(4000), np.empty(kernels._BUCKETS, np.int64)
    for n in [1, 2, 3, 24, 25, 26, 149, 150, 1349, 1350, 3999]:
        if kind == "gamma":
            v = rng.gamma(2.0, 0.02, n)
        elif kind == "grey_levels":
            v = np.abs(rng.integers(0, 40, n) / 255.0 - rng.integers(0, 40, n) / 255.0)
        elif kind == "heavy_tail":
            v = np.abs(rng.standard_cauchy(n))
        elif kind == "two_values":
            v = np.where(rng.random(n) < 0.4, 0.0, 0.5)
        else:
            v = rng.random(n) * 1e-3
            v[rng.integers(0, n, 3)] = [1e300, 0.0, 5e-324]
        assert kernels.median_nonneg(v.copy(), work, counts) == np.median(v)
        assert kernels.robust_scale_in_place(v.copy(), 0.0, work, counts) == robust_scale(v, 0.0)


def test_voxel_filter_matches_sorted_unique():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-1.0, 2.0, (3000, 3))
    inten = rng.random(3000)
    cen, mean_i, inverse = voxel_filter(xyz, inten, 0.1)
    keys = np.floor(xyz / 0.1).astype(np.int64)
    _, ref_inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    ref_inverse = ref_inverse.ravel()
    np.testing.assert_array_equal(inverse, ref_inverse)
    m = len(counts)
    np.testing.assert_array_equal(cen, np.stack([np.bincount(ref_inverse, xyz[:, a], m) for a in range(3)], 1)
                                  / counts[:, None])
    np.testing.assert_array_equal(mean_i, np.bincount(ref_inverse, inten, m) / counts)


def _mls_reference(xyz: np.ndarray, radius: float, voxel: float):
    """Point by point: Gaussian-weighted plane through the points of the 3x3x3 cells within ``radius``."""
    cells: dict[tuple, int] = {}
    for i, key in enumerate(map(tuple, np.floor(xyz / voxel).astype(int))):
        cells[key] = i
    out, keep, normals = xyz.copy(), np.zeros(len(xyz), bool), np.zeros_like(xyz)
    for i, p in enumerate(xyz):
        key = np.floor(p / voxel).astype(int)
        nb = [cells[t] for t in ((key[0] + a, key[1] + b, key[2] + c) for a in (-1, 0, 1) for b in (-1, 0, 1)
                                 for c in (-1, 0, 1)) if t in cells]
        nb = [j for j in nb if np.sum((xyz[j] - p) ** 2) <= radius**2]
        if len(nb) < 3:
            continue
        d = xyz[nb] - p
        w = np.exp(-np.sum(d**2, axis=1) / radius**2)
        m = w @ d / w.sum()
        cov = (w[:, None] * d).T @ d / w.sum() - np.outer(m, m)
        n = np.linalg.eigh(cov)[1][:, 0]
        keep[i], normals[i] = True, n
        out[i] = p - ((p - (p + m)) @ n) * n
    return out, keep, normals


def test_mls_matches_pointwise_reference():
    rng = np.random.default_rng(4)
    g = rng.uniform(0.0, 0.6, (1500, 2))
    surface = np.column_stack([g, 1.5 + 0.2 * np.sin(4 * g[:, 0]) + rng.normal(0, 0.01, len(g))])
    surface = np.vstack([surface, rng.uniform(-0.5, 1.0, (20, 3))])      # a few isolated points
    xyz, _, _ = voxel_filter(surface, np.zeros(len(surface)), 0.05)
    out, keep, normals = mls_smooth(xyz, 0.1, 0.05)
    ref_out, ref_keep, ref_normals = _mls_reference(xyz, 0.1, 0.05)
    np.testing.assert_array_equal(keep, ref_keep)
    assert 0 < keep.sum() < len(keep)
    np.testing.assert_allclose(out, ref_out, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(normals * ref_normals, axis=1))[keep], 1.0, atol=1e-9)


def test_mask_on_the_samples_box_equals_whole_image():
    rng = np.random.default_rng(5)
    h, w = 120, 160
    for trial in range(200):
        n = int(rng.integers(1, 60))
        centre = rng.integers(0, [h, w])                      # blobs anywhere, borders included
        pix = np.clip(centre + rng.normal(0, rng.uniform(1, 40), (n, 2)).astype(int), 0, [h - 1, w - 1])
        radius = int(rng.integers(1, 8))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        ref = np.zeros((h, w), np.uint8)
        ref[pix[:, 0], pix[:, 1]] = 1
        ref = cv2.morphologyEx(cv2.dilate(ref, kernel), cv2.MORPH_CLOSE, kernel)
        np.testing.assert_array_equal(samples_to_mask((h, w), pix, radius), ref, err_msg=f"trial {trial}")


def test_correlation_scores_match_a_per_pose_loop():
    rng = np.random.default_rng(6)
    ref_xyz, ref_i = rng.uniform(0, 1, (2000, 3)), rng.random(2000)
    ref = Cloud(ref_xyz, ref_i, np.zeros((0, 2), int), np.zeros(0, int), (1, 1), _tree=cKDTree(ref_xyz))
    src, src_i = rng.uniform(0, 1, (500, 3)), rng.random(500)
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, :3, 3] = rng.normal(0, 0.05, (5, 3))
    cfg = CprConfig(score_points=300, score_candidates=4, score_max_distance=0.0)   # the unbounded kNN R
    pick = (np.arange(300) * 500) // 300
    expected = []
    for T in poses:                                           # the straightforward pose-by-pose version
        moved = np.einsum("ab,nb->na", T[:3, :3], src[pick]) + T[:3, 3]
        dist, idx = cKDTree(ref_xyz).query(moved, k=4)
        expected.append(np.min(dist + np.abs(src_i[pick][:, None] - ref_i[idx]), axis=1).mean())
    np.testing.assert_allclose(correlation_scores(src, src_i, poses, ref, cfg), expected, rtol=1e-12)


@pytest.mark.parametrize("k", [3, 10])
def test_kmeans_matches_scipy_kmeans2(k):
    import warnings

    from scipy.cluster.vq import kmeans2

    from frontend.dynamic.cpr_icp import cluster

    rng = np.random.default_rng(7 + k)
    clouds = [rng.normal(size=(800, 3)),
              np.repeat(rng.normal(size=(40, 3)), 15, axis=0),        # duplicates: ties and empty clusters
              rng.uniform(0, 3, (3000, 3))]
    for xyz in clouds:
        for seed in range(3):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")                        # kmeans2 warns about empty clusters
                _, expected = kmeans2(xyz, k, iter=10, minit="++", seed=np.random.default_rng(seed),
                                      check_finite=False)
            np.testing.assert_array_equal(cluster(xyz, k, seed), expected)   # bit for bit


def test_projective_candidates_are_the_window_around_the_projection():
    """ProjectiveTarget.query against a per-point loop: distort the projection, take the nearest sample's grid
    cell, the (2r+1)^2 cells around it; missing samples (holes, off the grid) have no candidate (inf)."""
    from frontend.dynamic.cpr_assoc import ProjectiveGrid, ProjectiveTarget
    from slam.core.camera import PinholeCamera

    cam = PinholeCamera(540.0, 541.0, 318.0, 241.0, 640, 480, (0.04, -0.1, -0.0007, -0.0001, 0.0))
    step, r = 4, 1
    grid = ProjectiveGrid(cam, 480, 640, step, r)
    rng = np.random.default_rng(3)
    rows, cols = np.meshgrid(np.arange(2, 480, step), np.arange(2, 640, step), indexing="ij")
    pix = np.stack([rows.ravel(), cols.ravel()], axis=1)
    pix = pix[rng.random(len(pix)) > 0.2]                          # holes
    xyz, inten = rng.uniform(-1, 1, (len(pix), 3)), rng.random(len(pix))
    target = ProjectiveTarget(grid, pix, xyz, inten)
    cell_of = {(a // step, b // step): i for i, (a, b) in enumerate(pix)}
    p = np.column_stack([rng.uniform(-1.5, 1.5, 300), rng.uniform(-1.2, 1.2, 300), rng.uniform(0.5, 3, 300)])
    p[:5, 2] = -1.0                                                # behind the camera: no candidates
    dist, idx = target.query(p, 9)
    for n in range(len(p)):
        u, v = np.rint(cam.fx * p[n, 0] / p[n, 2] + cam.cx), np.rint(cam.fy * p[n, 1] / p[n, 2] + cam.cy)
        if p[n, 2] <= 0 or not (0 <= u < 640 and 0 <= v < 480):
            assert np.all(np.isinf(dist[n]))
            continue
        ru, rv = cv2.projectPoints(np.array([[(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0]]), np.zeros(3),
                                   np.zeros(3), cam.K, np.asarray(cam.distortion))[0][0, 0]
        if not (-0.5 < ru < 639.5 and -0.5 < rv < 479.5):
            assert np.all(np.isinf(dist[n]))
            continue
        gr = int(np.clip(np.rint((rv - 2) / step), 0, rows.shape[0] - 1))
        gc = int(np.clip(np.rint((ru - 2) / step), 0, rows.shape[1] - 1))
        expected = sorted(np.linalg.norm(xyz[cell_of[(gr + a, gc + b)]] - p[n])
                          for a in range(-r, r + 1) for b in range(-r, r + 1) if (gr + a, gc + b) in cell_of)
        got = np.sort(dist[n][np.isfinite(dist[n])])
        np.testing.assert_allclose(got, expected, rtol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(target.xyz[idx[n]] - p[n], axis=1)[np.isfinite(dist[n])],
                                   dist[n][np.isfinite(dist[n])], rtol=1e-12)
    near_dist, _ = target.query(p, 1)                               # k = 1: the window's nearest
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(near_dist[:, 0], dist.min(axis=1))


def _digest(out) -> str:
    """sha256 of a cpr output's mask and scores."""
    import hashlib

    return hashlib.sha256(np.ascontiguousarray(out.mask).tobytes() + np.asarray(out.info["scores"]).tobytes()).hexdigest()


def test_compiled_kernels_load_from_the_cache_in_a_new_process():
    """numba's on-disk cache is what every run after the first loads: two fresh processes (the second certainly
    loads what the first compiled or loaded) give this process's masks and scores. The cache once crashed a
    recursive kernel when loaded (a segfault, not an exception), which only a new process shows."""
    import subprocess
    import sys
    from pathlib import Path

    from frontend.dynamic.cpr import compile_kernels

    code = ("from frontend.dynamic.cpr import compile_kernels; from tests.test_cpr_vectorised import _digest; "
            "o = compile_kernels(); print(_digest(o), o.info['dynamic_clusters'])")
    here = compile_kernels()
    expected = (_digest(here), here.info["dynamic_clusters"])
    for _ in range(2):
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                             cwd=Path(__file__).resolve().parents[1])
        assert run.returncode == 0, run.stderr[-2000:]
        digest, clusters = run.stdout.split()
        assert (digest, int(clusters)) == expected
    assert expected[1] >= 1                                   # the moving block is found
