"""How well the dynamic methods classify features, measured on generated scenes with exact masks.

Runs the full System on a SyntheticSequence with moving objects, using the ground-truth boxes as
the detector (the synthetic people are not COCO-like enough for YOLOX), and compares every
method's and the fusion's per-feature decision (p >= 0.5) with the ground-truth dynamic mask at the
keypoint. Abstentions count as "static". Features within ``boundary_px`` of a mask boundary are
left out: ORB corners sit on silhouettes, where the label of the rounded pixel is a coin toss.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import cv2
import numpy as np

from frontend.dynamic.base import keypoints_in_mask
from frontend.dynamic.oracle import precision_recall, synthetic_oracle
from slam.core.config import SlamConfig, apply_overrides, apply_yaml
from slam.datasets import SyntheticSequence
from slam.run.run_artifacts import mask_to_png
from slam.runtime.system import System


@dataclass
class ClassificationScores:
    precision: dict[str, float] = field(default_factory=dict)
    recall: dict[str, float] = field(default_factory=dict)
    features: int = 0
    boundary_features: int = 0
    dynamic_features: int = 0
    tracked_frames: int = 0
    frames: int = 0

    def table(self) -> str:
        lines = ["| method | precision | recall |", "|---|---|---|"]
        lines += [f"| {name} | {self.precision[name]:.3f} | {self.recall[name]:.3f} |" for name in self.precision]
        return "\n".join(lines)


def synthetic_config(sequence: SyntheticSequence, methods: list[str] | None = None, preset: str | None = None,
                     **overrides) -> SlamConfig:
    """The generated sequence's camera, then ``preset`` (e.g. "dynamic_all"), then ``methods`` (if
    given, with single/noisy-OR fusion), then dotted ``overrides``."""
    fx, fy, cx, cy = sequence.intrinsics
    config = SlamConfig()
    if preset is not None:
        apply_yaml(config, preset)
    camera = {"camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy,
              "camera.width": sequence.width, "camera.height": sequence.height}
    if methods is not None:
        camera.update({"dynamic.methods": methods, "dynamic.fusion": "single" if len(methods) == 1 else "noisy_or"})
    apply_overrides(config, {**camera, **overrides})
    return config


def scene_detector(scene, margin_px: int = 0):
    """The ground-truth person boxes of a ``HardScene`` (``frontend.dynamic.oracle``), widened by
    ``margin_px``, without the frames in ``scene.detector_misses``."""
    return synthetic_oracle(scene, margin_px=margin_px, skip_frames=scene.detector_misses)


def boundary_band(mask: np.ndarray, radius: int) -> np.ndarray:
    """Pixels within ``radius`` of the boundary between True and False regions."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    m = mask.astype(np.uint8)
    return (cv2.dilate(m, kernel) != cv2.erode(m, kernel))


def classify_synthetic(sequence: SyntheticSequence, config: SlamConfig, boundary_px: int = 3,
                       detector=None) -> ClassificationScores:
    """Run ``System`` on ``sequence`` with ``detector`` (default: its ground-truth boxes) and score every
    method's per-feature decision against the exact dynamic mask."""
    return evaluate_synthetic(sequence, config, boundary_px, detector).classification


@dataclass
class PixelCounts:
    """Moving-pixel counts of one method's mask at p >= 0.5 against the exact mask, summed over frames."""

    true_positive: int = 0
    flagged: int = 0
    dynamic: int = 0

    def add(self, mask: np.ndarray, truth: np.ndarray) -> None:
        flagged = mask >= 0.5
        self.true_positive += int(np.count_nonzero(flagged & truth))
        self.flagged += int(np.count_nonzero(flagged))
        self.dynamic += int(np.count_nonzero(truth))

    @property
    def precision(self) -> float:
        return self.true_positive / self.flagged if self.flagged else float("nan")

    @property
    def recall(self) -> float:
        return self.true_positive / self.dynamic if self.dynamic else float("nan")


@dataclass
class SceneEvaluation:
    """One run of ``System`` on a generated sequence: per-feature classification, the pixel masks of the
    keyframes (what ``masks/`` holds) against the exact masks, and the trajectory against ground truth
    (ATE over tracked frames, per-frame error, frames LOST)."""

    classification: ClassificationScores
    keyframe_masks: dict[str, PixelCounts]
    ate_rmse: float
    max_error: float
    errors: np.ndarray
    lost_frames: list[int]
    keyframes: int
    final_masks: dict[int, np.ndarray] = field(default_factory=dict)   # frame index -> 8-bit, as masks/ holds it

    def mask_table(self) -> str:
        lines = ["| method | mask precision | mask recall |", "|---|---|---|"]
        lines += [f"| {name} | {c.precision:.3f} | {c.recall:.3f} |" for name, c in self.keyframe_masks.items()]
        return "\n".join(lines)


def median_ate_ratio(runs: list[SceneEvaluation], clean_runs: list[SceneEvaluation]) -> float:
    """The median over seeds of a scene's ATE over the clean path's ATE at the same seed (runs[k] and
    clean_runs[k] share seed k): the hard scenes' bar, robust to one seed's luck."""
    return float(np.median([r.ate_rmse / c.ate_rmse for r, c in zip(runs, clean_runs, strict=True)]))


def evaluate_synthetic(sequence: SyntheticSequence, config: SlamConfig, boundary_px: int = 3,
                       detector=None, observer: Optional[Callable] = None,
                       split: Optional[tuple[str, Callable[[int], np.ndarray]]] = None) -> SceneEvaluation:
    """Run ``System`` on ``sequence`` (a ``SyntheticSequence`` or ``HardScene``) with ``detector``
    (default: its ground-truth boxes) and measure classification, keyframe masks and trajectory.
    ``observer(frame, output, system)``, if given, sees every frame after it is processed (tests that
    need more of the same run than these measures; the system is closed at the end, its map kept).
    ``split`` (label, region of a frame index as HxW bool), if given: the fused keyframe masks are also counted
    inside and outside that region (``keyframe_masks`` "fused, <label>" and "fused, not <label>"; e.g.
    ``CompositeScene.real_holes``, where the real frame measured no depth)."""
    from slam.run.evaluation import ate

    detector = synthetic_oracle(sequence) if detector is None else detector
    system = System(config, detector=detector, sequence_name=sequence.name)
    flags: dict[str, list[np.ndarray]] = {}
    truths: list[np.ndarray] = []
    keeps: list[np.ndarray] = []
    masks: dict[str, PixelCounts] = {}
    keyframe_masks: dict[int, tuple[np.ndarray, np.ndarray]] = {}   # frame index -> (8-bit fused, truth)
    scores = ClassificationScores()
    for frame in sequence:
        out = system.process(frame.rgb, frame.depth, frame.timestamp, frame.index)
        scores.frames += 1
        scores.tracked_frames += out.T_wc is not None
        rejector = system.dynamic_filter
        truths.append(keypoints_in_mask(frame.dynamic_mask, rejector.last_keypoints).astype(bool))
        keeps.append(~keypoints_in_mask(boundary_band(frame.dynamic_mask, boundary_px), rejector.last_keypoints))
        for name, output in rejector.last_outputs.items():
            flags.setdefault(name, []).append(np.nan_to_num(output.prob, nan=0.0) >= 0.5)
        flags.setdefault("fused", []).append(rejector.last_fused >= config.tracking.dynamic_threshold)
        _revise(keyframe_masks, system.revised_keyframe_masks)   # a person there turned out to stand still
        if out.is_keyframe:
            _count_masks(masks, rejector.last_outputs, frame.dynamic_mask)
            fused = system.last_dynamic_mask
            fused = np.zeros(frame.dynamic_mask.shape, np.float32) if fused is None else fused
            keyframe_masks[frame.index] = (mask_to_png(fused), frame.dynamic_mask.astype(bool))
        if observer is not None:
            observer(frame, out, system)
    _revise(keyframe_masks, system.finish_keyframe_masks())
    _count_final_masks(masks, keyframe_masks, split)
    keep = np.concatenate(keeps)
    truth = np.concatenate(truths)[keep]
    scores.features, scores.dynamic_features = len(truth), int(truth.sum())
    scores.boundary_features = int((~keep).sum())
    for name, per_frame in flags.items():
        scores.precision[name], scores.recall[name] = precision_recall(np.concatenate(per_frame)[keep], truth)
    system.close()   # the final updates and global adjustment first: the trajectory a run writes
    stamps, poses, tracked = system.trajectory()
    gt_t, gt_poses = sequence.groundtruth()
    result = ate(gt_t, gt_poses, stamps[tracked], poses[tracked])
    evaluation = SceneEvaluation(scores, masks, result.rmse, result.max, result.errors,
                                 [int(i) for i in np.flatnonzero(~tracked)], system.num_keyframes,
                                 {i: png for i, (png, _) in keyframe_masks.items()})
    return evaluation


def _revise(keyframe_masks: dict[int, tuple[np.ndarray, np.ndarray]], revised) -> None:
    """Replace the 8-bit fused mask of each revised keyframe (``RevisedMask``), keeping its exact mask."""
    for mask in revised:
        keyframe_masks[mask.frame_index] = (mask_to_png(mask.mask), keyframe_masks[mask.frame_index][1])


def _count_final_masks(counts: dict[str, PixelCounts], keyframe_masks: dict[int, tuple[np.ndarray, np.ndarray]],
                       split: Optional[tuple[str, Callable[[int], np.ndarray]]]) -> None:
    """The fused keyframe masks as ``masks/`` holds them at the end of the run, against the exact masks; with
    ``split`` also inside and outside its region (see ``evaluate_synthetic``)."""
    for index, (png, truth) in keyframe_masks.items():
        fused = png.astype(np.float32) / 255.0
        counts.setdefault("fused", PixelCounts()).add(fused, truth)
        if split is not None:
            label, region_of = split
            region = region_of(index)
            counts.setdefault(f"fused, {label}", PixelCounts()).add(np.where(region, fused, 0), truth & region)
            counts.setdefault(f"fused, not {label}", PixelCounts()).add(np.where(region, 0, fused), truth & ~region)


def _count_masks(counts: dict[str, PixelCounts], outputs, truth: np.ndarray) -> None:
    """Each method's pixel mask (a method without one counts as flagging nothing)."""
    empty = np.zeros(truth.shape, np.float32)
    for name, output in outputs.items():
        mask = output.mask if output.mask is not None and np.shape(output.mask) == truth.shape else empty
        counts.setdefault(name, PixelCounts()).add(np.asarray(mask, np.float32), truth)
