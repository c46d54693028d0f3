"""The compiled loops of the keyframe-mask path (fusion of whole masks, the free-space test's projection and
growth, the near-occluder's splat, depth_sdf's bands, box_depth's Eq. 8, the masks' PNG values) against the whole-array numpy code they replaced, kept here as the
reference: the same bits on inputs full of the cases that decide them (NaN and out-of-range probabilities,
cells without depth, depth ties in a splat, points behind the camera or outside the grid)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from types import SimpleNamespace

from frontend.dynamic import free_space, near_occluder
from frontend.dynamic.box_depth_segmentation import _LAYER_HALF_M, ALL_SIDES, eq8_filter, side_distance
from frontend.dynamic.depth_sdf import DepthSdfMethod
from frontend.dynamic.fusion import fuse, fuse_masks
from slam.core.camera import PinholeCamera
from slam.run.run_artifacts import mask_to_png
from slam.core.geometry import se3_exp

CAMERA = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)


# --- references: the numpy formulations before the kernels ------------------------------------------------

def reference_grow(moving: np.ndarray, depth: np.ndarray, tolerance: np.ndarray, steps: int) -> np.ndarray:
    grown = moving.copy()
    h, w = grown.shape
    padded_depth = np.pad(depth, 1, constant_values=np.nan)
    for _ in range(steps):
        padded = np.pad(grown, 1)
        added = np.zeros_like(grown)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:
                    near = padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                    near_depth = padded_depth[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                    with np.errstate(invalid="ignore"):
                        added |= near & (np.abs(depth - near_depth) <= tolerance)
        added &= ~grown
        if not added.any():
            break
        grown |= added
    return grown


def reference_compare(p: np.ndarray, depth: np.ndarray, nearest: np.ndarray, margin_m: float):
    gh, gw = depth.shape
    step, far = free_space._STEP, free_space._FAR
    front = p[:, 2] > 1e-6
    zr = np.where(front, p[:, 2], 1.0)
    col = np.rint((CAMERA.fx * p[:, 0] / zr + CAMERA.cx) / step).astype(np.int64)
    row = np.rint((CAMERA.fy * p[:, 1] / zr + CAMERA.cy) / step).astype(np.int64)
    inside = front & (col >= 0) & (col < gw) & (row >= 0) & (row < gh)
    seen = np.full(len(p), far, np.float32)
    near = np.full(len(p), far, np.float32)
    seen[inside] = depth[row[inside], col[inside]]
    near[inside] = nearest[row[inside], col[inside]]
    margin = margin_m + 3.0 * free_space._NOISE_COEFF * seen.astype(float) ** 2
    known = inside & (seen < far) & (p[:, 2] <= seen + margin)
    return known, known & (p[:, 2] < near - margin)


def reference_paint(mask, depth, det, model) -> None:
    """depth_sdf's band of one model, painted with numpy (a Python float against the image: NEP 50)."""
    if model["inliers"] == 0 or model["half_width"] <= 0:
        return
    h, w = mask.shape
    x0, y0 = int(max(0, np.floor(det.x0))), int(max(0, np.floor(det.y0)))
    x1, y1 = int(min(w, np.ceil(det.x1))), int(min(h, np.ceil(det.y1)))
    if x1 <= x0 or y1 <= y0:
        return
    crop = depth[y0:y1, x0:x1]
    mask[y0:y1, x0:x1] |= (crop > 0) & (np.abs(crop - model["mu"]) < model["half_width"])


def reference_eq8(region, depth, alpha, omega, sides=ALL_SIDES, layer=None) -> np.ndarray:
    """box_depth's Eq. 8 with whole-array steps (a Python float against the image: NEP 50)."""
    if not region.any():
        return region
    d_ave = float(depth[region].mean())
    deficit = alpha * d_ave - depth
    keep = deficit + omega * side_distance(*depth.shape) >= 0.0
    if layer is not None and not all(sides):
        on_body = np.abs(depth - np.float32(layer)) <= _LAYER_HALF_M
        keep |= on_body & (deficit + omega * side_distance(*depth.shape, sides) >= 0.0)
    return region & keep


def reference_splat(prev_depth, prev_gray, prev_T_cw, T_cw, keep):
    scale = near_occluder._SCALE
    z = prev_depth.ravel()
    valid = z > 0
    rows, cols = np.divmod(np.flatnonzero(valid), prev_depth.shape[1])
    uv = np.stack([cols * scale + scale // 2, rows * scale + scale // 2], 1)
    z = z[valid].astype(np.float64)
    cam = CAMERA
    xyz = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], 1)
    rel = T_cw @ np.linalg.inv(prev_T_cw)
    p = xyz @ rel[:3, :3].T + rel[:3, 3]
    front = p[:, 2] > 0.1
    p, g = p[front], prev_gray.ravel()[valid][front]
    u = np.floor((cam.fx * p[:, 0] / p[:, 2] + cam.cx) / scale).astype(np.int64)
    v = np.floor((cam.fy * p[:, 1] / p[:, 2] + cam.cy) / scale).astype(np.int64)
    h, w = keep.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    inside[inside] = keep[v[inside], u[inside]]
    cell, zc, g = v[inside] * w + u[inside], p[inside, 2], g[inside]
    if not len(cell):
        return np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    order = np.lexsort((zc, cell))
    cell, zc, g = cell[order], zc[order], g[order]
    first = np.r_[True, cell[1:] != cell[:-1]]
    depth_out = np.zeros(h * w, np.float32)
    gray_out = np.zeros(h * w, np.float32)
    depth_out[cell[first]], gray_out[cell[first]] = zc[first], g[first]
    depth_img = depth_out.reshape(h, w)
    kernel = np.ones((3, 3), np.uint8)
    landed = (depth_img > 0).astype(np.uint8)
    gaps = (cv2.morphologyEx(landed, cv2.MORPH_CLOSE, kernel) > 0) & (landed == 0)
    filled = cv2.dilate(depth_img, kernel)
    gray_img = gray_out.reshape(h, w)
    gray_img[gaps] = cv2.dilate(gray_img, kernel)[gaps]
    depth_img[gaps] = filled[gaps]
    return depth_img, gray_img


# --- inputs --------------------------------------------------------------------------------------------------

def _probability_masks(rng, k: int, n: int) -> list[np.ndarray]:
    """k float32 masks of n pixels: probabilities, abstentions (NaN), and values a method should not give
    but the fusion clips (below 0, above 1, infinities)."""
    masks = []
    for _ in range(k):
        kind = rng.integers(0, 4, n)
        odd = rng.choice([0.0, 1.0, -0.5, 1.5, np.inf, -np.inf, 0.45, 0.9], n)
        masks.append(np.select([kind == 0, kind == 1, kind == 2], [rng.random(n), np.nan, odd],
                               rng.random(n) * 3 - 1).astype(np.float32))
    return masks


def _layered_depth(rng, shape) -> np.ndarray:
    """Depth in a few layers with noise and holes (NaN), so neighbours lie both within and beyond a margin."""
    depth = rng.choice([0.8, 0.85, 1.0, 1.05, 1.3, 2.0], size=shape) + rng.normal(0, 0.03, shape)
    depth[rng.random(shape) < 0.1] = np.nan
    return depth


# --- tests ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(6))
def test_fused_masks_are_the_keypoint_fusions_bits(seed):
    rng = np.random.default_rng(seed)
    for k in (1, 2, 3, 4):
        masks = _probability_masks(rng, k, 4000)
        weights = list(rng.choice([0.2, 0.45, 1.0, 0.75, 1.3, -0.1], size=k))
        expected = fuse([m.reshape(1, -1) for m in masks], weights, "noisy_or", 4000).astype(np.float32)
        assert fuse_masks(masks, weights, "noisy_or").tobytes() == expected.tobytes()
        expected_max = fuse([m.reshape(1, -1) for m in masks], weights, "max", 4000).astype(np.float32)
        assert fuse_masks(masks, weights, "max").tobytes() == expected_max.tobytes()


@pytest.mark.parametrize("seed", range(6))
def test_growth_along_surfaces_is_the_shifted_comparisons(seed):
    rng = np.random.default_rng(seed)
    check = free_space.FreeSpaceCheck(CAMERA, (0.5, 1.0), 0.1, 20)
    for _ in range(20):
        shape = (int(rng.integers(1, 40)), int(rng.integers(1, 40)))
        depth = _layered_depth(rng, shape)
        moving = rng.random(shape) < rng.choice([0.0, 0.02, 0.1, 0.5])
        tolerance = check._margin(np.nan_to_num(depth, nan=0.0))
        grown = check._grow_along_surfaces(moving, depth)
        assert np.array_equal(grown, reference_grow(moving, depth, tolerance, free_space._GROW_CELLS))
    # one cell grows along a ramp within the margin, and stops at a step and at a hole
    depth = np.array([[1.0, 1.05, 1.1, 2.0, 2.0, np.nan, 1.0]])
    grown = check._grow_along_surfaces(np.array([[True, False, False, False, False, False, False]]), depth)
    assert grown.tolist() == [[True, True, True, False, False, False, False]]


@pytest.mark.parametrize("seed", range(4))
def test_the_free_space_projection_is_the_whole_array_test(seed):
    rng = np.random.default_rng(seed)
    check = free_space.FreeSpaceCheck(CAMERA, (0.5, 1.0), 0.1, 20)
    for trial in range(6):
        depth = (rng.choice([0.6, 1.0, 2.5, 4.0], size=(480, 640)) + rng.normal(0, 0.05, (480, 640))).astype(np.float32)
        depth[rng.random((480, 640)) < 0.1] = 0
        earlier = depth.copy()
        earlier[50:250, 100:500] += np.float32(rng.choice([0.3, 1.0]))     # seen through: the box moved in
        T_earlier = se3_exp(rng.normal(0, 0.05, 6))
        T_key = T_earlier if trial % 2 else se3_exp(rng.normal(0, 0.3, 6)) @ T_earlier   # some points leave
        check.reset()
        check.remember(0.0, earlier, T_earlier)
        check.keyframe(("key",), 0.6, depth, T_key)
        record, reference = check._pending[-1], check._frames[-1]
        known, moving = check._test(record, reference)
        p = record.world @ reference.T_cw[:3, :3].T + reference.T_cw[:3, 3]
        ref_known, ref_moving = reference_compare(p, reference.depth, reference.nearest, check.margin_m)
        assert np.array_equal(known, ref_known) and np.array_equal(moving, ref_moving)
        if trial == 1:
            assert moving.any() and (known & ~moving).any()      # the same pose: the box moved in, the rest not


@pytest.mark.parametrize("seed", range(4))
def test_the_near_occluders_splat_is_the_sorted_z_buffer(seed):
    rng = np.random.default_rng(seed)
    h, w = 120, 160
    for trial in range(8):
        prev_depth = rng.choice([0.0, 0.7, 1.0, 2.0, 3.5], size=(h, w)).astype(np.float32)
        if trial % 2:       # planes: many points land on one cell at the same depth (ties in the z-buffer)
            prev_depth = np.where(prev_depth > 0, np.float32(2.0), np.float32(0.0))
        prev_gray = rng.integers(0, 256, (h, w), dtype=np.uint8)
        prev_T = se3_exp(rng.normal(0, 0.1, 6))
        T = se3_exp(rng.normal(0, 0.05 if trial < 6 else 0.6, 6)) @ prev_T      # the last ones turn far
        if trial % 2:       # straight back from the plane: the view shrinks, cells get several equal depths
            back = np.eye(4)
            back[2, 3] = 0.5
            T = back @ prev_T
        keep = rng.random((h, w)) < rng.choice([0.3, 1.0])
        occluder = near_occluder.NearOccluder(CAMERA)
        occluder._prev = (prev_depth, prev_gray, prev_T)
        depth, gray = occluder._warp_previous(T, keep)
        ref_depth, ref_gray = reference_splat(prev_depth, prev_gray, prev_T, T, keep)
        assert depth.tobytes() == ref_depth.tobytes() and gray.tobytes() == ref_gray.tobytes()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_sdf_bands_are_the_per_model_union(dtype):
    rng = np.random.default_rng(0)
    for trial in range(100):
        depth = (rng.choice([0.0, 1.0, 1.5, 2.0], size=(60, 80)) + rng.normal(0, 0.2, (60, 80))).astype(dtype)
        depth[rng.random((60, 80)) < 0.05] = np.nan
        x0, y0 = rng.uniform(-10, 70), rng.uniform(-10, 50)
        det = SimpleNamespace(x0=x0, y0=y0, x1=x0 + rng.uniform(0, 60), y1=y0 + rng.uniform(0, 40))
        models = []
        for _ in range(int(rng.integers(0, 25))):
            mu = float(rng.choice([1.0, 1.5, 2.0]) + rng.normal(0, 0.1))
            half_width = float(abs(rng.normal(0, 0.2)) * rng.integers(0, 2))
            if rng.random() < 0.3:      # a band edge exactly at a pixel's depth: the precision decides
                d = float(depth[int(rng.integers(0, 60)), int(rng.integers(0, 80))])
                half_width = abs(d - mu) if np.isfinite(d) else half_width
            models.append(dict(mu=mu, half_width=half_width, inliers=int(rng.integers(0, 3))))
        expected, painted = np.zeros((60, 80), bool), np.zeros((60, 80), bool)
        for model in models:
            reference_paint(expected, depth, det, model)
        DepthSdfMethod._paint(painted, depth, det, models)
        assert np.array_equal(painted, expected), trial
    # a model whose centre float32 cannot hold: numpy compares in the image's precision (NEP 50), so a float32
    # pixel 1.19e-7 above 1.0 lies outside a 1e-7 band around 1.00000005 (rounded to 1.0), a float64 one inside
    depth = np.full((4, 4), np.nextafter(np.float32(1.0), np.float32(2.0)), dtype)
    det = SimpleNamespace(x0=0.0, y0=0.0, x1=4.0, y1=4.0)
    model = dict(mu=1.00000005, half_width=1e-7, inliers=1)
    expected, painted = np.zeros((4, 4), bool), np.zeros((4, 4), bool)
    reference_paint(expected, depth, det, model)
    DepthSdfMethod._paint(painted, depth, det, [model])
    assert np.array_equal(painted, expected) and expected.all() == (dtype == np.float64)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, bool])
def test_masks_become_the_same_pngs(dtype):
    """``masks/`` PNGs: NaN 0, clipped, times 255 and rounded half to even in the mask's precision."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        mask = rng.random((48, 64))
        for value, share in ((np.nan, 0.1), (np.inf, 0.05), (-np.inf, 0.05), (-0.5, 0.05), (1.5, 0.05), (-0.0, 0.05)):
            mask[rng.random(mask.shape) < share] = value
        halfway = (rng.integers(0, 255, mask.shape) + 0.5) / 255          # x.5 after the scaling: ties
        mask = np.where(rng.random(mask.shape) < 0.2, halfway, mask).astype(dtype)
        expected = np.round(np.clip(np.nan_to_num(mask, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
        assert np.array_equal(mask_to_png(mask), expected)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_eq8_is_the_whole_array_filter(dtype):
    rng = np.random.default_rng(2)
    trimmed = 0
    for trial in range(150):
        h, w = int(rng.integers(1, 120)), int(rng.integers(1, 90))
        depth = (rng.choice([0.0, 1.0, 1.2, 2.5], size=(h, w)) + rng.normal(0, 0.3, (h, w))).astype(dtype)
        region = rng.random((h, w)) < rng.random()
        sides = tuple(bool(x) for x in rng.integers(0, 2, 4))          # a box cut by the image's border
        layer = None if trial % 3 == 0 else float(rng.choice([1.0, 1.2, 2.5]) + rng.normal(0, 0.05))
        alpha, omega = float(rng.choice([1.0, 0.8, 1.2])), float(rng.choice([0.01, 0.02]))
        expected = reference_eq8(region, depth, alpha, omega, sides, layer)
        assert np.array_equal(eq8_filter(region, depth, alpha, omega, sides, layer), expected), trial
        trimmed += int(expected.sum() < region.sum())
    assert trimmed > 50                     # the cases remove pixels, the test decides something
