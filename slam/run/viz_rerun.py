"""A live view of a run with rerun (https://rerun.io): ``dynslam run SEQ --viz`` / ``--viz-save run.rrd``.

``RerunObserver`` is a ``slam.run.pipeline.FrameObserver``. Entities, on the timelines ``frame`` (the
frame index) and ``time`` (seconds since the first frame):

- ``world``                            view coordinates RDF (the SLAM world is the first camera's frame);
- ``world/camera``                     Pinhole (intrinsics, static) + Transform3D of the current pose
                                       (tracked frames only: a lost frame keeps the last pose);
- ``world/camera/image``               the colour image (JPEG-encoded, see ``VizOptions``);
- ``world/camera/depth``               DepthImage in metres (meter=1);
- ``world/camera/image/keypoints``     Points2D, green static .. red dynamic (the fused probability);
- ``world/camera/image/dynamic_mask``  SegmentationImage of the fused dynamic mask (class 1 = dynamic,
                                       probability >= ``tracking.dynamic_threshold``), dynamic handling on;
- ``world/trajectory``                 LineStrips3D of the path so far (tracked frames, following the
                                       optimised keyframes, as ``trajectory.txt``);
- ``world/landmarks``                  Points3D of the map's good landmarks (image colours), at keyframes;
- ``world/ground_truth``               static LineStrips3D when the sequence has ground truth: at the first
                                       tracked frame aligned by that frame alone, at the end re-logged with
                                       the run's ATE alignment (``evaluation.json``), see ``log``;
- ``world/trajectory_final``           static, at the end: the final trajectory;
- ``log``                              TextLog: lost frames, which alignment the ground truth uses.

rerun is an optional extra (``pip install "dynslam[viz]"``): this module imports it only when an
observer is made, so importing dynslam never needs it. ``--viz-save`` records to a temporary file in the
destination folder and renames it when the run ends (also after Ctrl-C or an error): no half-written
.rrd is ever left under the final name.
"""
from __future__ import annotations

import logging
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

from slam.core.atomic_io import fsync_directory
from slam.core.config import SlamConfig
from slam.core.errors import DynslamError, RuntimeFailure
from slam.datasets.base import RGBDFrame
from slam.run.evaluation import EvaluationReport
from slam.run.run_results import RunSummary
from slam.run.sparse_map import sparse_points
from slam.runtime.system import FrameOutput, System

log = logging.getLogger("dynslam")

INSTALL_HINT = 'pip install "dynslam[viz]"'
APPLICATION_ID = "dynslam"
VIEWER_FLUSH_TIMEOUT_S = 10.0   # waiting for a spawned viewer at the end (it may have been closed)
MIN_RERUN_VERSION = (0, 41)   # the version tested (API of set_time(sequence=/duration=), rerun.chunk)


class VizUnavailable(DynslamError):
    """--viz / --viz-save cannot work here (rerun missing, no display): a usage error, exit status 2."""


@dataclass(frozen=True)
class VizOptions:
    """What is logged and how often: a 640x480 frame is 0.9 MB as raw BGR and 1.2 MB as float depth, so
    the colour image goes as JPEG and the depth only every ``depth_every`` frames."""

    jpeg_quality: int = 80        # 0: raw pixels (exact, ~10x larger recordings)
    depth_every: int = 5          # frames between depth images (keyframes always get one)
    landmarks_every: int = 0      # frames between landmark clouds; 0: at keyframes only
    max_trajectory_points: int = 5000   # longer paths are logged thinned (every k-th pose + the last)


def import_rerun() -> Any:
    """The rerun module, or VizUnavailable saying how to install it."""
    try:
        import rerun
    except ImportError as exc:
        raise VizUnavailable(f"the live view needs the rerun SDK, which is not installed ({exc}): "
                             f"{INSTALL_HINT}") from None
    version = tuple(int(p) for p in rerun.__version__.split(".")[:2] if p.isdigit())
    if version < MIN_RERUN_VERSION:
        raise VizUnavailable(f"rerun-sdk {rerun.__version__} is too old (dynslam needs >= "
                             f"{'.'.join(map(str, MIN_RERUN_VERSION))}): {INSTALL_HINT} --upgrade")
    return rerun


def check_display() -> None:
    """--viz spawns a window: on Linux without X11/Wayland the viewer cannot start (rerun would only
    warn and the data go nowhere), so say so up front."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise VizUnavailable("--viz opens the rerun viewer, but this session has no display (DISPLAY and "
                             "WAYLAND_DISPLAY are unset); record with --viz-save run.rrd and open the file "
                             "with `rerun run.rrd` where there is one")


def check_save_path(path: Path | str) -> Path:
    """The --viz-save target: its folder must exist and it must not be a folder itself."""
    target = Path(path)
    if target.is_dir():
        raise VizUnavailable(f"--viz-save {target}: is a folder, expected a file name such as run.rrd")
    if not target.parent.is_dir():
        raise VizUnavailable(f"--viz-save {target}: folder {target.parent} does not exist")
    if not os.access(target.parent, os.W_OK):
        raise VizUnavailable(f"--viz-save {target}: folder {target.parent} is not writable")
    return target


def dynamic_colors(prob: np.ndarray) -> np.ndarray:
    """(N,3) uint8 RGB from dynamic probability in [0, 1]: green (static) to red (dynamic)."""
    p = np.clip(np.nan_to_num(np.asarray(prob, np.float32), nan=0.0), 0.0, 1.0)
    return np.stack([255.0 * p, 255.0 * (1.0 - p), np.zeros_like(p)], axis=1).astype(np.uint8)


def thin_path(xyz: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of a path (every k-th point, always ending on the last)."""
    if len(xyz) <= max_points:
        return xyz
    step = int(np.ceil(len(xyz) / (max_points - 1)))
    return np.concatenate([xyz[::step], xyz[-1:]])


def ground_truth_in_world(gt_poses: np.ndarray, T_world_gt: np.ndarray) -> np.ndarray:
    """(N,3) ground-truth positions in the SLAM world, ``T_world_gt`` mapping the ground truth's frame."""
    return gt_poses[:, :3, 3] @ T_world_gt[:3, :3].T + T_world_gt[:3, 3]


class RerunObserver:
    """Logs a run to a spawned rerun viewer (``save_path`` None) or into an .rrd file (atomically)."""

    def __init__(self, config: SlamConfig, groundtruth: Optional[tuple[np.ndarray, np.ndarray]] = None,
                 save_path: Optional[Path | str] = None, options: VizOptions = VizOptions()):
        self.rr = import_rerun()
        if save_path is None:
            check_display()
        self.save_path = None if save_path is None else check_save_path(save_path)
        self.config = config
        self.options = options
        self.groundtruth = groundtruth
        self._rec: Any = None            # opened at the first frame (nothing to clean up before the run)
        self._tmp_path: Optional[Path] = None
        self._t0: Optional[float] = None
        self._gt_logged = False
        self.frames_logged = 0
        self.frame_ms: list[float] = []   # time spent logging each frame (the view's cost to the run)

    # --- FrameObserver ----------------------------------------------------------------------------
    def on_frame(self, frame: RGBDFrame, output: FrameOutput, system: System) -> None:
        start = time.perf_counter()
        rr, rec = self.rr, self._open()
        if self._t0 is None:
            self._t0 = frame.timestamp
        rec.set_time("frame", sequence=int(output.index))
        rec.set_time("time", duration=float(frame.timestamp - self._t0))
        if output.T_wc is not None:
            rec.log("world/camera", rr.Transform3D(translation=output.T_wc[:3, 3], mat3x3=output.T_wc[:3, :3]))
        else:
            rec.log("log", rr.TextLog(f"frame {output.index}: {output.state.name}", level=rr.TextLogLevel.WARN))
        self._log_images(frame, output, system)
        self._log_trajectory(system)
        if output.T_wc is not None and not self._gt_logged:
            self._log_first_frame_ground_truth(output)
        if self._landmarks_due(output):
            xyz, rgb = sparse_points(system.mapper.map)
            rec.log("world/landmarks", rr.Points3D(xyz, colors=rgb, radii=rr.Radius.ui_points(2.0)))
        self.frames_logged += 1
        self.frame_ms.append((time.perf_counter() - start) * 1e3)

    def on_finish(self, system: System, summary: RunSummary, report: Optional[EvaluationReport]) -> None:
        rr, rec = self.rr, self._open()
        try:
            _, poses, tracked = system.trajectory()
            final = thin_path(poses[tracked][:, :3, 3], self.options.max_trajectory_points)
            rec.log("world/trajectory_final", rr.LineStrips3D([final], colors=[[255, 200, 0]]), static=True)
            if report is not None and self.groundtruth is not None:
                T_world_gt = np.linalg.inv(report.ate.alignment)   # the ATE alignment maps estimate -> gt
                self._log_ground_truth(T_world_gt, "aligned with the run's ATE alignment (evaluation.json)")
        finally:
            self._close(summary.interrupted)

    # --- steps ------------------------------------------------------------------------------------
    def _open(self) -> Any:
        """The recording stream, made at first use: a file sink on a temporary name beside the target,
        or a spawned viewer. Static data (coordinates, intrinsics, annotation) go first."""
        if self._rec is not None:
            return self._rec
        rr = self.rr
        rec = rr.RecordingStream(APPLICATION_ID)
        if self.save_path is None:
            rec.spawn()
        else:
            fd, name = tempfile.mkstemp(prefix=f".{self.save_path.name}.", suffix=".tmp", dir=self.save_path.parent)
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)   # mkstemp makes 0600; a recording is meant to be shared
            os.close(fd)
            self._tmp_path = Path(name)
            rec.save(self._tmp_path)
        self._rec = rec
        cam = self.config.camera
        K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
        rec.log("world", rr.ViewCoordinates.RDF, static=True)   # the first camera's axes: x right, y down
        rec.log("world/camera", rr.Pinhole(image_from_camera=K, resolution=[cam.width, cam.height],
                                           image_plane_distance=0.3), static=True)
        rec.log("world/camera/image/dynamic_mask",
                rr.AnnotationContext([(0, "static", (0, 0, 0, 0)), (1, "dynamic", (255, 0, 0, 110))]), static=True)
        return rec

    def _landmarks_due(self, output: FrameOutput) -> bool:
        """The map only grows at keyframes, so by default that is when its cloud is re-logged."""
        every = self.options.landmarks_every
        return output.is_keyframe if every <= 0 else self.frames_logged % every == 0

    def _log_images(self, frame: RGBDFrame, output: FrameOutput, system: System) -> None:
        rr, rec, opts = self.rr, self._rec, self.options
        if opts.jpeg_quality > 0:
            ok, jpeg = cv2.imencode(".jpg", frame.rgb, [cv2.IMWRITE_JPEG_QUALITY, opts.jpeg_quality])
            if not ok:
                raise RuntimeFailure(f"frame {output.index}: could not encode the colour image as JPEG")
            rec.log("world/camera/image", rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))
        else:
            rec.log("world/camera/image", rr.Image(frame.rgb, color_model="BGR"))
        if output.is_keyframe or self.frames_logged % max(opts.depth_every, 1) == 0:
            rec.log("world/camera/depth", rr.DepthImage(frame.depth, meter=1.0))
        features = system.last_frame
        if features is not None:
            rec.log("world/camera/image/keypoints",
                    rr.Points2D(features.uv_raw, colors=dynamic_colors(features.dynamic_prob),
                                radii=rr.Radius.ui_points(3.0)))
        mask = system.last_dynamic_mask
        if mask is not None:
            classes = (np.nan_to_num(mask, nan=0.0) >= self.config.tracking.dynamic_threshold).astype(np.uint8)
            rec.log("world/camera/image/dynamic_mask", rr.SegmentationImage(classes))

    def _log_trajectory(self, system: System) -> None:
        _, poses, tracked = system.trajectory(smoothed=False)   # every frame: the smoother's solve is for the end
        xyz = thin_path(poses[tracked][:, :3, 3], self.options.max_trajectory_points)
        self._rec.log("world/trajectory", self.rr.LineStrips3D([xyz], colors=[[0, 160, 255]]))

    def _log_first_frame_ground_truth(self, output: FrameOutput) -> None:
        """Until the run's alignment exists (at the end), align the ground truth by the first tracked
        frame: the ground-truth pose nearest in time is put onto that frame's estimate."""
        self._gt_logged = True
        if self.groundtruth is None or len(self.groundtruth[0]) == 0:
            return
        gt_t, gt_poses = self.groundtruth
        nearest = int(np.argmin(np.abs(gt_t - output.timestamp)))
        if abs(gt_t[nearest] - output.timestamp) > self.config.max_association_dt:
            self._rec.log("log", self.rr.TextLog("ground truth: no pose near the first tracked frame; "
                                                 "shown at the end, after the ATE alignment"))
            return
        T_world_gt = output.T_wc @ np.linalg.inv(gt_poses[nearest])
        self._log_ground_truth(T_world_gt, f"aligned by the first tracked frame ({output.index}) until the run ends")

    def _log_ground_truth(self, T_world_gt: np.ndarray, how: str) -> None:
        xyz = thin_path(ground_truth_in_world(self.groundtruth[1], T_world_gt), self.options.max_trajectory_points)
        self._rec.log("world/ground_truth", self.rr.LineStrips3D([xyz], colors=[[160, 160, 160]]), static=True)
        self._rec.log("log", self.rr.TextLog(f"ground truth: {how}"))

    def _close(self, interrupted: bool) -> None:
        """Flush and close the stream; a recording is renamed onto its final name only once complete."""
        rec, self._rec = self._rec, None
        if rec is None:
            return
        if self._tmp_path is None:   # a viewer the user may have closed: its end is not the run's failure
            try:
                rec.flush(timeout_sec=VIEWER_FLUSH_TIMEOUT_S)
                rec.disconnect()
            except Exception as exc:
                log.warning("rerun viewer: the last data may not have arrived (%s)", exc)
            return
        try:
            rec.flush()
            rec.disconnect()   # closes the file sink: writes the rest and the footer
        except Exception as exc:
            self._discard_tmp()
            raise RuntimeFailure(f"--viz-save {self.save_path}: the recording could not be written ({exc})") from exc
        try:
            os.replace(self._tmp_path, self.save_path)
        except OSError as exc:
            self._discard_tmp()
            raise RuntimeFailure(f"--viz-save: could not move the recording to {self.save_path}: {exc}") from exc
        fsync_directory(self.save_path.parent)
        note = " (run interrupted: frames up to the stop)" if interrupted else ""
        cost = f", {np.median(self.frame_ms):.1f} ms/frame median to log" if self.frame_ms else ""
        log.info("rerun recording written to %s%s%s; open it with `rerun %s`", self.save_path, note, cost,
                 self.save_path)

    def _discard_tmp(self) -> None:
        if self._tmp_path is not None and self._tmp_path.exists():
            self._tmp_path.unlink()
