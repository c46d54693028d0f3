"""Checks on every frame a run reads, before the System sees it (used by ``slam.run.pipeline``).

- A colour image whose size differs from the camera's (``camera.width`` x ``camera.height``) would be
  projected with intrinsics that do not belong to it: every pose from it would be wrong. The frame
  is skipped with a warning naming the file and both sizes, and listed in the summary's
  ``skipped_files``, like an unreadable file. When the first frames all have one wrong size, the
  camera configuration is what is wrong, not the frames: that is an error saying so.
- A frame without a single valid depth pixel (a sensor dropout) is still processed: the tracker
  follows it against the map without depth, or reports it LOST; no landmark comes from it. A
  stretch of such frames is reported once when it starts and once when depth comes back, and the
  frames are listed in the summary's ``no_depth_frames``.
- NaN, infinite and negative depths become 0 in ``System.process`` itself
  (``slam.runtime.inputs.clean_depth``), whatever feeds it.
"""
from __future__ import annotations

import logging
import warnings
from typing import Optional

import numpy as np

from slam.datasets.base import RGBDFrame
from slam.datasets.tum import DatasetError, DatasetWarning

log = logging.getLogger("dynslam")

WRONG_SIZE_LIMIT = 5   # wrong-size frames before any good one: the camera config is wrong, not the frames


def frame_source(frame: RGBDFrame, dataset_name: str, depth: bool = False) -> str:
    """The file a frame came from, or ``<dataset> frame <i> (t=...)`` for generated frames and bags."""
    path = frame.depth_path if depth else frame.rgb_path
    return str(path) if path is not None else f"{dataset_name} frame {frame.index} (t={frame.timestamp:.6f})"


class InputChecks:
    def __init__(self, width: int, height: int, dataset_name: str):
        self.size = (int(width), int(height))
        self.dataset_name = dataset_name
        self.skipped: list[tuple[str, str]] = []     # (file, reason) of frames not processed
        self.no_depth_frames: list[int] = []
        self._accepted = 0
        self._no_depth_start: Optional[RGBDFrame] = None
        self._no_depth_count = 0

    def accept(self, frame: RGBDFrame) -> bool:
        """Whether the frame can be processed; warns and records it when it cannot."""
        h, w = frame.rgb.shape[:2]
        if (w, h) != self.size:
            source = frame_source(frame, self.dataset_name)
            reason = (f"colour image is {w}x{h} but the camera is {self.size[0]}x{self.size[1]} "
                      "(camera.width x camera.height)")
            self.skipped.append((source, reason))
            if self._accepted == 0 and len(self.skipped) >= WRONG_SIZE_LIMIT and \
                    all(r == reason for _, r in self.skipped[-WRONG_SIZE_LIMIT:]):
                raise DatasetError(f"{self.dataset_name}: the first {len(self.skipped)} frames are all {w}x{h} "
                                   f"but the camera is {self.size[0]}x{self.size[1]}: wrong camera "
                                   "configuration? (pass --config with this camera's intrinsics)")
            warnings.warn(f"{self.dataset_name}: skipping frame {frame.index} ({source}): {reason}",
                          DatasetWarning, stacklevel=2)
            return False
        self._accepted += 1
        return True

    def observe_depth(self, frame: RGBDFrame) -> None:
        """Report the start and the end of stretches of frames without any valid depth."""
        if not np.any((frame.depth > 0) & (frame.depth < np.inf)):   # NaN compares False: never a depth
            if self._no_depth_start is None:
                self._no_depth_start, self._no_depth_count = frame, 0
                warnings.warn(f"{self.dataset_name}: frame {frame.index} "
                              f"({frame_source(frame, self.dataset_name, depth=True)}) has no valid depth; "
                              "tracking without depth against the map (or LOST) until depth comes back",
                              DatasetWarning, stacklevel=2)
            self.no_depth_frames.append(frame.index)
            self._no_depth_count += 1
        elif self._no_depth_start is not None:
            log.warning("%s: depth is back at frame %d after %d frame(s) without any (from frame %d)",
                        self.dataset_name, frame.index, self._no_depth_count, self._no_depth_start.index)
            self._no_depth_start, self._no_depth_count = None, 0
