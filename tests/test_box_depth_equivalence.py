"""box_depth's faster formulations against the ones they replaced: the compiled frame-to-frame match
(frontend/dynamic/box_depth_kernels.py) and the ring of depths around a box (box_depth_segmentation), each the
same result, so the same trajectories."""
from __future__ import annotations

import numpy as np

from frontend.dynamic.box_depth import match_descriptors

H, W = 480, 640


def _match_by_sorting(desc_a, uv_a, desc_b, uv_b, radius=40.0, max_distance=50):
    """The numpy formulation the kernel replaced: per side, a stable argsort on (index, distance) keeps the
    first least-distance candidate in the k-d tree's order."""
    from scipy.spatial import cKDTree

    from slam.core.descriptors import hamming
    pairs = cKDTree(uv_a).sparse_distance_matrix(cKDTree(uv_b), radius, output_type="ndarray")
    ia, ib = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    ham = hamming(desc_a[ia], desc_b[ib])
    keep = ham <= max_distance
    ia, ib, ham = ia[keep], ib[keep], ham[keep]

    def first_per_group(groups):
        order = np.argsort(groups * (1 << 20) + ham, kind="stable")
        g = groups[order]
        return order[np.r_[True, g[1:] != g[:-1]]]
    ok = np.zeros(len(ia), bool)
    ok[first_per_group(ia)] = True
    ok_b = np.zeros(len(ia), bool)
    ok_b[first_per_group(ib)] = True
    ok &= ok_b
    return np.stack([ia[ok], ib[ok]], axis=1)


def test_match_descriptors_keeps_the_sorted_formulations_matches_and_order():
    """Many ties (descriptors from a few prototypes with a bit or two flipped): the compiled match gives the
    same rows in the same order as the sort-based formulation, so RANSAC's homography sees the same input."""
    rng = np.random.default_rng(3)
    protos = rng.integers(0, 256, (12, 32), dtype=np.uint8)

    def descriptors(n):
        d = protos[rng.integers(0, len(protos), n)].copy()
        flip = rng.integers(0, 32, n)
        d[np.arange(n), flip] ^= np.uint8(1) << rng.integers(0, 8, n).astype(np.uint8)
        return d
    for n_a, n_b in [(600, 650), (50, 900), (1, 3)]:
        uv_a = rng.uniform(0, [640, 480], (n_a, 2))
        uv_b = np.clip(uv_a[rng.integers(0, n_a, n_b)] + rng.normal(0, 15, (n_b, 2)), 0, [639, 479])
        da, db = descriptors(n_a), descriptors(n_b)
        got = match_descriptors(da, uv_a, db, uv_b)
        want = _match_by_sorting(da, uv_a, db, uv_b)
        assert got.shape == want.shape and np.array_equal(got, want)
        assert n_a < 10 or len(got) > 0.2 * n_a


def test_ring_depths_are_the_sampled_pixels_around_the_box():
    """The ring around a box as four strips holds the same sampled depths as the mask over the whole
    outer rectangle it replaced (order aside: the person layer only counts them), for boxes anywhere,
    touching the image's edges included."""
    from frontend.dynamic import box_depth_segmentation as seg

    rng = np.random.default_rng(0)
    depth = rng.uniform(0.0, 5.0, (H, W)).astype(np.float32)
    depth[rng.random((H, W)) < 0.2] = 0.0
    step = seg._LAYER_PIXEL_STEP
    boxes = [(0, 0, W, H), (0, 0, 1, 1), (W - 1, H - 1, W, H)]
    for _ in range(300):
        x0, y0 = int(rng.integers(0, W - 1)), int(rng.integers(0, H - 1))
        boxes.append((x0, y0, int(rng.integers(x0 + 1, W + 1)), int(rng.integers(y0 + 1, H + 1))))
    for x0, y0, x1, y1 in boxes:
        dx, dy = int(seg._RING_SHARE * (x1 - x0)) + 1, int(seg._RING_SHARE * (y1 - y0)) + 1
        X0, Y0, X1, Y1 = max(x0 - dx, 0), max(y0 - dy, 0), min(x1 + dx, W), min(y1 + dy, H)
        rr, cc = np.mgrid[Y0:Y1:step, X0:X1:step]
        outer = depth[Y0:Y1:step, X0:X1:step].astype(float)
        want = outer[~((rr >= y0) & (rr < y1) & (cc >= x0) & (cc < x1)) & (outer > 0)]
        got = seg._ring_depths((x0, y0, x1, y1), depth)
        assert np.array_equal(np.sort(got), np.sort(want)), (x0, y0, x1, y1)
