"""Depth standard-deviation fitting (CP-SLAM) on small synthetic frames."""
from __future__ import annotations

import numpy as np

from frontend.dynamic.base import Detection, DynamicContext
from frontend.dynamic.depth_sdf import DepthSdfMethod, band_half_width, fit_depth_layer, neg_log_likelihood
from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import ClassGroups, DepthSdfConfig
from slam.core.frame import FeatureFrame

CAM = PinholeCamera(525, 525, 319.5, 239.5, 640, 480)
H, W = 480, 640
BOX = Detection(200, 60, 300, 420, 0, 0.9)


def make_frame(uv, depths, index=0) -> FeatureFrame:
    uv = np.asarray(uv, float).reshape(-1, 2)
    d = np.asarray(depths, float)
    n = len(uv)
    desc = np.random.default_rng(index).integers(0, 256, (n, 32), dtype=np.uint8)
    u_right = np.where(d > 0, uv[:, 0] - CAM.bf / np.maximum(d, 1e-9), np.nan)
    return FeatureFrame(index, float(index), uv, uv.copy(), np.zeros(n, int), desc, d, u_right,
                        np.zeros(n), np.array([1.0]))


def make_ctx(frame, detections, depth=None) -> DynamicContext:
    depth = np.zeros((H, W), np.float32) if depth is None else depth
    gray = np.full((H, W), 128, np.uint8)
    return DynamicContext(frame, np.repeat(gray[:, :, None], 3, axis=2), gray, depth, CAM, detections)


def layered_scene(rng, n_person=30, n_bg=12, n_obj=6, n_out=8):
    """Features in the person box: the person at 2.0 +- 0.03 m, the wall at 4 m, an object at 1 m;
    plus features outside the box."""
    uv_in = np.column_stack([rng.uniform(201, 299, n_person + n_bg + n_obj),
                             rng.uniform(61, 419, n_person + n_bg + n_obj)])
    d_in = np.concatenate([rng.uniform(1.97, 2.03, n_person), rng.normal(4.0, 0.01, n_bg),
                           rng.normal(1.0, 0.01, n_obj)])
    uv_out = np.column_stack([rng.uniform(0, 190, n_out), rng.uniform(0, 479, n_out)])
    d_out = rng.uniform(1.97, 2.03, n_out)      # same depth as the person, but outside any box
    labels = np.r_[np.ones(n_person), np.zeros(n_bg + n_obj + n_out)]
    return np.vstack([uv_in, uv_out]), np.r_[d_in, d_out], labels


def test_inliers_are_the_person_depth_layer():
    rng = np.random.default_rng(1)
    uv, d, labels = layered_scene(rng)
    method = DepthSdfMethod(DepthSdfConfig(combine="best"), ClassGroups())
    for index in range(10):                      # every frame seed finds the same layer
        out = method.process(make_ctx(make_frame(uv, d, index), [BOX]))
        np.testing.assert_array_equal(out.prob, labels)
        assert out.info["fitted"] == 1 and out.info["dynamic"] == 30


def test_paper_union_flags_every_layer_an_iteration_fits():
    # Algorithm 1 adds each iteration's inliers to S1: with 20 draws, pairs from the wall (12 of 48
    # features) and the object in front (6) fit their own layers, so those are flagged too; features
    # outside the box never are.
    rng = np.random.default_rng(1)
    uv, d, labels = layered_scene(rng)
    out = DepthSdfMethod(DepthSdfConfig(combine="union"), ClassGroups()).process(make_ctx(make_frame(uv, d), [BOX]))
    assert (out.prob[:30] == 1).all()                          # the person layer always
    assert out.prob[30:48].sum() > 0                            # plus the other layers drawn
    assert (out.prob[48:] == 0).all()


def test_deterministic_for_a_seed_and_frame():
    rng = np.random.default_rng(2)
    # Depths spread over 1-5 m with no dominant layer: different draws win different bands.
    uv = np.column_stack([rng.uniform(201, 299, 60), rng.uniform(61, 419, 60)])
    d = rng.uniform(1.0, 5.0, 60)
    cfg = DepthSdfConfig(seed=7)
    a = DepthSdfMethod(cfg, ClassGroups()).process(make_ctx(make_frame(uv, d, 5), [BOX])).prob
    m = DepthSdfMethod(cfg, ClassGroups())
    m.process(make_ctx(make_frame(uv, d, 4), [BOX]))       # history must not matter
    b = m.process(make_ctx(make_frame(uv, d, 5), [BOX])).prob
    np.testing.assert_array_equal(a, b)
    runs = {tuple(DepthSdfMethod(DepthSdfConfig(seed=s), ClassGroups())
                  .process(make_ctx(make_frame(uv, d, 5), [BOX])).prob) for s in range(12)}
    assert len(runs) > 1                          # the seed is really used


def test_vectorised_fit_matches_a_loop_over_the_paper_steps():
    rng = np.random.default_rng(3)
    d = np.r_[rng.uniform(1.9, 2.1, 25), rng.uniform(3.0, 4.0, 15)]
    inl, (model,) = fit_depth_layer(d, np.random.default_rng(11), 20, 0.02, 0.01, combine="best")
    union, models = fit_depth_layer(d, np.random.default_rng(11), 20, 0.02, 0.01, combine="union")
    # Same draws, one model at a time.
    r = np.random.default_rng(11)
    i = r.integers(0, len(d), 20)
    j = (i + 1 + r.integers(0, len(d) - 1, 20)) % len(d)
    best_count, best = -1, None
    s1 = np.zeros(len(d), bool)             # Algorithm 1's S1: the inliers of every iteration
    n_models = 0
    for k in range(20):
        pair = d[[i[k], j[k]]]
        mu, sigma = pair.mean(), max(pair.std(), 0.01)
        nll = [np.log(np.sqrt(2 * np.pi) * sigma ** 2) + (x - mu) ** 2 / (2 * sigma ** 2) for x in d]
        n0 = sum(v < 0.02 for v in nll)
        th = 0.02 * (1.0 + n0 / len(d))
        flags = np.array([v < th for v in nll])
        s1 |= flags
        n_models += bool(flags.any())
        if flags.sum() > best_count:
            best_count, best = flags.sum(), flags
    np.testing.assert_array_equal(inl, best)
    assert model["inliers"] == best_count
    np.testing.assert_array_equal(union, s1)
    assert len(models) == n_models and union.sum() >= inl.sum()


def test_broad_models_have_no_inliers():
    # A person/background pair (sigma = 1 m) must not swallow the box: -ln L >= th everywhere.
    assert band_half_width(1.0, 0.04) == 0.0
    assert np.all(neg_log_likelihood(np.linspace(0, 6, 50), 3.0, 1.0) > 0.04)
    # The widest band any model admits is about +-0.55 m (sigma ~ 0.39 m).
    widths = [band_half_width(s, 0.02) for s in np.linspace(0.01, 1.0, 200)]
    assert 0.5 < max(widths) < 0.6


def test_equal_depths_do_not_break_the_fit():
    uv = np.column_stack([np.linspace(210, 290, 12), np.linspace(80, 400, 12)])
    d = np.r_[np.full(8, 2.0), np.full(4, 4.0)]            # quantised depth: sigma = 0 pairs
    out = DepthSdfMethod(DepthSdfConfig(), ClassGroups()).process(make_ctx(make_frame(uv, d), [BOX]))
    np.testing.assert_array_equal(out.prob, np.r_[np.ones(8), np.zeros(4)])


def test_features_without_depth_abstain_and_tiny_boxes_are_not_fitted():
    uv = np.array([[250, 100], [250, 150], [250, 200], [250, 250], [100, 100], [450, 100], [460, 120]], float)
    d = np.array([2.0, 2.01, 0.0, 1.99, 0.0, 2.0, 0.0])
    box2 = Detection(440, 90, 480, 130, 0, 0.8)               # one depth feature only: no fit
    out = DepthSdfMethod(DepthSdfConfig(), ClassGroups()).process(make_ctx(make_frame(uv, d), [BOX, box2]))
    assert out.prob[0] == 1 and out.prob[1] == 1 and out.prob[3] == 1
    assert np.isnan(out.prob[2])                              # in a box, no depth
    assert out.prob[4] == 0                                   # outside every box
    assert np.isnan(out.prob[5]) and np.isnan(out.prob[6])    # box with < 2 depth features
    assert out.info["fitted"] == 1 and out.info["abstained"] == 3


def test_only_dynamic_classes_and_outside_features_are_static():
    rng = np.random.default_rng(4)
    uv, d, labels = layered_scene(rng)
    chair = Detection(200, 60, 300, 420, 56, 0.9)              # same box, but a chair
    method = DepthSdfMethod(DepthSdfConfig(), ClassGroups())
    out = method.process(make_ctx(make_frame(uv, d), [chair]))
    assert (out.prob == 0).all() and not out.mask.any()
    out = method.process(make_ctx(make_frame(uv, d), []))
    assert (out.prob == 0).all()
    assert np.isnan(method.process(make_ctx(make_frame(uv, d), None)).prob).all()


def test_mask_is_the_person_depth_band_inside_the_box():
    depth = np.full((H, W), 4.0, np.float32)
    person = np.zeros((H, W), bool)
    person[100:400, 220:280] = True
    depth[person] = 2.0
    depth[250:280, 235:265] = 1.0                             # object in front
    rng = np.random.default_rng(5)
    rows, cols = np.nonzero(person)
    pick = rng.choice(len(rows), 30, replace=False)
    uv = np.column_stack([cols[pick], rows[pick]]).astype(float)
    d = depth[rows[pick], cols[pick]].astype(float) + rng.uniform(-0.02, 0.02, 30)
    out = DepthSdfMethod(DepthSdfConfig(combine="best"), ClassGroups()).process(
        make_ctx(make_frame(uv, d), [BOX], depth))
    mask = out.mask > 0
    assert mask[person & (depth == 2.0)].all()
    assert not mask[depth == 1.0].any()
    assert not mask[~person].any()                            # wall in the box and everything outside


def test_protocol_attributes():
    m = DepthSdfMethod(DepthSdfConfig(), ClassGroups())
    assert m.name == "depth_sdf" and m.needs_detector is True
    assert m.end_frame(None, None, None, False) is None
