"""Bounding box + depth continuity (Fang et al. 2021) on small synthetic RGB-D frames."""
from __future__ import annotations

import numpy as np
import pytest

from frontend.dynamic.base import Detection, DynamicContext
from frontend.dynamic.box_depth import (BoxDepthMethod, eq8_filter, flood_fill, match_descriptors, seed_points,
                                        segment_box)
from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import BoxDepthConfig, ClassGroups
from slam.core.frame import FeatureFrame

CAM = PinholeCamera(525, 525, 319.5, 239.5, 640, 480)
H, W = 480, 640
PERSON, CHAIR = 0, 56


def make_frame(uv, depth, index=0, desc=None, seed=0) -> FeatureFrame:
    uv = np.asarray(uv, float).reshape(-1, 2)
    n = len(uv)
    if desc is None:
        desc = np.random.default_rng(seed).integers(0, 256, (n, 32), dtype=np.uint8)
    cols = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
    rows = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
    d = depth[rows, cols].astype(float)
    u_right = np.where(d > 0, uv[:, 0] - CAM.bf / np.maximum(d, 1e-9), np.nan)
    return FeatureFrame(index, float(index), uv, uv.copy(), np.zeros(n, int), desc, d, u_right,
                        np.zeros(n), np.array([1.0]))


def make_ctx(frame, depth, detections, gray=None) -> DynamicContext:
    gray = np.full((H, W), 128, np.uint8) if gray is None else gray
    rgb = np.repeat(gray[:, :, None], 3, axis=2)
    return DynamicContext(frame, rgb, gray, depth.astype(np.float32), CAM, detections)


def person_scene(ramp: bool = False):
    """Background wall at 4 m; a person (torso + head + legs) at ~2 m inside the box (200..300, 60..420)."""
    depth = np.full((H, W), 4.0, np.float32)
    person = np.zeros((H, W), bool)
    person[70:100, 235:265] = True           # head
    person[100:280, 210:290] = True          # torso
    person[280:415, 215:245] = True          # legs
    person[280:415, 255:285] = True
    depth[person] = 2.0
    if ramp:
        # The body leans: 1.8 m at the head to 2.3 m at the feet, far more than omega_pixel overall,
        # but only ~1.5 mm between neighbouring rows.
        rows = np.arange(H, dtype=np.float32)[:, None] * np.ones((1, W), np.float32)
        depth[person] = (1.8 + 0.5 * (rows[person] - 70) / 345.0).astype(np.float32)
    box = Detection(200, 60, 300, 420, PERSON, 0.9)
    return depth, person, box


# ----------------------------------------------------------------------------------------------
# Algorithm 1


def test_seed_order_centre_then_half_axes():
    assert seed_points(100, 40) == [(50, 20), (25, 20), (75, 20), (50, 10), (50, 30)]


def test_flood_fill_stops_at_depth_edge():
    depth, person, box = person_scene()
    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    on_person = [(250, 150), (230, 250), (260, 90), (230, 350), (270, 400)]
    bg_in_box = [(205, 70), (295, 350), (250, 350), (205, 410)]
    outside = [(100, 100), (500, 300), (400, 50)]
    frame = make_frame(on_person + bg_in_box + outside, depth)
    out = method.process(make_ctx(frame, depth, [box]))
    mask = out.mask > 0
    assert mask[person].mean() > 0.97
    box_bg = np.zeros((H, W), bool)
    box_bg[60:420, 200:300] = True
    box_bg &= ~person
    assert mask[box_bg].mean() < 0.01
    assert not mask[:, :195].any() and not mask[:, 305:].any()
    np.testing.assert_array_equal(out.prob, [1] * 5 + [0] * 4 + [0] * 3)
    assert out.info["fallback"] == 0


def test_flood_fill_is_neighbour_to_neighbour():
    """A 0.5 m ramp is crossed in small steps (seed-relative filling would stop after 5 cm)."""
    depth, person, _ = person_scene(ramp=True)
    crop = depth[60:420, 200:300]
    region = flood_fill(crop, np.array([[90, 50]]), 0.05)
    assert region[person[60:420, 200:300]].all()
    assert not region[~person[60:420, 200:300]].any()


def test_invalid_depth_blocks_the_fill_and_holes_join_the_segment():
    depth, person, box = person_scene()
    depth[100:103, 200:300] = 0.0            # a band without depth across the neck
    depth[200:204, 240:244] = 0.0            # a hole (dark clothes), 4 x 4 px
    crop = depth[60:420, 200:300]
    region = flood_fill(crop, np.array([[180, 50]]), 0.05)
    assert not region[:43].any()             # the fill cannot jump the invalid band to the head
    assert not region[140:144, 40:44].any()  # nor enter the hole
    seg, accepted = segment_box(crop, BoxDepthConfig())
    assert accepted == 0
    assert seg[140:144, 40:44].all()         # the hole joins the segment (within invalid_fill_px)
    assert seg[41:43, 10:90].all()           # so do the band rows next to the torso
    assert not seg[:40].any()                # the head, beyond the band, stays out


def test_seed_on_invalid_depth_moves_to_a_valid_neighbour():
    depth, person, box = person_scene()
    depth[238:243, 248:253] = 0.0            # the centre seed pixel (row 240, col 250) has no depth
    seg, accepted = segment_box(depth[60:420, 200:300], BoxDepthConfig())
    assert accepted == 0 and seg[person[60:420, 200:300]].mean() > 0.97


def test_height_check_rejects_small_object_and_uses_next_seed():
    depth, person, box = person_scene()
    # A small object held in front of the person exactly at the box centre (row 240, col 250).
    obj = np.zeros((H, W), bool)
    obj[225:256, 235:266] = True
    depth[obj] = 1.0
    crop = depth[60:420, 200:300]
    seg, accepted = segment_box(crop, BoxDepthConfig())
    assert accepted == 1                      # the centre fill spans 31 rows < 0.75 * 360: next seed
    full = np.zeros((H, W), bool)
    full[60:420, 200:300] = seg
    assert full[person & ~obj].mean() > 0.97
    assert not full[obj].any()

    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    frame = make_frame([(250, 240), (240, 230), (250, 150)], depth)
    out = method.process(make_ctx(frame, depth, [box]))
    np.testing.assert_array_equal(out.prob, [0, 0, 1])


def test_no_valid_seed_keeps_the_largest_fill():
    # Horizontal depth bands 40 rows high, 0.5 m apart: no fill can span 0.75 of the box height.
    rows = np.arange(H)[:, None] * np.ones((1, W))
    depth = (3.0 + 0.5 * ((rows // 40) % 2)).astype(np.float32)
    seg, accepted = segment_box(depth[60:420, 200:300], BoxDepthConfig())
    assert accepted == -1
    spans = seg.any(axis=1).nonzero()[0]
    assert 30 <= spans[-1] - spans[0] < 40   # one band (the largest-span fill), not the box


def test_eq8_removes_deep_pixels_near_the_box_sides_only():
    h, w = 200, 200
    depth = np.full((h, w), 2.0, np.float32)
    depth[:, :5] = 2.3                        # deeper strip along the left side  (G < 5 px)
    depth[95:105, 95:105] = 2.3               # equally deep blob at the box centre (G ~ 100 px)
    depth[:, -5:] = 1.7                       # nearer strip along the right side
    region = np.ones((h, w), bool)
    kept = eq8_filter(region, depth, alpha=1.0, omega=0.01)
    assert not kept[:, :5].any()              # D + w*G = 2.0x - 2.3 + 0.01*G < 0
    assert kept[95:105, 95:105].all()          # far from the sides the same depth step is tolerated
    assert kept[:, -5:].all()                  # nearer than the mean: D > 0, never removed
    assert kept[10:190, 10:190].all()


def test_eq8_trims_a_fill_that_overflowed_along_a_slanted_surface():
    depth, person, box = person_scene()
    # A slanted surface touching the person's right side (like a wall going away from the camera):
    # 2.0 m at the body, 2.4 m at the box side, continuous in depth so the flood fill follows it.
    cols = np.arange(290, 300)
    depth[100:280, 290:300] = (2.0 + 0.04 * (cols - 289))[None, :]
    crop = depth[60:420, 200:300]
    raw = flood_fill(crop, np.array([[180, 50]]), 0.05)
    assert raw[100 - 60:280 - 60, 90:100].all()                 # the fill overflowed into it
    seg, _ = segment_box(crop, BoxDepthConfig())
    assert not seg[100 - 60:280 - 60, 96:100].any()              # the deep pixels at the side go
    assert seg[person[60:420, 200:300]].mean() > 0.97            # the person stays


# ----------------------------------------------------------------------------------------------
# Algorithm 2


def chair_scene(chair_depth: float):
    depth, person, box = person_scene()
    chair = np.zeros((H, W), bool)
    chair[250:400, 290:350] = True            # touches the torso at column 290
    depth[chair] = chair_depth
    chair_box = Detection(270, 245, 360, 405, CHAIR, 0.8)
    return depth, person, box, chair, chair_box


def test_dragged_chair_connected_in_depth_is_dynamic():
    # 8 cm from the torso: beyond omega_pixel (the person stays separate) but within the passive 10 cm.
    depth, person, box, chair, chair_box = chair_scene(2.08)
    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    frame = make_frame([(320, 300), (340, 380), (250, 150), (500, 300)], depth)
    out = method.process(make_ctx(frame, depth, [box, chair_box]))
    assert out.info["dragged"] == 1
    assert (out.prob[:2] >= 0.5).all()
    assert out.prob[2] == 1.0 and out.prob[3] == 0.0
    mask = out.mask > 0
    assert mask[chair].mean() > 0.9


def test_distant_chair_is_not_dragged():
    depth, person, box, chair, chair_box = chair_scene(3.0)
    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    frame = make_frame([(320, 300), (340, 380), (250, 150)], depth)
    out = method.process(make_ctx(frame, depth, [box, chair_box]))
    assert out.info["dragged"] == 0
    np.testing.assert_array_equal(out.prob, [0, 0, 1])


def test_passive_box_needs_enough_overlap():
    depth, person, box, chair, _ = chair_scene(2.08)
    # Same chair pixels but a box that barely overlaps the person box: A_pas / A_int > K * p_pas.
    far_box = Detection(298, 245, 420, 405, CHAIR, 0.8)
    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    out = method.process(make_ctx(make_frame([(320, 300)], depth), depth, [box, far_box]))
    assert out.info["dragged"] == 0 and out.prob[0] == 0.0


# ----------------------------------------------------------------------------------------------
# Algorithm 3


def test_still_part_of_a_person_is_reused_moving_part_is_not():
    rng = np.random.default_rng(3)
    shift = np.array([5.0, 3.0])              # camera motion: the whole static scene moves by this
    n_bg, n_still, n_move = 40, 6, 6
    desc = rng.integers(0, 256, (n_bg + n_still + n_move, 32), dtype=np.uint8)
    bg = np.column_stack([rng.integers(20, 180, n_bg), rng.integers(20, 460, n_bg)]).astype(float)
    bg[n_bg // 2:, 0] += 400                  # left and right of the person
    still = np.array([[225, 120 + 20 * k] for k in range(n_still)], float)
    move = np.array([[250, 110 + 25 * k] for k in range(n_move)], float)

    depth_a, _, box_a = person_scene()
    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    frame_a = make_frame(np.vstack([bg, still, move]), depth_a, index=0, desc=desc)
    out_a = method.process(make_ctx(frame_a, depth_a, [box_a]))
    assert out_a.info["reused"] == 0
    assert (out_a.prob[n_bg:] == 1).all()

    # Next frame: everything shifted with the camera; the "moving" features moved 20 px more.
    depth_b = np.full((H, W), 4.0, np.float32)
    depth_b[3:, 5:] = depth_a[:-3, :-5]
    box_b = Detection(205, 63, 305, 423, PERSON, 0.9)
    uv_b = np.vstack([bg + shift, still + shift, move + shift + [20.0, 0.0]])
    frame_b = make_frame(uv_b, depth_b, index=1, desc=desc)
    out_b = method.process(make_ctx(frame_b, depth_b, [box_b]))
    assert out_b.info["static_matches"] >= 30
    assert out_b.info["reused"] == n_still
    np.testing.assert_allclose(out_b.prob[n_bg:n_bg + n_still], BoxDepthConfig().reuse_prob)
    assert (out_b.prob[n_bg + n_still:] == 1).all()
    assert (out_b.prob[:n_bg] == 0).all()


def test_reuse_needs_depth_agreement():
    """A feature that moved like the scene but sits on a depth edge fails Eq. 17."""
    rng = np.random.default_rng(4)
    depth_a, _, box = person_scene()
    bg = np.column_stack([rng.integers(20, 180, 30), rng.integers(20, 460, 30)]).astype(float)
    desc = rng.integers(0, 256, (31, 32), dtype=np.uint8)
    uv_a = np.vstack([bg, [[250.0, 200.0]]])
    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    method.process(make_ctx(make_frame(uv_a, depth_a, 0, desc), depth_a, [box]))
    # Next frame: static scene still, the feature 2 px right of where H predicts (inside Eq. 13's
    # 3 px), and the depth at the prediction differs (a depth step between the two pixels).
    depth_b = depth_a.copy()
    depth_b[190:211, 245:250] = 2.5
    uv_b = np.vstack([bg, [[252.0, 200.0]]])
    out = method.process(make_ctx(make_frame(uv_b, depth_b, 1, desc), depth_b, [box]))
    assert out.info["reused"] == 0 and out.prob[-1] == 1.0


def test_match_descriptors_is_mutual_and_local():
    rng = np.random.default_rng(0)
    d = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    uv = np.array([[10, 10], [100, 100], [200, 200], [300, 300], [400, 400]], float)
    m = match_descriptors(d, uv, d[::-1].copy(), uv[::-1] + 2.0)
    assert sorted(map(tuple, m)) == [(0, 4), (1, 3), (2, 2), (3, 1), (4, 0)]
    assert len(match_descriptors(d, uv, d, uv + 100.0)) == 0      # too far apart


# ----------------------------------------------------------------------------------------------
# Output conventions


def test_no_detections_is_static_and_none_abstains():
    depth, _, _ = person_scene()
    frame = make_frame([(250, 150), (100, 100)], depth)
    method = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    out = method.process(make_ctx(frame, depth, []))
    np.testing.assert_array_equal(out.prob, [0, 0])
    assert not out.mask.any()
    assert np.isnan(method.process(make_ctx(frame, depth, None)).prob).all()


def test_empty_frame():
    depth, _, box = person_scene()
    frame = make_frame(np.zeros((0, 2)), depth)
    out = BoxDepthMethod(BoxDepthConfig(), ClassGroups()).process(make_ctx(frame, depth, [box]))
    assert out.prob.shape == (0,) and out.mask.any()


def test_protocol_attributes():
    m = BoxDepthMethod(BoxDepthConfig(), ClassGroups())
    assert m.name == "box_depth" and m.needs_detector is True
    assert m.end_frame(None, None, None, False) is None


def test_a_monitor_over_the_middle_of_a_persons_box_is_not_taken_for_the_person():
    """The paper's first seed is the box's centre; with a monitor in front of a standing person it lands on
    the monitor, whose fill spans the box's height too (composited fr1/rpy walk_stand). The person's depth
    layer is the one that stays inside the box (the monitor goes on beyond it): the fill starts there."""
    from frontend.dynamic.box_depth_segmentation import person_layer, segment_box

    depth = np.full((480, 640), 4.0, np.float32)          # the wall
    depth[100:400, 270:360] = 2.0                          # the person
    depth[150:420, 310:500] = 1.0                          # a monitor in front of their right side, wider than them
    box = (262, 92, 368, 408)                              # the detector's box around the person
    x0, y0, x1, y1 = box
    assert person_layer(box, depth) == pytest.approx(2.0, abs=0.05)
    assert person_layer((300, 200, 300, 260), depth) is None                 # an empty box
    paper, _ = segment_box(depth[y0:y1, x0:x1], BoxDepthConfig())
    seg, accepted = segment_box(depth[y0:y1, x0:x1], BoxDepthConfig(), person_layer(box, depth))
    assert np.median(depth[y0:y1, x0:x1][paper]) == pytest.approx(1.0)     # the paper's seeds: the monitor
    assert accepted >= 0 and np.all(depth[y0:y1, x0:x1][seg] == 2.0) and seg.sum() > 0.9 * (
        (depth[y0:y1, x0:x1] == 2.0).sum())
    # Nothing in front of the middle: the paper's seeds, unchanged.
    clear = np.full((480, 640), 4.0, np.float32)
    clear[100:400, 270:360] = 2.0
    plain, k = segment_box(clear[y0:y1, x0:x1], BoxDepthConfig(), person_layer(box, clear))
    assert k == 0 and np.array_equal(plain, segment_box(clear[y0:y1, x0:x1], BoxDepthConfig())[0])


def test_the_box_depth_preset_keeps_the_papers_five_seeds():
    """`-c dynamic_box_depth` is the method as its paper describes it (five seeds, Eq. 8 to all four sides); the
    default seeds past an occluder and spares a person's layer at the image border."""
    from slam.core.config import SlamConfig, apply_yaml, resolve_config_path

    assert SlamConfig().dynamic.box_depth.seed_past_occluder and SlamConfig().dynamic.box_depth.eq8_border_on_body
    preset = apply_yaml(SlamConfig(), resolve_config_path("dynamic_box_depth"))
    assert preset.dynamic.box_depth.seed_past_occluder is False and preset.dynamic.methods == ["box_depth"]
    assert preset.dynamic.box_depth.eq8_border_on_body is False


def test_side_distance_skips_the_sides_that_do_not_count():
    from frontend.dynamic.box_depth_segmentation import image_sides, side_distance

    g = side_distance(4, 6, (False, True, True, True))        # the left side does not count
    np.testing.assert_allclose(g[1, :], [1.5, 1.5, 1.5, 1.5, 1.5, 0.5])
    np.testing.assert_allclose(side_distance(4, 6)[1, :], [0.5, 1.5, 1.5, 1.5, 1.5, 0.5])
    assert np.isinf(side_distance(3, 3, (False,) * 4)).all()
    assert image_sides((0, 10, 100, 480), 640, 480) == (False, True, True, False)
    assert image_sides((5, 10, 100, 400), 640, 480) == (True, True, True, True)


def test_a_person_cut_by_the_image_border_keeps_their_pixels_at_the_border():
    """Eq. 8 trims pixels deeper than the fill's mean next to the box's sides: the fill's overflow into the
    background. A box side on the image border is where the view ends, not the person: a walker entering past
    the left border whose body turns away there lost their first 10 columns (composited fr1/rpy walk_stand,
    keyframe 185). There, pixels on the person's depth layer are measured to the sides inside the image only;
    a surface the fill follows to the border off the layer is trimmed as before; the paper's preset (no
    layer) trims both."""
    depth = np.full((H, W), 4.0, np.float32)
    person = np.zeros((H, W), bool)
    person[60:420, 0:80] = True
    cols = np.arange(W, dtype=np.float32)[None, :] * np.ones((H, 1), np.float32)
    depth[person] = 2.0 + 0.003 * np.clip(30 - cols[person], 0, None)   # 2.0 m, 2.09 m at the border
    # A slanted surface from the person's legs to the border, continuous in depth (a desk going away).
    depth[380:420, 0:40] = (2.0 + 0.012 * (40 - cols[380:420, 0:40])).astype(np.float32)   # 2.48 m at the border
    box = Detection(0, 52, 88, 428, PERSON, 0.9)
    frame = make_frame([(2, 240), (40, 240), (120, 240), (2, 410)], depth)
    ours = BoxDepthMethod(BoxDepthConfig(), ClassGroups()).process(make_ctx(frame, depth, [box]))
    paper = BoxDepthMethod(BoxDepthConfig(seed_past_occluder=False, eq8_border_on_body=False),
                           ClassGroups()).process(make_ctx(frame, depth, [box]))
    np.testing.assert_array_equal(ours.prob, [1, 1, 0, 0])           # the body at the border; not the slant
    on_body = person & (np.abs(depth - 2.0) <= 0.2)
    assert ours.mask[on_body].mean() > 0.97
    assert not ours.mask[380:420, 0:5].any()
    np.testing.assert_array_equal(paper.prob, [0, 1, 0, 0])          # the paper's Eq. 8 trims the border
    assert not paper.mask[60:380, 0:5].any()
    # A box inside the image: the same segment either way.
    inside_depth = np.full((H, W), 4.0, np.float32)
    inside_depth[60:420, 200:280] = depth[60:420, 0:80]
    inside = Detection(192, 52, 288, 428, PERSON, 0.9)
    a = BoxDepthMethod(BoxDepthConfig(), ClassGroups()).process(make_ctx(frame, inside_depth, [inside]))
    b = BoxDepthMethod(BoxDepthConfig(eq8_border_on_body=False), ClassGroups()).process(
        make_ctx(frame, inside_depth, [inside]))
    np.testing.assert_array_equal(a.mask, b.mask)
