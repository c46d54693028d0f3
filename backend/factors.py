"""What both graph back ends share: parameters, calibration, and the factors built from observations.

``FactorGraphBackend`` (iSAM2 over the whole map, backend/graph.py) and ``LocalWindowBackend`` (local
bundle adjustment over a window of covisible keyframes, backend/window_graph.py) build the same factors
from the same measurements, so one run's numbers can be compared across them: a keypoint with depth
is a virtual stereo factor, without depth a projection factor, both under a Huber kernel with the
noise inflated by pyramid level and dynamic probability; relative poses are BetweenFactorPose3.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Optional

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from slam.core.config import BackendConfig
from slam.core.errors import RuntimeFailure


_MONO_HUBER_K = float(np.sqrt(5.991))   # ORB-SLAM's chi-square bound (95 %, 2 dof) for a keypoint without depth


class BackendError(RuntimeFailure, RuntimeError):
    """The graph cannot accept a request (unknown variable, singular system, ...)."""


@dataclass(frozen=True)
class StereoCalibration:
    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float


def _config_default(name: str):
    """The default of ``backend.<name>`` in the run config: one set of defaults for both entry points."""
    return BackendConfig.model_fields[name].default


@dataclass
class BackendParams:
    """What the graph needs. The shared parameters default to the config's ``backend`` section, so
    ``FactorGraphBackend(BackendParams(), calib)`` computes what a run with default settings does."""

    relinearize_threshold: float = _config_default("relinearize_threshold")
    relinearize_skip: int = _config_default("relinearize_skip")
    extra_updates: int = _config_default("extra_updates")
    pixel_sigma: float = _config_default("pixel_sigma")
    depth_noise_coeff: float = _config_default("depth_noise_coeff")
    huber_k: float = _config_default("huber_k")
    max_dynamic_inflation: float = _config_default("max_dynamic_inflation")
    prior_sigma: float = 1e-4
    # A very weak prior (metres) at each landmark's first estimate. It never competes with real
    # observations (1 px at 3 m is ~6 mm), but keeps the system solvable when every observation of a
    # landmark stops informing it: a stereo factor whose point falls behind its camera (e.g. after
    # a loop correction moves keyframes) has zero Jacobians, and iSAM2 throws IndeterminantLinearSystem.
    landmark_prior_sigma: float = 100.0

    @classmethod
    def from_config(cls, cfg: BackendConfig) -> "BackendParams":
        """The graph's parameters from a run's ``backend`` section (the priors keep their defaults)."""
        shared = {f.name: getattr(cfg, f.name) for f in fields(cls) if f.name in BackendConfig.model_fields}
        return cls(**shared)


def pose3(T: np.ndarray) -> gtsam.Pose3:
    """A gtsam pose from a 4x4 matrix; the rotation is re-orthonormalised (gtsam does not check)."""
    T = np.asarray(T, dtype=float)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return gtsam.Pose3(gtsam.Rot3(R), gtsam.Point3(*T[:3, 3]))


class FactorBuilder:
    """GTSAM factors from measurements, with the noise models cached by their parameters."""

    def __init__(self, params: BackendParams, calibration: StereoCalibration):
        self.params = params
        self.calibration = c = calibration
        self._K_stereo = gtsam.Cal3_S2Stereo(c.fx, c.fy, 0.0, c.cx, c.cy, c.baseline)
        self._K_mono = gtsam.Cal3_S2(c.fx, c.fy, 0.0, c.cx, c.cy)
        self._noise_cache: dict[tuple, gtsam.noiseModel.Base] = {}
        self._sqrt_info_cache: dict[tuple, np.ndarray] = {}     # (sigma px, inflation) -> stereo noise's S

    def first_pose_prior(self, kf_id: int, T_wc: np.ndarray) -> gtsam.NonlinearFactor:
        """The tight prior on the first keyframe that fixes the gauge (where the map starts)."""
        noise = gtsam.noiseModel.Isotropic.Sigma(6, self.params.prior_sigma)
        return gtsam.PriorFactorPose3(X(kf_id), pose3(T_wc), noise)

    def landmark_prior(self, lm_id: int, xyz: np.ndarray) -> Optional[gtsam.NonlinearFactor]:
        if self.params.landmark_prior_sigma <= 0:
            return None
        noise = self._noise_cache.setdefault(
            ("landmark_prior",), gtsam.noiseModel.Isotropic.Sigma(3, self.params.landmark_prior_sigma))
        return gtsam.PriorFactorPoint3(L(lm_id), gtsam.Point3(*np.asarray(xyz, float)), noise)

    def observation(self, kf_id: int, lm_id: int, uv, depth: float = 0.0, level_scale: float = 1.0,
                    dynamic_prob: float = 0.0) -> gtsam.NonlinearFactor:
        """With a valid depth a virtual stereo factor (u_R = u - fx*b/z) whose noise couples u_R to u
        and adds the depth noise; without, a projection factor. ``level_scale`` (the pyramid scale of
        the keypoint) and ``dynamic_prob`` inflate the noise."""
        sigma_px, inflation = self._noise_sigmas(level_scale, dynamic_prob)
        u, v = float(uv[0]), float(uv[1])
        if depth > 0:
            measurement = gtsam.StereoPoint2(u, u - self._disparity(depth), v)
            return gtsam.GenericStereoFactor3D(measurement, self._stereo_noise(sigma_px, inflation), X(kf_id),
                                               L(lm_id), self._K_stereo)
        noise = self._mono_noise(sigma_px)
        return gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(u, v), noise, X(kf_id), L(lm_id), self._K_mono)

    def observation_arrays(self, uv, depth: float = 0.0, level_scale: float = 1.0,
                           dynamic_prob: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
        """``observation``'s factor as arrays (``backend.window_solver``): the measurement (u_L, u_R, v; u_R 0
        without depth), the square-root information S of its noise (S'S = covariance^-1; the u_R row 0 without
        depth) and its Huber threshold: the same noise as the factor's."""
        sigma_px, inflation = self._noise_sigmas(level_scale, dynamic_prob)
        u, v = float(uv[0]), float(uv[1])
        if depth > 0:
            key = (sigma_px, inflation)
            if key not in self._sqrt_info_cache:
                self._sqrt_info_cache[key] = np.linalg.cholesky(np.linalg.inv(self._stereo_covariance(*key))).T
            return np.array([u, u - self._disparity(depth), v]), self._sqrt_info_cache[key], float(self.params.huber_k)
        return np.array([u, 0.0, v]), np.diag([1.0 / sigma_px, 0.0, 1.0 / sigma_px]), _MONO_HUBER_K

    @staticmethod
    def relative_pose(kf_a: int, kf_b: int, T_ab: np.ndarray, sigma_t: float, sigma_r_deg: float,
                      kernel: Optional[str] = "huber", kernel_k: float = 1.0) -> gtsam.NonlinearFactor:
        """Pose b seen from pose a is T_ab; ``kernel`` "huber", "cauchy" or None."""
        sigmas = np.r_[np.full(3, np.radians(sigma_r_deg)), np.full(3, sigma_t)]
        noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        if kernel == "huber":
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(kernel_k), noise)
        elif kernel == "cauchy":
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(kernel_k), noise)
        elif kernel is not None:
            raise BackendError(f"unknown kernel '{kernel}' (use 'huber', 'cauchy' or None)")
        return gtsam.BetweenFactorPose3(X(kf_a), X(kf_b), pose3(T_ab), noise)

    def _dynamic_inflation(self, p: float) -> float:
        p = min(max(float(p), 0.0), 1.0)
        return min(1.0 / max(1.0 - p, 1e-6), np.sqrt(self.params.max_dynamic_inflation))

    def _noise_sigmas(self, level_scale: float, dynamic_prob: float) -> tuple[float, float]:
        """(pixel sigma, inflation) of an observation, rounded to 3 decimals: the noise models' cache keys."""
        inflation = self._dynamic_inflation(dynamic_prob)
        return round(self.params.pixel_sigma * level_scale * inflation, 3), round(inflation, 3)

    def _disparity(self, depth: float) -> float:
        return self.calibration.fx * self.calibration.baseline / depth

    def _stereo_covariance(self, sigma_px: float, inflation: float) -> np.ndarray:
        """u_R = u_L - d shares u_L's pixel noise; the disparity adds the sensor's depth noise,
        sigma_d = fx*b*sigma_z/z^2 with sigma_z = c*z^2, which makes it depth-independent."""
        sigma_d = self.calibration.fx * self.calibration.baseline * self.params.depth_noise_coeff * inflation
        s2 = sigma_px**2
        return np.array([[s2, s2, 0.0], [s2, s2 + sigma_d**2, 0.0], [0.0, 0.0, s2]])

    def _stereo_noise(self, sigma_px: float, inflation: float):
        key = ("stereo", sigma_px, inflation)
        if key not in self._noise_cache:
            base = gtsam.noiseModel.Gaussian.Covariance(self._stereo_covariance(sigma_px, inflation))
            huber = gtsam.noiseModel.mEstimator.Huber.Create(self.params.huber_k)
            self._noise_cache[key] = gtsam.noiseModel.Robust.Create(huber, base)
        return self._noise_cache[key]

    def _mono_noise(self, sigma_px: float):
        key = ("mono", sigma_px)
        if key not in self._noise_cache:
            base = gtsam.noiseModel.Isotropic.Sigma(2, sigma_px)
            huber = gtsam.noiseModel.mEstimator.Huber.Create(_MONO_HUBER_K)
            self._noise_cache[key] = gtsam.noiseModel.Robust.Create(huber, base)
        return self._noise_cache[key]
