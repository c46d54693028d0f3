"""Classification quality of the dynamic methods on a generated scene with exact dynamic masks.

Ground-truth person boxes stand in for the detector; the fusion is the shipped `dynamic_all`
preset. ``MEASURED`` is what ``python tools/classification.py`` prints for 60 frames of people walking
(seed 0; the table is also printed at the end of the test run); a method fails when its precision or
recall falls more than 15 % below (the regression margin of every accuracy gate). The fusion must
also keep the 0.9 / 0.9 that the dynamic front end was accepted with.
"""
from __future__ import annotations

import numpy as np
import pytest

from frontend.dynamic.base import DetectorDefaults
from frontend.dynamic.oracle import precision_recall
from slam.datasets import SyntheticSequence
from slam.run.dynamic_eval import boundary_band, classify_synthetic, synthetic_config

from conftest import report_figures

METHODS = ("cpr", "box_depth", "flow_epipolar", "depth_sdf")
MEASURED = {  # precision, recall (2026-11-24; cpr 2026-11-25 with projective association, was 0.751 / 0.927)
    "cpr": (0.830, 0.927), "box_depth": (1.000, 0.967), "flow_epipolar": (0.866, 0.766),
    "depth_sdf": (0.917, 0.941), "fused": (0.944, 0.998),
}
REGRESSION_MARGIN = 0.85


@pytest.fixture(scope="module")
def scores():
    sequence = SyntheticSequence(n_frames=60, movers="people", seed=0)
    result = classify_synthetic(sequence, synthetic_config(sequence, preset="dynamic_all"))
    report_figures("classification on 60 generated frames of people walking (tools/classification.py)",
                   result.table())
    return result


@pytest.mark.slow
def test_every_frame_is_tracked_with_people_walking(scores):
    assert scores.tracked_frames == scores.frames == 60


@pytest.mark.slow
def test_fusion_reaches_090_precision_and_recall(scores):
    assert scores.precision["fused"] >= 0.9
    assert scores.recall["fused"] >= 0.9


@pytest.mark.slow
def test_fusion_beats_every_single_method_on_recall(scores):
    assert scores.recall["fused"] >= max(scores.recall[m] for m in METHODS)


@pytest.mark.slow
@pytest.mark.parametrize("method", [*METHODS, "fused"])
def test_each_method_keeps_its_measured_precision_and_recall(scores, method):
    precision, recall = MEASURED[method]
    assert scores.precision[method] >= REGRESSION_MARGIN * precision, (method, scores.precision[method])
    assert scores.recall[method] >= REGRESSION_MARGIN * recall, (method, scores.recall[method])


@pytest.mark.slow
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


class _DetectorThatSeesNobody(DetectorDefaults):
    def detect(self, bgr, timestamp: float = 0.0) -> list:
        return []


@pytest.mark.slow
def test_without_any_detection_moving_people_are_still_found_by_motion_alone():
    """Issue 11, item 1: where the detector sees nobody (blur, a close torso, a person cut by the border)
    the regions cpr flags and flow_epipolar's epipolar test confirms are moving (region_motion.
    confirmed_regions), and so are the regions the frames before a keyframe saw move (free_space).
    Measured (60 frames of people walking, seed 0): keyframe masks 0.79 / 0.69 precision / recall; with
    the epipolar regions alone 0.99 / 0.25, nothing at all without either. Bars: the issue's precision bar
    for the masks (0.7), and more than half of the people's pixels found with no detection at all."""
    from slam.run.dynamic_eval import evaluate_synthetic

    sequence = SyntheticSequence(n_frames=60, movers="people", seed=0)
    result = evaluate_synthetic(sequence, synthetic_config(sequence, preset="dynamic_all"),
                                detector=_DetectorThatSeesNobody())
    masks = result.keyframe_masks["fused"]
    assert masks.recall >= 0.5 and masks.precision >= 0.7, (masks.precision, masks.recall)


@pytest.mark.slow
def test_scene_evaluation_scores_the_trajectory_a_run_writes():
    """The ATE of ``evaluate_synthetic`` is that of the trajectory after ``System.close`` (the graph's last
    updates and the final global adjustment), the one ``dynslam run`` writes; it once read the trajectory
    before them, and the hard scenes' ratios then described poses no user gets."""
    from slam.run.dynamic_eval import evaluate_synthetic
    from slam.run.evaluation import ate

    sequence = SyntheticSequence(n_frames=40, movers="people", seed=0)
    seen = {}

    def observe(frame, output, system):
        seen["system"] = system
        if frame.index == len(sequence) - 1:
            seen["before_close"] = system.trajectory()

    result = evaluate_synthetic(sequence, synthetic_config(sequence, preset="dynamic_all"), observer=observe)
    gt_t, gt_poses = sequence.groundtruth()
    stamps, poses, tracked = seen["system"].trajectory()          # closed by now
    assert result.ate_rmse == ate(gt_t, gt_poses, stamps[tracked], poses[tracked]).rmse
    before = seen["before_close"]
    assert not np.array_equal(before[1][before[2]], poses[tracked])   # the final adjustment moved them


def test_a_scene_evaluates_with_dynamic_handling_off_too():
    """``tools/hard_scenes.py --preset static`` (the baseline a hard scene is compared with) once ended in
    an AttributeError: the evaluation read keypoints the null filter did not keep. With every feature
    static, nothing is flagged: recall 0 per feature and per mask pixel, and the trajectory is scored."""
    from slam.run.dynamic_eval import evaluate_synthetic

    sequence = SyntheticSequence(n_frames=12, movers="people", seed=0)
    result = evaluate_synthetic(sequence, synthetic_config(sequence, preset="static"))
    assert result.classification.recall["fused"] == 0.0 and result.classification.dynamic_features > 0
    assert result.keyframe_masks["fused"].recall == 0.0 and np.isfinite(result.ate_rmse)
    assert list(result.classification.recall) == ["fused"]         # no method ran
