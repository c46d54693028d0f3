"""What local mapping, loop closing and landmark fusion ask of a graph back end.

Implemented by ``FactorGraphBackend`` (iSAM2 over the whole map) and ``LocalWindowBackend`` (local
bundle adjustment, pose-graph loop correction). Poses are 4x4 camera-to-world matrices; handles are
consecutive integers, one per factor added (priors included), so a caller can predict them.
"""
from __future__ import annotations

from typing import Iterable, Optional, Protocol, Sequence

import numpy as np


class GraphBackend(Protocol):
    def add_keyframe(self, kf_id: int, T_wc_guess: np.ndarray) -> None: ...

    def add_landmark(self, lm_id: int, xyz_guess: np.ndarray) -> None: ...

    def has_keyframe(self, kf_id: int) -> bool: ...

    def has_landmark(self, lm_id: int) -> bool: ...

    def add_observation(self, kf_id: int, lm_id: int, uv, depth: float = 0.0, level_scale: float = 1.0,
                        dynamic_prob: float = 0.0) -> int: ...

    def add_relative_pose(self, kf_a: int, kf_b: int, T_ab: np.ndarray, sigma_t: float, sigma_r_deg: float,
                          kernel: Optional[str] = "huber", kernel_k: float = 1.0) -> int: ...

    def relative_pose_error(self, handle: int) -> tuple[float, float]: ...

    def remove_factors(self, handles: Iterable[int]) -> None: ...

    def update(self, extra_updates: Optional[int] = None, relinearize: bool = False) -> None: ...

    def optimize_all(self, iterations: Optional[int] = None) -> None: ...

    def keyframe_pose(self, kf_id: int) -> np.ndarray: ...

    def keyframe_poses(self) -> tuple[np.ndarray, np.ndarray]: ...

    def landmark_positions(self) -> tuple[np.ndarray, np.ndarray]: ...

    def sync(self) -> None:
        """Wait until every update asked for is applied to the estimates (a no-op in process)."""

    def close(self) -> None:
        """Release what the graph holds (a worker process); the estimates stay readable."""

    @property
    def num_factors(self) -> int: ...

    @property
    def holding_back(self) -> bool:
        """Whether the last ``update`` held its estimates back for a later keyframe (a worker solving a loop's
        correction: ``backend.loop_result_keyframes``): the estimates reported are those already taken up,
        and taking them up again would undo what the caller moved since. False in process."""
        ...

    @property
    def update_cpu_ms(self) -> Sequence[float]:
        """CPU milliseconds of every ``update`` applied so far, in order: what the back end costs per
        keyframe, wherever it runs (a worker process measures its own, graph building included)."""
        ...
