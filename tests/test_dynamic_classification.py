"""Classification quality of the dynamic methods on a generated scene with exact dynamic masks.

Ground-truth person boxes stand in for the detector. Measured (60 frames, people walking):
box_depth P 0.79 / R 0.75, flow_epipolar P 0.57 / R 0.60, depth_sdf P 0.28 / R 0.52, fusion with
trust weights (box_depth 1, others 0.45) P 0.66 / R 0.84. The thresholds below guard those levels;
the issue's 0.9 / 0.9 target is not reached yet (see docs/dynamic.md).
"""
from __future__ import annotations

import numpy as np
import pytest

from frontend.dynamic.oracle import precision_recall
from slam.datasets import SyntheticSequence
from slam.dynamic_eval import boundary_band, classify_synthetic, synthetic_config


@pytest.fixture(scope="module")
def scores():
    sequence = SyntheticSequence(n_frames=60, movers="people", seed=0)
    config = synthetic_config(sequence, ["box_depth", "flow_epipolar", "depth_sdf"],
                              **{"dynamic.depth_sdf.weight": 0.45, "dynamic.flow_epipolar.weight": 0.45})
    return classify_synthetic(sequence, config)


def test_every_frame_is_tracked_with_people_walking(scores):
    assert scores.tracked_frames == scores.frames == 60


def test_box_depth_segments_the_people(scores):
    assert scores.precision["box_depth"] >= 0.7 and scores.recall["box_depth"] >= 0.7


def test_fusion_recovers_most_dynamic_features(scores):
    assert scores.recall["fused"] >= 0.8
    assert scores.precision["fused"] >= 0.6
    # Fusion catches more than any single method.
    assert scores.recall["fused"] > max(scores.recall[m] for m in ("box_depth", "flow_epipolar", "depth_sdf"))


def test_scores_cover_enough_dynamic_features(scores):
    assert scores.dynamic_features > 1000 and scores.features > 30000


def test_precision_recall_and_boundary_band():
    flagged = np.array([True, True, False, False])
    truth = np.array([True, False, True, False])
    assert precision_recall(flagged, truth) == (0.5, 0.5)
    mask = np.zeros((20, 20), bool)
    mask[5:15, 5:15] = True
    band = boundary_band(mask, 2)
    assert band[5, 10] and band[4, 10] and not band[10, 10] and not band[0, 0]
