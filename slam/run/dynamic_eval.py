"""How well the dynamic methods classify features, measured on generated scenes with exact masks.

Runs the full System on a SyntheticSequence with moving objects, using the ground-truth boxes as
the detector (the synthetic people are not COCO-like enough for YOLOX), and compares every
method's and the fusion's per-feature decision (p >= 0.5) with the ground-truth dynamic mask at the
keypoint. Abstentions count as "static". Features within ``boundary_px`` of a mask boundary are
left out: ORB corners sit on silhouettes, where the label of the rounded pixel is a coin toss.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from frontend.dynamic.base import keypoints_in_mask
from frontend.dynamic.oracle import precision_recall, synthetic_oracle
from slam.core.config import SlamConfig, apply_overrides, apply_yaml
from slam.datasets import SyntheticSequence
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


def boundary_band(mask: np.ndarray, radius: int) -> np.ndarray:
    """Pixels within ``radius`` of the boundary between True and False regions."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    m = mask.astype(np.uint8)
    return (cv2.dilate(m, kernel) != cv2.erode(m, kernel))


def classify_synthetic(sequence: SyntheticSequence, config: SlamConfig, boundary_px: int = 3) -> ClassificationScores:
    system = System(config, detector=synthetic_oracle(sequence), sequence_name=sequence.name)
    flags: dict[str, list[np.ndarray]] = {}
    truths: list[np.ndarray] = []
    keeps: list[np.ndarray] = []
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
    keep = np.concatenate(keeps)
    truth = np.concatenate(truths)[keep]
    scores.features, scores.dynamic_features = len(truth), int(truth.sum())
    scores.boundary_features = int((~keep).sum())
    for name, per_frame in flags.items():
        scores.precision[name], scores.recall[name] = precision_recall(np.concatenate(per_frame)[keep], truth)
    return scores
