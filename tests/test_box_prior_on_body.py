"""The person-box prior off the body (``dynamic.box_prior_on_body``, frontend/dynamic/keyframe_masks.py
``features_off_body``): which features in a person's box are freed of the prior, and in which boxes."""
from __future__ import annotations

import numpy as np


def test_features_off_the_body_and_clear_of_it_are_the_only_ones_freed_of_the_box_prior():
    """``dynamic.box_prior_on_body``: in a person's box, a feature on the wall behind them (more than a body's
    reach from their layer) and more than the margin from the person is freed of the prior; one on the person,
    one on the wall within the margin of their silhouette, one outside the boxes and one without depth are not."""
    from frontend.dynamic.keyframe_masks import features_off_body

    shape = (480, 640)
    depth = np.full(shape, 3.5, np.float32)                 # the wall
    depth[100:400, 280:340] = 1.5                           # the person, 60 px wide
    depth[120:140, 400:420] = 0.0                           # a hole in the depth, in the box
    box = (220, 92, 440, 408)
    region = np.zeros(shape, bool)
    region[82:418, 210:450] = True                          # the box dilated by 10 px
    uv = np.array([[300.0, 200.0],    # on the person
                   [345.0, 200.0],    # wall, 5 px from the person
                   [420.0, 300.0],    # wall, 80 px from the person
                   [410.0, 130.0],    # no depth
                   [100.0, 200.0],    # outside every box
                   [225.0, 300.0],    # wall, 5 px inside the box's side (the dilation ring counts as person)
                   [235.0, 300.0]])   # wall, 15 px inside it
    free = features_off_body(region, [box], depth, {}, uv, margin_px=10)
    assert free.tolist() == [False, False, True, False, False, False, True]
    # Without depth for a layer, or without boxes, nothing is freed.
    assert not features_off_body(region, [box], np.zeros(shape, np.float32), {}, uv, 10).any()
    assert not features_off_body(region, [], depth, {}, uv, 10).any()


def test_only_boxes_their_person_fills_sparsely_free_features_of_the_box_prior():
    """``dynamic.box_prior_on_body_max_fill``: the prior is lifted only in a box whose person layer fills less
    than that share of it (a walker cut diagonally by a rolled camera's box, a person mostly hidden), and not
    where such a box overlaps a box its person fills (an upright person in full view)."""
    from frontend.dynamic.box_depth_segmentation import layer_fill
    from frontend.dynamic.keyframe_masks import features_off_body

    shape = (480, 640)
    depth = np.full(shape, 3.5, np.float32)                 # the wall
    depth[100:400, 280:340] = 1.5                           # person A, 60 px wide, in a wide box
    depth[100:400, 460:560] = 2.0                           # person B, 100 px wide, in a box they fill
    sparse, dense = (220, 92, 440, 408), (430, 92, 600, 408)
    region = np.zeros(shape, bool)
    for x0, y0, x1, y1 in (sparse, dense):
        region[y0 - 10:y1 + 10, x0 - 10:x1 + 10] = True      # the boxes dilated by 10 px
    layers: dict = {}
    assert layer_fill(sparse, depth, layers) < 1 / 3 < 0.5 < layer_fill(dense, depth, layers)
    uv = np.array([[400.0, 300.0],    # wall in the sparse box only, 60 px from person A, 20 px from the dense box
                   [580.0, 300.0],    # wall in the dense box only, 20 px from person B and its side
                   [435.0, 300.0],    # wall where the boxes overlap, 25 px from person B
                   [300.0, 200.0]])   # on person A
    every_box = features_off_body(region, [sparse, dense], depth, layers, uv, 10)
    assert every_box.tolist() == [True, True, True, False]
    gated = features_off_body(region, [sparse, dense], depth, layers, uv, 10, max_fill=1 / 3)
    assert gated.tolist() == [True, False, False, False]
    # A box whose layer cannot be found counts as filled: nothing is freed by the fill rule alone.
    assert layer_fill(sparse, np.zeros(shape, np.float32), {}) == 1.0
