"""Dynamic-feature rejection: each method gives every keypoint a dynamic probability.

The core system honours ``FeatureFrame.dynamic_prob`` in tracking and in the back end; the methods
plug in through a ``DynamicFilter``. ``frontend.dynamic_filter.build_dynamic_filter`` picks them from
the config; with none enabled it returns the null filter (every feature static), so the pipeline has no
"if dynamic" branches. Ablations are configs: any subset of methods, any fusion mode. (The factory
lives outside this package because it also builds the detector, which imports this package.)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Protocol, Sequence

import numpy as np

from slam.core.frame import FeatureFrame

@dataclass
class DynamicStats:
    frames: int = 0
    flagged: dict[str, list[int]] = field(default_factory=dict)   # method -> per-frame counts ("fused" too)

    def add(self, name: str, count: int) -> None:
        self.flagged.setdefault(name, []).append(count)

    def summary(self) -> dict[str, dict[str, float]]:
        return {name: {"mean_flagged": float(np.mean(c)), "max_flagged": int(np.max(c)),
                       "frames_with_flags": int(np.count_nonzero(c))} for name, c in self.flagged.items() if c}


@dataclass
class RevisedMask:
    """An earlier keyframe's masks composed again (``keyframe_masks``): ``mask`` for
    ``masks/<index>.png``, ``still_people`` for ``masks/<index>_still.png`` (None: nobody stands still)."""

    frame_index: int
    timestamp: float
    mask: np.ndarray
    still_people: Optional[np.ndarray]


class DynamicFilter(Protocol):
    name: str
    stats: Optional[DynamicStats]   # per-frame flag counts (None for the null filter)
    # After ``end_frame``: earlier keyframes whose masks changed, because a person in them was found
    # standing still once followed for a whole window (frontend/dynamic/keyframe_masks.py).
    revised_masks: Sequence[RevisedMask]

    def begin_frame(self, rgb: np.ndarray, gray: np.ndarray, depth: np.ndarray, timestamp: float,
                    predicted_T_cw: Optional[np.ndarray], last_T_cw: Optional[np.ndarray]) -> None:
        """A new frame arrived: start what needs only the images and poses (the detector, the methods'
        ``prepare``; on threads) so it runs while the features are extracted. Optional: ``process`` does
        it itself when this was not called for its frame."""
        ...

    def begin_images(self, rgb: np.ndarray, gray: np.ndarray, timestamp: float) -> None:
        """Start only what needs the image alone (the detector), earlier: one frame ahead, while the frame
        before is tracked (the System's lookahead). ``begin_frame`` for the same frame (the same ``gray``)
        then adds the pose-dependent work. Optional."""
        ...

    def process(self, frame: FeatureFrame, rgb: np.ndarray, gray: np.ndarray, depth: np.ndarray,
                predicted_T_cw: Optional[np.ndarray], last_T_cw: Optional[np.ndarray]) -> np.ndarray:
        """Dynamic probability in [0, 1] for each of the frame's features."""
        ...

    def end_frame(self, T_cw: Optional[np.ndarray], is_keyframe: bool) -> None:
        """The tracked pose of the frame just processed (None if lost) and its keyframe status."""
        ...

    @property
    def last_mask(self) -> Optional[np.ndarray]:
        """HxW float dynamic probability per pixel of the last frame (None when there is none)."""
        ...

    @property
    def last_still_people(self) -> Optional[np.ndarray]:
        """HxW bool: pixels of people standing still in the last frame (out of ``last_mask``, but never
        to be mapped); None when there are none."""
        ...

    def finish_masks(self) -> Sequence[RevisedMask]:
        """At the end of a run: earlier keyframes whose masks change now that the run has ended (a person
        followed for less than a window who never moved)."""
        ...

    def close(self) -> None:
        """Persist what is worth keeping (e.g. the detection cache)."""
        ...

    # The last frame's keypoints (Nx2, raw pixels), fused probabilities (N) and per-method outputs
    # (``MethodOutput`` by method name; empty for the null filter), for diagnostics and evaluation.
    last_keypoints: np.ndarray
    last_fused: np.ndarray
    last_outputs: dict


class StaticWorld:
    """The null filter: every feature is static."""

    name = "none"
    stats = None
    last_mask = None
    last_still_people = None
    revised_masks: Sequence[RevisedMask] = ()

    def __init__(self) -> None:
        self.last_keypoints = np.zeros((0, 2))
        self.last_fused = np.zeros(0)
        self.last_outputs: dict = {}

    def begin_frame(self, rgb, gray, depth, timestamp, predicted_T_cw, last_T_cw) -> None:
        return None

    def begin_images(self, rgb, gray, timestamp) -> None:
        return None

    def process(self, frame, rgb, gray, depth, predicted_T_cw, last_T_cw) -> np.ndarray:
        self.last_keypoints, self.last_fused = frame.uv_raw, np.zeros(len(frame))
        return self.last_fused

    def end_frame(self, T_cw, is_keyframe) -> None:
        return None

    def finish_masks(self) -> Sequence[RevisedMask]:
        return ()

    def close(self) -> None:
        return None
