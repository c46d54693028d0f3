"""Generated people composited in 3-D into a real RGB-D sequence, with exact masks.

The hard scenes of ``synthetic_scenes`` put their people in a generated room; real sequences have what a
generated room lacks (a hand-held camera's blur and rolling shutter, sensor noise, depth holes, real
texture), and issue 11's hidden check composites people into full TUM sequences. ``CompositeScene`` does
the same with the sequences we have: every frame is the real colour and depth, and the scripted people are
ray-cast from the frame's ground-truth camera pose and replace the real pixels wherever they are in front
of the real surface (or where the sensor has no depth). The moving-people mask is exact by construction,
and the clean sequence (``scene="none"``) is the same frames untouched, so ATE can be compared with it.

- **Poses.** Motion capture, interpolated to the colour frame's timestamp (rotation by slerp, position
  linearly); a frame outside the capture's time range takes its nearest end.
- **World.** The motion-capture frame of TUM and Bonn has z up with the floor near z = 0 (the hand-held
  camera is ~1.5 m above it), the generated people's world; they walk on z = 0.
- **Camera.** The real intrinsics, pinhole: the real images are not undistorted (fr1's lens moves a corner
  pixel by up to ~10 px), so a person is drawn where an undistorted camera would see them. Colour and depth
  agree with each other and the person moves anyway; what this leaves out is only that part of the lens.
- **Scripts.** The four hard scenes (``HARD_SCENES``), scripted against the real camera path as against the
  generated one, and the two compositions of the hidden check: ``two_walk`` (two people walking across
  the view in opposite directions) and ``walk_stand`` (one standing the whole time, one walking past).
  A person behind a real surface is hidden by it, as a real one would be.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .base import RGBDFrame
from .synthetic import SyntheticSequence
from .synthetic_bodies import mover_bodies
from .synthetic_movers import Mover
from .synthetic_primitives import sensed_depth
from .synthetic_scenes import BLUR_SAMPLES, EXPOSURE_S, HARD_SCENE_KINDS, HARD_SCENES, HardScene, _walker
from .tum import DatasetError, TumDataset

COMPOSITE_SCENES = ("none",) + HARD_SCENES + ("two_walk", "walk_stand")

_KINDS = {"none": (), **HARD_SCENE_KINDS, "two_walk": ("person",) * 2, "walk_stand": ("person",) * 2}


class CompositeScene(HardScene):
    """A scripted scene (``COMPOSITE_SCENES``) composited into the first ``n_frames`` frames of the real
    TUM-layout sequence ``base`` (a folder or a ``TumDataset``; it needs ``groundtruth.txt``), seen with
    the pinhole ``intrinsics`` (fx, fy, cx, cy) of its camera. ``timestamps`` start at 0."""

    def __init__(self, scene: str, base: Union[str, Path, TumDataset], intrinsics: tuple[float, float, float, float],
                 n_frames: Optional[int] = None, seed: int = 0) -> None:
        if scene not in COMPOSITE_SCENES:
            raise ValueError(f"unknown composite scene {scene!r}; expected one of {', '.join(COMPOSITE_SCENES)}")
        self.base = base if isinstance(base, TumDataset) else TumDataset(base)
        self._last_real: Optional[RGBDFrame] = None
        gt = self.base.groundtruth()
        if gt is None:
            raise DatasetError(f"{self.base.root}: no groundtruth.txt; people are composited from the "
                               "ground-truth camera poses")
        n = len(self.base) if n_frames is None else min(int(n_frames), len(self.base))
        if n < 2:
            raise DatasetError(f"{self.base.root}: {n} frame(s); a composite needs at least 2")
        stamps = np.asarray(self.base.timestamps[:n], float)
        self._t0 = float(stamps[0])
        self._times = stamps - self._t0
        gt_t, gt_T = gt
        self._gt_t, self._gt_p = gt_t, gt_T[:, :3, 3]
        self._slerp = Slerp(gt_t, Rotation.from_matrix(gt_T[:, :3, :3]))
        first = self.base[0]
        height, width = first.depth.shape
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        self.scene = scene
        # The scripts time their people from the middle of the sequence (n_frames / fps / 2): the real rate.
        fps = (n - 1) / max(float(self._times[-1]), 1e-9)
        SyntheticSequence.__init__(self, n_frames=n, width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy,
                                   seed=seed, fps=fps, movers=list(_KINDS[scene]))
        self.name = f"{self.base.name}_{scene}" + (f"_seed{seed}" if seed else "")
        self._mover_primitives = [p for m in self.movers for p in m.parts]
        self._no_hit = len(self._tex_w) - 1
        self.coverage = self._coverage()
        self.blurred = self._blurred_frames()
        self.detector_misses = self._misses()

    # -- the real sequence ----------------------------------------------------------------------------

    @property
    def timestamps(self) -> np.ndarray:
        return self._times

    def pose(self, time: float) -> np.ndarray:
        """Ground-truth camera-to-world pose ``time`` seconds after the first frame (interpolated)."""
        t = float(np.clip(self._t0 + time, self._gt_t[0], self._gt_t[-1]))
        pose = np.eye(4)
        pose[:3, :3] = self._slerp([t]).as_matrix()[0]
        pose[:3, 3] = [np.interp(t, self._gt_t, self._gt_p[:, a]) for a in range(3)]
        return pose

    # -- compositing ----------------------------------------------------------------------------------

    def _people(self, pose: np.ndarray, time: float, real_depth: np.ndarray):
        """(box frames, depth, face) of the people in front of the real surface, the real depth elsewhere."""
        frames = self._box_frames(pose, time)
        if not self._mover_primitives:
            return frames, real_depth, np.full(real_depth.shape, self._no_hit, np.int64)
        depth, face = self._cast(frames, self._mover_primitives)
        front = (depth > 0) & ((real_depth <= 0) | (depth < real_depth))
        return frames, np.where(front, depth, real_depth).astype(np.float32), np.where(front, face, self._no_hit)

    def _cast_at(self, index: int):
        time = float(self.timestamps[index])
        return self._people(self.pose(time), time, self._real(index).depth)

    def real_holes(self, index: int) -> np.ndarray:
        """HxW bool: where the real frame ``index`` measured no depth. People are drawn there whatever the
        real scene holds (beyond the sensor's range that is what a camera sees; on a black monitor screen or
        in the shadow beside a near edge a real person would be hidden): on fr1/rpy most of walk_stand's and
        stand_walk's moving pixels (docs/dynamic.md, "Most of the composites' moving pixels")."""
        return ~(self._real(index).depth > 0)

    def _real(self, index: int) -> RGBDFrame:
        """The real frame ``index``, the last one kept: ``frame`` and the cast it triggers read it once."""
        real = self._last_real   # read once: a reader thread may render another frame meanwhile
        if real is None or real.index != index:
            real = self.base[index]
            self._last_real = real
        return real

    def frame(self, index: int, cache: bool = True) -> RGBDFrame:
        real = self._real(index)
        time = float(self.timestamps[index])
        frames, depth, face = self._cast_frame(index, cache)
        rgb = self._over(real.rgb, frames, depth, face)
        if index in self.blurred:
            # The person blurs over the exposure; the real pixels carry the real camera's own blur already.
            acc = np.zeros(rgb.shape, np.float32)
            for offset in np.linspace(-EXPOSURE_S / 2, EXPOSURE_S / 2, BLUR_SAMPLES):
                acc += self._over(real.rgb, *self._people(self.pose(time + offset), time + offset, real.depth))
            rgb = np.round(acc / BLUR_SAMPLES).astype(np.uint8)
        sensed = sensed_depth(depth.copy() if cache else depth, self.sensor_min_range_m)
        return RGBDFrame(index=index, timestamp=time, rgb=rgb, depth=sensed, dynamic_mask=self._mask(face, time))

    def _over(self, real_rgb: np.ndarray, frames, depth: np.ndarray, face: np.ndarray) -> np.ndarray:
        person = face != self._no_hit
        if not person.any():
            return real_rgb.copy()
        out = real_rgb.copy()
        out[person] = self._texture(frames, depth, face)[person]
        return out

    def render(self, pose: np.ndarray, time: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The people alone seen from ``pose`` at ``time`` (black, depth 0 where no person is hit): a
        composite has no model of the real room, only its frames (``frame``)."""
        no_room = np.zeros((self.height, self.width), np.float32)
        frames, depth, face = self._people(pose, time, no_room)
        return self._over(np.zeros((self.height, self.width, 3), np.uint8), frames, depth, face), depth

    # -- the scripts ----------------------------------------------------------------------------------

    def _border_time(self) -> float:
        """border: the walker is placed on the left border's line of sight projected on the floor, which is
        the border only while that line is near level. A real hand-held camera pitches: fr1/rpy's looks
        down at the desk at mid-sequence (the left border's line of sight 50 degrees below the horizon),
        where the floor line leaves the view and the whole walk happened out of sight (477 moving pixels in
        400 frames). So the moment is the one of the middle half of the sequence whose left border's line
        of sight is nearest to level (fr1/rpy-400: frame 251, 7 degrees down; the walk spans frames
        161-281, the walker in view on 95 of them, up to 15 % of the image, missed on 31)."""
        fx, _, cx, _ = self.intrinsics
        edge = np.array([-cx / fx, 0.0, 1.0]) / np.hypot(cx / fx, 1.0)
        times = self.timestamps[len(self.timestamps) // 4: max(3 * len(self.timestamps) // 4, 1)]
        if not len(times):
            return super()._border_time()
        pitch = [float((self.pose(float(t))[:3, :3] @ edge)[2]) for t in times]
        return float(times[int(np.argmax(pitch))])

    def _plan_movers(self, kinds) -> list[Mover]:
        if self.scene in HARD_SCENES:
            return super()._plan_movers(kinds)
        if not kinds:
            return []
        look, shape = np.random.default_rng([self.seed, 41]), np.random.default_rng([self.seed, 43])
        bodies = [mover_bodies("person", look, shape)[0] for _ in kinds]
        mid = self.n_frames / self.fps / 2
        if self.scene == "two_walk":
            # Across the view in opposite directions at 1.2 m/s, 1.1 and 1.7 m ahead (horizontally) a
            # second apart around mid-sequence: within the office's depth (fr1's desk edge ~0.8 m, the
            # walls ~2-3 m), so they pass behind the desk and in front of the wall, as people there would.
            return [_walker(bodies[0], self._ahead(mid - 0.5, 1.1), self._across(mid), 1.2, mid - 0.5),
                    _walker(bodies[1], self._ahead(mid + 0.5, 1.7), -self._across(mid), 1.2, mid + 0.5)]
        # walk_stand: one person stands 1.8 m ahead, facing the camera, for the whole sequence (never a
        # moving surface); the other walks across in front of them at 1.2 m, 1.0 m/s.
        spot = self._ahead(mid, 1.8, 0.3)
        start = 2.0 * mid + 1.0                        # still standing when the sequence ends
        return [_walker(bodies[0], spot, self._across(mid), 1.0, start, stand_until=start,
                        face=self._facing_camera(mid, spot)),
                _walker(bodies[1], self._ahead(mid, 1.2), self._across(mid), 1.0, mid)]
