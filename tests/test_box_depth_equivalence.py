"""box_depth's faster formulations against the ones they replaced: the compiled frame-to-frame match
(frontend/dynamic/box_depth_kernels.py), the ring of depths around a box, the person layer's histogram and band
counts, and the flood fill's prepared crop (box_depth_segmentation), each the same result, so the same
trajectories."""
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


def _reference_person_layer(box, depth):
    """``person_layer`` as it was before its counts were compiled: numpy's histogram and a count per peak."""
    from frontend.dynamic import box_depth_segmentation as seg

    x0, y0, x1, y1 = box
    if x1 <= x0 or y1 <= y0:
        return None
    inside = depth[y0:y1:seg._LAYER_PIXEL_STEP, x0:x1:seg._LAYER_PIXEL_STEP].astype(float)
    inside = inside[inside > 0]
    if len(inside) < 20:
        return None
    ring = seg._ring_depths(box, depth)
    bin_m = seg._LAYER_BIN_M
    hist, edges = np.histogram(inside, np.arange(bin_m * np.floor(inside.min() / bin_m) - bin_m,
                                                 inside.max() + 2 * bin_m, bin_m))
    smooth = np.convolve(hist, np.ones(3) / 3, mode="same")
    peak = (smooth[1:-1] >= smooth[:-2]) & (smooth[1:-1] > smooth[2:]) & (smooth[1:-1] > 0)
    best, best_score = None, -1.0
    for k in np.flatnonzero(peak) + 1:
        centre = 0.5 * (edges[k] + edges[k + 1])
        held = np.count_nonzero(np.abs(inside - centre) <= seg._LAYER_HALF_M)
        if held < seg._LAYER_MIN_SHARE * len(inside):
            continue
        near = seg._LAYER_HALF_M + seg._LAYER_RING_SLACK_M
        beyond = np.count_nonzero(np.abs(ring - centre) <= near) if len(ring) else 0
        score = held / (held + beyond * len(inside) / max(len(ring), 1))
        if score > best_score:
            best, best_score = float(centre), score
    return best


def test_histogram_counts_are_numpys_histogram():
    """Values on the edges (each bin's left edge counts, the last bin's right edge too), outside them, NaN."""
    from frontend.dynamic.box_depth_kernels import histogram_counts

    rng = np.random.default_rng(4)
    for trial in range(200):
        edges = np.arange(-0.1 + 0.05 * int(rng.integers(0, 20)), 3.0 + rng.random(), 0.05)
        values = np.concatenate([rng.uniform(edges[0] - 0.2, edges[-1] + 0.2, 300),
                                 rng.choice(edges, 40), [np.nan] * (trial % 2)])
        expected = np.histogram(values[np.isfinite(values)], edges)[0]
        for guess in (0.05, 0.03, 0.11):        # the step only guesses the bin: any guess, the same counts
            assert np.array_equal(histogram_counts(values, edges, guess), expected), trial
    assert len(histogram_counts(np.ones(3), np.array([1.0]), 0.05)) == 0


def test_band_counts_are_numpys_counts_at_the_band_edges():
    from frontend.dynamic.box_depth_kernels import band_counts

    rng = np.random.default_rng(7)
    for centres, half in [(0.5 * (np.arange(0.55, 4.0, 0.05)[:-1] + np.arange(0.55, 4.0, 0.05)[1:]), 0.2),
                          (np.arange(0.5, 4.0, 0.125), 0.25)]:      # dyadic: values exactly on the band's edges
        edges = np.concatenate([centres + half, centres - half, np.nextafter(centres + half, 0), centres])
        values = np.concatenate([edges, rng.uniform(0.3, 4.5, 500), [np.nan]])
        on_edge = 0
        for k in range(len(centres)):
            want = np.count_nonzero(np.abs(values - centres[k]) <= half)
            assert band_counts(values, centres[k:k + 1], half)[0] == want
            on_edge += np.count_nonzero(np.abs(values - centres[k]) == half)
        assert np.array_equal(band_counts(values, centres, half),
                              [np.count_nonzero(np.abs(values - c) <= half) for c in centres])
    assert on_edge > 10                     # the band's edge itself is tested


def test_person_layers_are_the_numpy_formulations():
    """Depth images of a few layers with depth quantised to half the histogram's 5 cm bins (values on its edges
    and on its bins' centres +- the layer's half width: ties of every comparison), boxes anywhere: the same
    layer, to the bit."""
    from frontend.dynamic.box_depth_segmentation import person_layer

    rng = np.random.default_rng(5)
    found = 0
    for trial in range(60):
        layers = rng.choice(np.arange(0.6, 4.0, 0.025), int(rng.integers(1, 5)))
        depth = layers[rng.integers(0, len(layers), (H // 8, W // 8))].repeat(8, 0).repeat(8, 1)
        depth = depth + np.where(rng.random((H, W)) < 0.5, 0.0, rng.normal(0, 0.04, (H, W)))
        depth[rng.random((H, W)) < 0.1] = 0.0
        depth = depth.astype(np.float32 if trial % 2 else np.float64)
        for _ in range(10):
            x0, y0 = int(rng.integers(0, W - 1)), int(rng.integers(0, H - 1))
            box = (x0, y0, int(rng.integers(x0 + 1, W + 1)), int(rng.integers(y0 + 1, H + 1)))
            want = _reference_person_layer(box, depth)
            assert person_layer(box, depth) == want, (trial, box)
            found += want is not None
    assert found > 300


def _reference_flood_fill(depth, seeds, omega, max_components=64):
    """``flood_fill`` as it was before the crop was prepared once per box (numpy's masks per fill)."""
    import cv2

    from frontend.dynamic.box_depth_segmentation import _FILL_FLAGS
    img = np.ascontiguousarray(depth, dtype=np.float32)
    h, w = img.shape
    mask = np.zeros((h + 2, w + 2), np.uint8)
    inner = mask[1:-1, 1:-1]
    inner[~(np.isfinite(img) & (img > 0))] = 1
    img = np.where(inner == 1, np.float32(0), img)
    seeds = np.asarray(seeds, dtype=np.int64).reshape(-1, 2)
    if len(seeds):
        seeds = seeds[(seeds[:, 0] >= 0) & (seeds[:, 0] < h) & (seeds[:, 1] >= 0) & (seeds[:, 1] < w)]
    diff = float(np.nextafter(np.float32(omega), np.float32(0)))
    for _ in range(max_components):
        if not len(seeds):
            break
        seeds = seeds[inner[seeds[:, 0], seeds[:, 1]] == 0]
        if not len(seeds):
            break
        r, c = int(seeds[0, 0]), int(seeds[0, 1])
        cv2.floodFill(img, mask, (c, r), 0, diff, diff, _FILL_FLAGS)
    return inner == 255


def test_fills_of_a_prepared_crop_are_the_fills_of_the_crop():
    """One ``DepthFill`` per crop, filled from several seed sets in turn (as Algorithm 1 tries its seeds): each
    fill the same pixels as a fill prepared anew, on strided float32 / float64 crops with NaN, inf, zero and
    negative depth, and steps of exactly omega (the paper's strict test)."""
    from frontend.dynamic.box_depth_segmentation import DepthFill

    rng = np.random.default_rng(6)
    for trial in range(40):
        full = (1.0 + 0.05 * rng.integers(0, 4, (120, 160))).astype(np.float64 if trial % 2 else np.float32)
        full[rng.random(full.shape) < 0.05] = rng.choice([0.0, np.nan, np.inf, -1.0])
        crop = full[10:110:1 + trial % 2, 5:150]
        fills = DepthFill(crop)
        for _ in range(4):
            seeds = np.stack([rng.integers(-5, crop.shape[0] + 5, 3), rng.integers(-5, crop.shape[1] + 5, 3)], 1)
            got = fills.fill(seeds, 0.05)
            assert np.array_equal(got, _reference_flood_fill(crop, seeds, 0.05)), trial


def _reference_composite(img, uv, skip_zero=False):
    """``box_depth.composite`` as it was before it was compiled (numpy's fancy indexing and row sums)."""
    h, w = img.shape[:2]
    if not len(uv):
        return np.zeros(0)
    with np.errstate(invalid="ignore"):
        cols = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
        rows = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    dr, dc = np.meshgrid(np.arange(-1, 2), np.arange(-1, 2), indexing="ij")
    ring = (dr != 0) | (dc != 0)
    nr = np.clip(rows[:, None] + dr[ring][None, :], 0, h - 1)
    nc = np.clip(cols[:, None] + dc[ring][None, :], 0, w - 1)
    centre = img[rows, cols].astype(float)
    neigh = img[nr, nc].astype(float)
    if skip_zero:
        ok = neigh > 0
        cnt = ok.sum(axis=1)
        with np.errstate(invalid="ignore"):
            mean = np.where(cnt > 0, (neigh * ok).sum(axis=1) / np.maximum(cnt, 1), centre)
        out = (centre + mean) / 2.0
        out[~(centre > 0)] = np.nan
        return out
    return (centre + neigh.mean(axis=1)) / 2.0


def test_composites_are_the_numpy_formulations():
    """Grey (uint8), depth (float32 with zeros, NaN and negative values; float64 too, where the order of the
    neighbours' sum shows in the bits), points at and beyond the image's
    border, half-pixel ties of the rounding, NaN, infinite and huge coordinates (a degenerate homography's):
    the same values to the bit (NaN where numpy gives NaN)."""
    from frontend.dynamic.box_depth import composite

    rng = np.random.default_rng(8)
    for trial in range(30):
        h, w = int(rng.integers(1, 60)), int(rng.integers(1, 80))
        gray = rng.integers(0, 256, (h, w), dtype=np.uint8)
        depth = (rng.uniform(0.3, 5.0, (h, w)) * 10 ** rng.uniform(-2, 2, (h, w))).astype(np.float32)
        depth[rng.random((h, w)) < 0.3] = rng.choice([0.0, np.nan, -1.0])
        uv = np.stack([rng.uniform(-3, w + 3, 200), rng.uniform(-3, h + 3, 200)], 1)
        uv[:40] = np.round(uv[:40]) + 0.5                                     # rounding ties (to even)
        uv[40:50] = rng.choice([np.nan, np.inf, -np.inf, 1e30, -1e30], (10, 2))
        uv = uv.astype(np.float32 if trial % 3 == 0 else np.float64)
        full = depth.astype(np.float64) * rng.uniform(0.5, 2.0, (h, w))      # float64: the sums' order shows
        for img in (gray, depth, full):
            for skip_zero in (False, True):
                got, want = composite(img, uv, skip_zero), _reference_composite(img, uv, skip_zero)
                assert np.array_equal(got, want, equal_nan=True), (trial, img.dtype, skip_zero)
    assert len(composite(gray, np.zeros((0, 2)))) == 0
