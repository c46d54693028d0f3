"""iSAM2 factor graph over keyframe poses X(k) and landmarks L(j): the back end's public core.

This is the part another pipeline can drive directly, with no front end::

    from backend import FactorGraphBackend, BackendParams, StereoCalibration
    graph = FactorGraphBackend(BackendParams(), StereoCalibration(fx, fy, cx, cy, baseline))
    graph.add_keyframe(0, T_wc0)                       # the first keyframe gets a prior
    graph.add_keyframe(1, T_wc1_guess)
    graph.add_landmark(7, xyz_guess)
    graph.add_observation(0, 7, uv=(u, v), depth=z)    # RGB-D: a virtual stereo factor
    graph.add_observation(1, 7, uv=(u, v))             # no depth: a plain projection factor
    handle = graph.add_relative_pose(0, 1, T_01, sigma_t=0.05, sigma_r_deg=2.0, kernel="cauchy")
    graph.update()
    T_wc1 = graph.keyframe_pose(1); ids, xyz = graph.landmark_positions()
    graph.remove_factors([handle]); graph.update()

Poses are 4x4 camera-to-world matrices (OpenCV camera axes). Factors and new variables wait in a
pending graph until ``update()``, which runs one iSAM2 update plus ``extra_updates`` more (iSAM2
needs them to converge after relinearisation, see docs/engineering notes).
"""
from __future__ import annotations

from typing import Iterable, Optional

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

# re-exported: the public names of the back end's core (backend/__init__.py, README)
from backend.factors import BackendError, BackendParams, FactorBuilder, StereoCalibration, pose3
from slam.core.geometry import relative_pose_residual
from slam.core.timing import thread_cpu_ms

__all__ = ["BackendError", "BackendParams", "FactorGraphBackend", "StereoCalibration", "pose3"]


class FactorGraphBackend:
    def __init__(self, params: BackendParams, calibration: StereoCalibration):
        self.params = params
        self.calibration = calibration
        self._factors = FactorBuilder(params, calibration)
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(params.relinearize_threshold)
        isam_params.relinearizeSkip = params.relinearize_skip
        self._isam = gtsam.ISAM2(isam_params)
        self._pending_factors: dict[int, gtsam.NonlinearFactor] = {}   # handle -> factor, until update()
        self._pending_values = gtsam.Values()
        self._factor_index: dict[int, int] = {}     # handle -> iSAM2 factor index
        self._next_handle = 0
        self._keyframes: set[int] = set()
        self._landmarks: set[int] = set()
        self._estimate: Optional[gtsam.Values] = None
        self._relative: dict[int, tuple[int, int, np.ndarray]] = {}   # handle -> (a, b, T_ab) of pose factors
        self.update_cpu_ms: list[float] = []        # thread CPU of every update (GraphBackend)

    # --- variables ------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, T_wc_guess: np.ndarray) -> None:
        """New pose variable; the very first one is anchored by a tight prior (gauge freedom)."""
        if kf_id in self._keyframes:
            raise BackendError(f"keyframe {kf_id} already exists")
        self._pending_values.insert(X(kf_id), pose3(T_wc_guess))
        if not self._keyframes:
            self._add_factor(self._factors.first_pose_prior(kf_id, T_wc_guess))
        self._keyframes.add(kf_id)

    def add_landmark(self, lm_id: int, xyz_guess: np.ndarray) -> None:
        if lm_id in self._landmarks:
            raise BackendError(f"landmark {lm_id} already exists")
        point = gtsam.Point3(*np.asarray(xyz_guess, float))
        self._pending_values.insert(L(lm_id), point)
        prior = self._factors.landmark_prior(lm_id, xyz_guess)
        if prior is not None:
            self._add_factor(prior)
        self._landmarks.add(lm_id)

    def has_keyframe(self, kf_id: int) -> bool:
        return kf_id in self._keyframes

    def has_landmark(self, lm_id: int) -> bool:
        return lm_id in self._landmarks

    # --- factors --------------------------------------------------------------------------------
    def add_observation(self, kf_id: int, lm_id: int, uv, depth: float = 0.0, level_scale: float = 1.0,
                        dynamic_prob: float = 0.0) -> int:
        """An observation of landmark ``lm_id`` at undistorted pixel ``uv`` from keyframe ``kf_id``.

        With a valid depth it is a virtual stereo factor (u_R = u - fx*b/z) whose noise couples u_R
        to u and adds the depth noise; without, a projection factor. ``level_scale`` (the pyramid
        scale of the keypoint) and ``dynamic_prob`` inflate the noise. Returns a factor handle.
        """
        self._require(kf_id, lm_id)
        factor = self._factors.observation(kf_id, lm_id, uv, depth, level_scale, dynamic_prob)
        return self._add_factor(factor)

    def add_relative_pose(self, kf_a: int, kf_b: int, T_ab: np.ndarray, sigma_t: float, sigma_r_deg: float,
                          kernel: Optional[str] = "huber", kernel_k: float = 1.0) -> int:
        """Constraint that pose b seen from pose a is T_ab (= T_wa^-1 T_wb), e.g. odometry or a loop.

        ``kernel`` is "huber", "cauchy" or None; a Cauchy kernel lets a wrong loop fade out.
        """
        self._require(kf_a)
        self._require(kf_b)
        factor = self._factors.relative_pose(kf_a, kf_b, T_ab, sigma_t, sigma_r_deg, kernel, kernel_k)
        handle = self._add_factor(factor)
        self._relative[handle] = (kf_a, kf_b, np.array(T_ab, dtype=float))
        return handle

    def relative_pose_error(self, handle: int) -> tuple[float, float]:
        """How far the current estimate is from a relative-pose factor's measurement: (metres, degrees)
        of ``T_ab^-1 T_wa^-1 T_wb``. Used to find loops that the rest of the graph contradicts."""
        if handle not in self._relative:
            raise BackendError(f"factor handle {handle} is not a live relative-pose factor")
        a, b, T_ab = self._relative[handle]
        return relative_pose_residual(self.keyframe_pose(a), self.keyframe_pose(b), T_ab)

    def remove_factors(self, handles: Iterable[int]) -> None:
        """Remove factors by their handles: pending ones are dropped, solved ones leave iSAM2 in
        one update. An unknown handle is an error (it would otherwise hide a bookkeeping bug)."""
        handles = list(handles)
        unknown = [h for h in handles if h not in self._pending_factors and h not in self._factor_index]
        if unknown:
            raise BackendError(f"unknown factor handle(s) {unknown} (already removed?)")
        for h in handles:
            self._pending_factors.pop(h, None)
            self._relative.pop(h, None)
        indices = [self._factor_index.pop(h) for h in handles if h in self._factor_index]
        if indices:
            self._run_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), indices)
            self._settle()

    # --- solving --------------------------------------------------------------------------------
    def update(self, extra_updates: Optional[int] = None, relinearize: bool = False) -> None:
        """Add pending factors and variables and solve. ``relinearize`` relinearises on every one of
        the updates whatever ``relinearize_skip`` says: after a loop, many variables move far."""
        with thread_cpu_ms(self.update_cpu_ms):
            self._update(extra_updates, relinearize)

    def _update(self, extra_updates: Optional[int], relinearize: bool) -> None:
        graph = gtsam.NonlinearFactorGraph()
        handles = list(self._pending_factors)
        for handle in handles:
            graph.add(self._pending_factors[handle])
        values, self._pending_values, self._pending_factors = self._pending_values, gtsam.Values(), {}
        result = self._run_update(graph, values, [], relinearize)
        for handle, index in zip(handles, result.getNewFactorsIndices()):
            self._factor_index[handle] = index
        self._settle(extra_updates, relinearize)

    def _settle(self, extra_updates: Optional[int] = None, relinearize: bool = False) -> None:
        n = self.params.extra_updates if extra_updates is None else extra_updates
        for _ in range(n):
            self._run_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], relinearize)
        self._estimate = self._isam.calculateEstimate()

    def _run_update(self, graph, values, remove: list[int], relinearize: bool = False):
        try:
            return self._isam.update(graph, values, remove, force_relinearize=relinearize)
        except RuntimeError as exc:
            raise BackendError(f"iSAM2 update failed: {exc}") from exc

    def optimize_all(self, iterations: Optional[int] = None) -> None:
        """iSAM2 already holds the whole map's solution: ``iterations`` more updates, relinearising."""
        self._update(iterations, True)     # not a keyframe's update: not in update_cpu_ms

    @property
    def holding_back(self) -> bool:
        return False           # solved in process: every update's estimates are there at once

    # --- estimates ------------------------------------------------------------------------------
    def keyframe_pose(self, kf_id: int) -> np.ndarray:
        if self._estimate is None or not self._estimate.exists(X(kf_id)):
            raise BackendError(f"keyframe {kf_id} has no estimate yet (call update())")
        return self._estimate.atPose3(X(kf_id)).matrix()

    def keyframe_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (K,), poses (K,4,4)) of every optimised keyframe, sorted by id."""
        ids = np.array(sorted(k for k in self._keyframes if self._estimated(X(k))), dtype=np.int64)
        flat = gtsam.utilities.extractPose3(self._estimate) if self._estimate is not None else np.zeros((0, 12))
        poses = np.tile(np.eye(4), (len(flat), 1, 1))
        poses[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
        poses[:, :3, 3] = flat[:, 9:]
        return ids, poses

    def landmark_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (M,), positions (M,3)) of every optimised landmark, sorted by id."""
        ids = np.array(sorted(j for j in self._landmarks if self._estimated(L(j))), dtype=np.int64)
        xyz = gtsam.utilities.extractPoint3(self._estimate) if self._estimate is not None else np.zeros((0, 3))
        return ids, np.asarray(xyz).reshape(-1, 3)

    def sync(self) -> None:
        """Solved in this process: every update is already applied."""

    def close(self) -> None:
        """Nothing held open."""

    @property
    def num_factors(self) -> int:
        return len(self._factor_index)

    # --- helpers --------------------------------------------------------------------------------
    def _estimated(self, key: int) -> bool:
        return self._estimate is not None and self._estimate.exists(key)

    def _require(self, kf_id: int, lm_id: Optional[int] = None) -> None:
        if kf_id not in self._keyframes:
            raise BackendError(f"unknown keyframe {kf_id}: add_keyframe() it first")
        if lm_id is not None and lm_id not in self._landmarks:
            raise BackendError(f"unknown landmark {lm_id}: add_landmark() it first")

    def _add_factor(self, factor) -> int:
        handle = self._next_handle
        self._next_handle += 1
        self._pending_factors[handle] = factor
        return handle
