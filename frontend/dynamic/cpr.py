"""Sub-point-cloud correlation (CPR-SLAM, Yu, Zheng & Ou 2024, seed 000): geometric, needs no detector.

``CprMethod(cfg: CprConfig)`` follows the ``DynamicMethod`` protocol (``prepare``, then ``process`` before
tracking, ``end_frame`` after). Steps 1-10 need no features, so they are ``prepare`` (``prepares = True``: the
rejector runs it on a thread while the features are extracted); ``process`` only reads the mask at the
keypoints. Per frame (Sections 3.3-3.8; steps 1-3 live in ``cpr_cloud.py``, 4-8 in ``cpr_icp.py``):

1. Point cloud from every ``sample_step``-th row/column of the depth image; depth > ``max_depth`` invalid.
2. Voxel filter (``voxel_size``): centroid and mean grey value per voxel (Eq. 2), index table + bincount.
3. Moving-least-squares smoothing (``mls_radius``).
4. K-Means on xyz into ``clusters`` sub-clouds (``kmeans2``, k-means++, seed ``seed``). The paper clusters
   "the depth image", i.e. the geometry; intensity is not a clustering feature.
5. Reference frame ``sigma_frame`` frames back (Section 3.4).
6. Sub-pose per sub-cloud (Section 3.5): intensity-assisted ICP (``candidates`` nearest neighbours, the one
   with the largest product of Student-t weights (``student_nu``) of its geometric and intensity residuals is
   the correspondence, Eqs. 4-9; weighted point-to-point step, Eqs. 10-11), then plain ICP. Initial guess:
   constant-velocity model (Eq. 3).
7. Correlation score R(j) (Eq. 12): the whole source cloud moved by sub-pose j; mean of distance plus
   intensity difference to the corresponding reference point.
8. eps = mean(R) + ``mad_scale`` * median(|R - median(R)|) (Eqs. 14-16); R(j) > eps => dynamic sub-cloud.
9. Mask: a disc of ``circle_radius`` px at every point of a dynamic sub-cloud, then a closing.
10. Refinement (Section 3.8, Algorithm 1) with the last ``refine_window`` masks, ``rho_keyframe``,
    ``rho_frame``, ``tau``; edges dilated.

Output: ``prob`` per keypoint = the mask at ``uv_raw``. Default (``refine=False``): the raw mask of this frame,
1 inside / 0 outside - what the paper uses for ordinary frames. With ``refine=True`` Algorithm 1 is applied to
every frame's output: 1 inside the refined mask; outside, a soft value min(0.49, 0.5 * vote / tau) from the
accumulated weight (vote = weight / total weight), so ``prob >= 0.5`` is exactly the refined mask while weaker
evidence still reaches the fusion (before ``refine_window`` masks exist: the raw mask). NaN (abstain) while
no reference frame exists (the first ``sigma_frame`` frames). ``MethodOutput.mask`` is the per-pixel map
(float32). ``info``: points, dynamic_clusters, threshold, scores (R per sub-cloud, NaN for sub-clouds with
< 10 points), ms_<stage> (cloud, kmeans, target, icp, score, mask, refine).

Interpretation of the paper, and deviations (numbers are all in ``CprConfig``):

* Eq. 3 as printed, (T_pre T_last)^-1 T_ref, does not chain (it composes camera->world with world->camera of
  another frame). The ICP needs current camera -> reference camera: T_ref_cw @ inv(T_cur_cw), with T_cur_cw =
  ``ctx.predicted_T_cw`` (ORB-SLAM's T_pre T_last, the same constant-velocity model) and T_ref_cw the pose
  ``end_frame`` stored for the reference. Identity when either is unknown (start, lost tracking). On Bonn crowd
  the identity guess did as well as the odometry guess: two frames apart the motion is small. Not on fr1/rpy's
  fast rotation: registered one frame ahead (while the frame before was tracked) with the prediction two
  frames past the last tracked one, its first 120 frames went from 0.0172 to 0.0292 m ATE, so the System's
  lookahead (slam/runtime/lookahead.py) runs only the detector and ORB ahead, not this registration.
* Eq. 7 is garbled in the paper. We use the Student-t weight of Kerl et al. [27] that it cites,
  w(r) = (nu + 1) / (nu + (r / s)^2), with s = 1.4826 * median(|r - median(r)|) (Eqs. 8-9) over all candidate
  residuals of the sub-cloud in that iteration (over one point's 10 candidates it would be meaningless, and
  centring on the median would prefer a mid-distance candidate to the nearest). Scales are floored (1 cm,
  0.01 intensity) so exact synthetic data cannot divide by zero. The chosen candidate's weight is its weight
  in the point-to-point step ("weighted Euclidean distance"). Plain ICP = nearest neighbour with the geometric
  t-weight (robust IRLS), so the part of a sub-cloud unseen in the reference cannot drag it.
* Data association (``association``, default ``projective``; ``kdtree`` is the paper's exact k nearest
  neighbours in 3-D): the reference is a depth image with a known camera, so a source point moved by its
  sub-pose guess is projected into the reference camera (lens distortion included, through a per-camera
  table) and its candidates are the reference samples in the 3x3 cells (``projective_window`` = 1) of the
  step-4 sampling grid around that pixel - up to 9 candidates, like the paper's 10, found in O(1) without a
  tree (the projective association of KinectFusion and of Kerl et al. [27], whom the paper cites). It serves
  the ICP (Student-t choice among the window's candidates; plain stage: the window's nearest; a point with no
  candidate gets weight 0, robust scales over existing candidates only) and R(j) (min over the window of
  distance + intensity difference). Why: the k-d tree (build ~2 ms, ICP queries ~5 ms, R queries ~5 ms per
  frame) was the largest cost. Projective candidates lie on the point's ray, so a point off every surface
  (a person that moved, an occlusion) would add the metres of depth gap behind it to R(j) and swamp the
  mean: with ``projective`` every static pose's R rose from ~0.05 to ~0.22 on the synthetic test scene and
  recall on generated walking people fell 0.93 -> 0.24. ``score_max_distance`` (5 cm, one voxel) bounds a
  point's distance in R; a point with no candidate counts 5 cm. Measured (``tools/classification.py``,
  60 generated frames of people walking, cpr precision / recall): kdtree 0.758 / 0.927; projective, window 1,
  cap 5 cm 0.820 / 0.927 (cap 3 cm 0.819 / 0.909, 10 cm 0.823 / 0.896, 20 cm 0.843 / 0.873; window 2
  0.732 / 0.912); kdtree with the 5 cm cap 0.743 / 0.960. Bonn numbers: docs/dynamic.md, "cpr's time".
* Iterations: the paper gives no count. ``icp_iterations`` (6) in all, the first ``icp_intensity_iterations``
  (3) intensity-assisted. On Bonn crowd 4, 6, 8, 10 and 20 iterations gave the same masks within noise (more
  iterations slightly worse: static sub-poses drift along their weak directions), so the cheap end is used.
  4 instead of 6 saves little and is not the same per frame (``python tools/cpr_timing.py --frames 200
  --set cpr.icp_iterations=4``, 2026-11-27: sub-poses 8.4 -> 6.9 ms, process 19.5 -> 18.3 ms, the masks'
  dynamic-pixel IoU with 6 iterations' 0.69), so 6 stays.
  Each sub-cloud is registered with at most ``icp_max_points`` (150) evenly spread points; all sub-clouds
  share one candidate query per iteration (75 points: precision 0.820 -> 0.789 on the generated people). A sub-cloud stops iterating when it moves < 0.1 mm and 0.01 deg.
* Registration target: the reference frame's depth samples (every 4th pixel, ~16k points) projected onto their
  voxel's MLS plane, not its 5 cm voxel centroids: against the coarse lattice, nearest-neighbour distances
  measure the lattice (R ~ 3.5 cm for a perfect fit) and point-to-point ICP snaps to it. This cut static false
  positives a little on Bonn (sub-cloud level 8.2 % -> 7.7 % at equal recall). The source stays the voxel cloud.
* Eq. 12's "an additional intensity value is used as a penalty to find the corresponding point": each point's
  correspondence is the one of its candidates (projective: the window's; kdtree: the ``score_candidates`` (4)
  nearest reference points) that minimises distance + |intensity difference|, and R(j) is the mean of that minimum over ``score_points`` (800) evenly
  spread source points (the same points for every pose). Intensities are grey / 255, so 0.1 (25 grey levels)
  weighs like 10 cm. 1 candidate gives the same masks on Bonn and saves ~2 ms.
* Eq. 14 subtracts the median without an absolute value; the MAD it names needs |R - median(R)|. Ties (all R
  equal) flag nothing. ``min_score_ratio`` (default 1.0 = off, the paper) optionally also requires
  R(j) > ratio * median(R): the paper's threshold always flags the upper tail, so static scenes lose 1-2 of 10
  sub-clouds per frame (see "Real data").
* MLS (Section 3.3): PCL-style first order: every voxel point is projected onto the plane fitted (Gaussian
  weights, h = ``mls_radius``, cut at ``mls_radius``) to the voxel points in the 3x3x3 voxels around it
  (a dense lookup table instead of a radius search; exact up to one voxel of reach, ~10x cheaper than a
  cKDTree query), normals in closed form. Points with < 3 neighbours are dropped as outliers (PCL skips them
  too). No second-order polynomial: with 5 cm voxels and a 10 cm radius a quadric adds nothing.
* Mask: the paper projects the dynamic sub-clouds' points. Voxel centroids are 5 cm apart (27 px at 1 m), much
  sparser than 6 px discs, so we mark the depth samples (every 4th pixel) whose voxel lies in a dynamic
  sub-cloud - the same points before voxelisation, at their own pixels: no reprojection, no distortion model,
  and the mask is in raw image coordinates like ``uv_raw``. Discs = dilation with a disc kernel; closing with
  the same kernel.
* Reference frame and keyframes: the keyframe decision comes after tracking, so the current frame's status is
  unknown in ``process``: every frame uses ``sigma_frame`` (2). ``sigma_keyframe`` (5) is used only with
  ``keyframe_recompute``: ``end_frame`` of a keyframe recomputes its mask against the frame 5 back and refines
  it; that mask (weight ``rho_keyframe``) is what later refinements see. Off by default: on Bonn it changed
  nothing measurable and costs a second pass (~20 ms) per keyframe; sigma = 5 for every frame doubled the
  static false positives (larger camera motion, worse sub-poses).
* Refinement (``refine=True``): any frame may become a keyframe and the back end takes a keyframe's features
  before ``end_frame`` can say so, so the paper's keyframe-only refinement cannot be applied to keyframes
  alone; with ``refine`` every frame's output is refined as Algorithm 1 refines a keyframe: weight =
  sum rho_i M_i over the last ``refine_window`` stored masks (``rho_keyframe`` for frames that became
  keyframes, ``rho_frame`` otherwise) plus the current raw mask with ``rho_keyframe`` (the "+1"). Eq. 19's
  threshold tau (N + 1) rho assumes one rho; we use tau times the total weight of the observations (the text:
  "tau times greater than the weight of total observation"), equal to Eq. 19 when all rho are equal. The
  history stores an ordinary frame's raw mask and a keyframe's refined mask. As in the paper, masks are not
  motion-compensated and nothing is refined until ``refine_window`` masks exist. Off by default because it
  made SLAM worse on real data (below): it removes the one-frame false positives, but it also drops people
  who just started moving (a pixel needs ~4 of the last 7 votes) and, without motion compensation, trails
  and shrinks the masks of walking people, so more dynamic features reach tracking.

Real data (Bonn crowd, first 480 frames; people from frame ~230). Mask quality with camera poses from
frame-to-frame ICP (keyframe every 5th frame); "person" pixels = YOLOX-nano person boxes cut to the box's
depth layer (a rough proxy that also counts people standing still):

===========================  ==========================  ============================================
setting                      static frames 0-199:        frames with people: person-pixel recall /
                             masked pixels, frames hit   precision, masked non-person pixels
===========================  ==========================  ============================================
default (paper, raw mask)    16.1 %, 98 %                0.56 / 0.53, 10.7 %
min_score_ratio 1.2          5.7 %, 49 %                 0.52 / 0.52, 8.5 %
refine (Algorithm 1)         5.4 %, 81 %                 0.42 / 0.49, 8.5 %
ratio 1.2 + refine           1.7 %, 21 %                 0.37 / 0.45, 7.0 %
ratio 1.3 + refine           0.6 %, 9 %                  0.31 / 0.41, 5.4 %
===========================  ==========================  ============================================

Full system (``-c bonn -c dynamic_cpr``, ATE RMSE, K-Means seeds 0/1/2): no dynamic handling 0.75 m;
raw mask (default) 0.07 / 0.20 / 0.27 m; ratio 1.2 0.19 / 0.21 / 0.29 m; refine 0.60 / 0.41 / 0.48 m;
raw mask union refined mask 0.22 m and raw mask plus soft votes 0.23 m (seed 0 only).

Moving people are masked whole when their sub-cloud is flagged; misses are slow or still people and sub-clouds
that mix a person with background (K = 10 is coarse for a crowd). Static scenes always lose the 1-2
sub-clouds whose sub-pose drifted most: a ~1 cm drift of a small sub-cloud's sub-pose moves R of the whole
cloud by up to ~60 %, even on exact synthetic data.

Time: ~10 ms median per Bonn crowd frame alone on a core (``python tools/cpr_timing.py
../shared/data/rgbd_bonn_crowd_first480 --frames 480``, 2026-12-02; the first run on a machine compiles the
kernels, ~20 s, numba's cache after). How it got there (the projective association, the robust scales'
shared column, the compiled kernels), each step with its measurements: ``docs/dynamic.md``, "cpr's time".
The paper reports 213 ms on a Jetson Orin.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from frontend.dynamic.base import DynamicContext, MethodOutput, keypoints_in_mask
from frontend.dynamic.cpr_assoc import ProjectiveGrid
from frontend.dynamic.cpr_cloud import (CellTable, Cloud, build_cloud, mls_smooth, sample_grid,  # noqa: F401
                                        voxel_filter, _smallest_eigvec)
from frontend.dynamic.cpr_icp import (cluster, correlation_scores, mad_threshold, sub_poses,  # noqa: F401
                                      _MIN_CLUSTER_POINTS)
from slam.core.dynamic_config import CprConfig
from slam.core.frame import FeatureFrame
from slam.core.geometry import invert


# --- masks -------------------------------------------------------------------------------------------------


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def samples_to_mask(shape: tuple[int, int], pix: np.ndarray, radius: int) -> np.ndarray:
    """Disc of ``radius`` px around every (row, col) in ``pix``, then a closing: uint8 {0,1} mask.

    Computed on the samples' bounding box grown by 3 * radius + 2 (dilation, then the closing's dilation and
    erosion): outside it every stage is 0, and the erosion reads the box's inner border only at pixels that
    are still 0 there, so the result equals the whole-image computation at a fraction of the area."""
    mask = np.zeros(shape, np.uint8)
    if len(pix) == 0:
        return mask
    pad = 3 * radius + 2
    lo = np.maximum(pix.min(axis=0) - pad, 0)
    hi = np.minimum(pix.max(axis=0) + pad + 1, shape)
    roi = np.zeros((hi[0] - lo[0], hi[1] - lo[1]), np.uint8)
    roi[pix[:, 0] - lo[0], pix[:, 1] - lo[1]] = 1
    kernel = _disc(radius)
    roi = cv2.dilate(roi, kernel)
    mask[lo[0]:hi[0], lo[1]:hi[1]] = cv2.morphologyEx(roi, cv2.MORPH_CLOSE, kernel)
    return mask


def refine_mask(history: list[tuple[np.ndarray, float]], current: np.ndarray, rho_current: float, tau: float,
                dilate_radius: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1: weight = sum rho_i M_i over history + rho_current * current; dynamic where the weight
    exceeds tau times the total weight. Returns (refined uint8 mask, weight / total weight)."""
    weight = current.astype(np.float32) * np.float32(rho_current)
    total = float(rho_current)
    for mask, rho in history:
        weight += mask.astype(np.float32) * np.float32(rho)
        total += float(rho)
    refined = (weight > tau * total).astype(np.uint8)
    if dilate_radius > 0 and refined.any():
        refined = cv2.dilate(refined, _disc(dilate_radius))
    return refined, weight / np.float32(total)


def soft_probability(refined: np.ndarray, fraction: np.ndarray, tau: float) -> np.ndarray:
    """1 inside the refined (dilated) mask; elsewhere the vote fraction scaled so that tau maps to 0.5,
    capped at 0.49: ``>= 0.5`` is exactly the refined mask, weaker evidence stays visible to the fusion."""
    soft = np.minimum(np.float32(0.49), fraction * np.float32(0.5 / max(tau, 1e-6)))
    return np.where(refined > 0, np.float32(1.0), soft).astype(np.float32)


# --- the method --------------------------------------------------------------------------------------------


@dataclass
class _Past:
    cloud: Cloud
    T_cw: Optional[np.ndarray]


class CprMethod:
    """Sub-point-cloud correlation. See the module docstring for the algorithm and the choices made."""

    name = "cpr"
    needs_detector = False
    prepares = True
    measures_motion = True

    def __init__(self, cfg: Optional[CprConfig] = None):
        self.cfg = cfg or CprConfig()
        self._past: deque[_Past] = deque(maxlen=max(self.cfg.sigma_frame, self.cfg.sigma_keyframe) + 1)
        self._masks: deque[tuple[np.ndarray, float]] = deque(maxlen=max(1, self.cfg.refine_window))
        self._grid_key = None
        self._cells = CellTable()
        self._pending: Optional[dict] = None
        self._prepared: Optional[tuple] = None     # (ctx, prob map or None = abstain, info, stage ms)
        self.timings: dict[str, float] = {}

    # -- public --
    def prepare(self, ctx: DynamicContext) -> None:
        """Everything but the keypoint lookup: the cloud, the sub-poses, the scores and the mask need only
        the depth, the grey image and the predicted pose, so the rejector runs this on a thread while the
        features are extracted (``ctx.frame`` may still be None). ``process`` finishes the frame."""
        self._flush_pending()
        times: dict[str, float] = {}
        t0 = time.perf_counter()
        cloud = self._cloud(ctx)
        times["cloud"] = (time.perf_counter() - t0) * 1e3
        pending = {"cloud": cloud, "raw": None, "refined": None}
        self._pending = pending
        ref = self._reference(self.cfg.sigma_frame)
        if ref is None or len(cloud) < self.cfg.clusters * _MIN_CLUSTER_POINTS or len(ref.cloud) < 10:
            self._prepared = (ctx, None, {"abstain": 1}, times)
            return
        raw, info = self._raw_mask(cloud, ref, ctx.predicted_T_cw, times)
        pending["raw"] = raw
        t0 = time.perf_counter()
        prob_map = raw.astype(np.float32)
        if self.cfg.refine and len(self._masks) >= self.cfg.refine_window:
            refined, fraction = refine_mask(list(self._masks), raw, self.cfg.rho_keyframe, self.cfg.tau,
                                            self.cfg.circle_radius)
            pending["refined"] = refined
            prob_map = soft_probability(refined, fraction, self.cfg.tau)
        times["refine"] = (time.perf_counter() - t0) * 1e3
        self._prepared = (ctx, prob_map, info, times)

    def process(self, ctx: DynamicContext) -> MethodOutput:
        prepared, self._prepared = self._prepared, None
        if prepared is None or prepared[0] is not ctx:     # not prepared for this frame: do it now
            self.prepare(ctx)
            prepared, self._prepared = self._prepared, None
        _, prob_map, info, times = prepared
        n = len(ctx.frame)
        self.timings = times
        info = {**info, **{f"ms_{k}": v for k, v in times.items()}}
        if prob_map is None:
            return MethodOutput(np.full(n, np.nan), None, info)
        prob = keypoints_in_mask(prob_map, ctx.frame.uv_raw).astype(float) if n else np.zeros(0)
        return MethodOutput(prob, prob_map, info)

    def end_frame(self, ctx: DynamicContext, output: MethodOutput, T_cw: Optional[np.ndarray],
                  is_keyframe: bool) -> None:
        pending = self._pending
        if pending is None:
            return
        self._pending = None
        T = None if T_cw is None else np.asarray(T_cw, float).copy()
        if is_keyframe and self.cfg.keyframe_recompute:
            ref = self._reference(self.cfg.sigma_keyframe)
            if ref is not None and pending["raw"] is not None:
                raw, _ = self._raw_mask(pending["cloud"], ref, T if T is not None else ctx.predicted_T_cw, {})
                pending["raw"] = raw
                pending["refined"] = None
                if len(self._masks) >= self.cfg.refine_window:
                    pending["refined"], _ = refine_mask(list(self._masks), raw, self.cfg.rho_keyframe, self.cfg.tau,
                                                        self.cfg.circle_radius)
        self._store(pending, T, is_keyframe)

    # -- internals --
    def _flush_pending(self) -> None:
        """A frame whose end_frame never came is kept as an ordinary frame with an unknown pose."""
        if self._pending is not None:
            self._store(self._pending, None, False)
            self._pending = None

    def _store(self, pending: dict, T_cw: Optional[np.ndarray], is_keyframe: bool) -> None:
        self._past.append(_Past(pending["cloud"], T_cw))
        mask = pending["refined"] if (is_keyframe and pending["refined"] is not None) else pending["raw"]
        if mask is not None:
            self._masks.append((mask, self.cfg.rho_keyframe if is_keyframe else self.cfg.rho_frame))

    def _reference(self, sigma: int) -> Optional[_Past]:
        if sigma < 1 or len(self._past) < sigma:
            return None
        return self._past[-sigma]

    def _cloud(self, ctx: DynamicContext) -> Cloud:
        h, w = ctx.depth.shape[:2]
        cam = ctx.camera
        key = (h, w, self.cfg.sample_step, cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion)
        if key != self._grid_key:
            self._pix, self._rays = sample_grid(cam, h, w, self.cfg.sample_step)
            self._proj_grid = ProjectiveGrid(cam, h, w, self.cfg.sample_step, self.cfg.projective_window)
            self._grid_key = key
        gray = ctx.gray if ctx.gray is not None else cv2.cvtColor(ctx.rgb, cv2.COLOR_BGR2GRAY)
        return build_cloud(ctx.depth, gray, self._pix, self._rays, self.cfg, cam.min_depth, self._cells)

    def _raw_mask(self, cloud: Cloud, ref: _Past, predicted_T_cw: Optional[np.ndarray],
                  times: dict[str, float]) -> tuple[np.ndarray, dict]:
        cfg = self.cfg
        t0 = time.perf_counter()
        labels = cluster(cloud.xyz, cfg.clusters, cfg.seed)
        times["kmeans"] = (time.perf_counter() - t0) * 1e3
        init = np.eye(4)
        if predicted_T_cw is not None and ref.T_cw is not None:
            init = ref.T_cw @ invert(np.asarray(predicted_T_cw, float))
        t0 = time.perf_counter()
        if cfg.association == "projective" and ref.cloud.shape == cloud.shape:
            target = ref.cloud.projective_target(self._proj_grid)
        else:
            target = ref.cloud.target()                  # builds the dense k-d tree once per reference
        times["target"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        poses, valid = sub_poses(cloud.xyz, cloud.intensity, labels, cfg.clusters, target, init, cfg)
        times["icp"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        r = np.full(cfg.clusters, np.nan)
        if np.any(valid):
            r[valid] = correlation_scores(cloud.xyz, cloud.intensity, poses[valid], target, cfg)
        eps = mad_threshold(r[valid], cfg.mad_scale) if np.any(valid) else np.inf
        dynamic = valid & (r > eps + 1e-9 * abs(eps))     # all-equal scores flag nothing
        if cfg.min_score_ratio > 1.0 and np.any(valid):
            dynamic &= r > cfg.min_score_ratio * np.median(r[valid])
        times["score"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        point_dyn = np.zeros(len(cloud) + 1, bool)       # last slot: samples whose voxel was dropped
        point_dyn[:-1] = dynamic[labels]
        sample_dyn = point_dyn[cloud.sample_point]
        mask = samples_to_mask(cloud.shape, cloud.sample_pix[sample_dyn], cfg.circle_radius)
        times["mask"] = (time.perf_counter() - t0) * 1e3
        info = {"points": len(cloud), "dynamic_clusters": int(dynamic.sum()), "threshold": float(eps),
                "scores": [float(x) for x in r]}
        return mask, info


def compile_kernels() -> MethodOutput:
    """Compile (or load from numba's cache) every kernel cpr runs, with the types a run gives them: three
    frames of a tilted plane with a block moving in front of it; returns the last frame's output. ``.ci/run``
    calls it once before the tests, so that the test processes load the kernels instead of each compiling
    them (~20 s)."""
    from slam.core.camera import PinholeCamera

    h, w = 64, 96
    camera = PinholeCamera(200.0, 200.0, 47.5, 31.5, w, h)      # samples ~4 cm apart at 2 m: MLS keeps them
    rows, cols = np.mgrid[0:h, 0:w]
    gray = ((rows * 7 + cols * 13) % 256).astype(np.uint8)
    rgb = np.dstack([gray] * 3)
    method = CprMethod(CprConfig(clusters=3))
    empty = FeatureFrame(0, 0.0, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 32), np.uint8),
                         np.zeros(0), np.zeros(0), np.zeros(0), np.ones(1))
    for i in range(3):
        depth = (2.0 + 0.01 * cols).astype(np.float32)
        depth[10:40, 8 + 6 * i:40 + 6 * i] = 1.2                 # the block moves 6 px a frame
        ctx = DynamicContext(empty, rgb, gray, depth, camera, predicted_T_cw=np.eye(4))
        out = method.process(ctx)
        method.end_frame(ctx, out, np.eye(4), False)
    return out
