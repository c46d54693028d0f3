"""Seeded synthetic RGB-D sequences: a textured room with boxes, rendered by vectorised ray casting.

Why: tests and the demo need RGB-D data with exact depth and exact ground-truth poses, fast and
without downloads. Everything is deterministic for a seed.

World frame: z up, the room spans x in [-3, 3], y in [-2.5, 2.5], z in [0, 3] metres. Camera frame is
OpenCV's (x right, y down, z forward); poses are camera-to-world 4x4. Each scene primitive is a textured
box with a ``pose_at(time)`` function: the room is a box seen from inside, furniture boxes are seen from
outside. Moving objects (``movers=``: walking people, flying rotating boxes, a chair dragged off by a
person) are further ``Box`` primitives with a time-varying ``pose_at`` and ``dynamic=True``; their paths
are planned against the camera path so that each crosses the view, and every frame carries the exact
per-pixel ``dynamic_mask`` from the ray-cast face map (see ``SyntheticSequence``).

Module layout: the box primitive and its textures are in ``synthetic_primitives``; the movers' model
and paths in ``synthetic_movers``, their looks in ``synthetic_bodies`` and their placement in
``synthetic_planning``. Their public names are re-exported here.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Callable, Iterator, Optional, Sequence, Union

import numpy as np

from .base import DatasetDefaults, RGBDFrame, read_ahead
from .synthetic_movers import MOVER_PRESETS, Mover, WalkLoop, mover_kinds  # noqa: F401  (some re-exported)
from .synthetic_planning import MoverPlanner
from .synthetic_primitives import _EDGES, _FACE_AXES, _NEAR, _SIGNS, TEXEL, Box, add_textures, sensed_depth, static_pose
from .synthetic_primitives import make_texture  # noqa: F401  (re-exported)

_LIGHT = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])


def room_scene(rng: np.random.Generator) -> list[Box]:
    """The default scene: a 6 x 5 x 3 m room, four boxes near the walls (kept >= 1.2 m from the paths)."""
    boxes = [
        Box(np.array([3.0, 2.5, 1.5]), static_pose((0.0, 0.0, 1.5)), inside=True),
        Box(np.array([0.4, 0.45, 0.4]), static_pose((2.1, 1.5, 0.4), 0.3)),
        Box(np.array([0.3, 0.35, 0.75]), static_pose((-2.3, -1.4, 0.75), -0.2)),
        Box(np.array([0.6, 0.3, 0.35]), static_pose((1.7, -1.9, 0.35))),
        Box(np.array([0.12, 0.5, 0.3]), static_pose((-2.85, 0.4, 1.6))),
    ]
    for box in boxes:
        add_textures(box, rng)
    return boxes


def look_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Camera-to-world rotation looking along (yaw, pitch) in the z-up world, then rolled about the view
    axis; camera y points down (OpenCV). Undefined at pitch = +-90 degrees, which the paths never reach."""
    fwd = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c, s = np.cos(roll), np.sin(roll)
    return np.stack([c * right + s * down, -s * right + c * down, fwd], axis=1)


def camera_path(kind: str, seed: int) -> Callable[[float], np.ndarray]:
    """Smooth camera-to-world pose as a function of time (s); sums of sinusoids, so velocity is continuous.

    "orbit": an ellipse (0.5 x 0.35 m) around the room centre at 0.35-0.5 m/s while the view sweeps the
    walls at up to ~30 deg/s with small pitch/roll and a little hand shake. "line": 0.2 m/s along x,
    facing the +y wall. Both keep the camera >= 1.2 m from anything static it sees. "still": a fixed
    camera at (0, -0.9, 1.4) facing the +y wall (3.4 m away), for moving-object tests.
    """
    rng = np.random.default_rng([seed, 7])
    phase, yaw0 = rng.uniform(0, 2 * np.pi, 2)
    shake = rng.uniform(0, 2 * np.pi, 6)

    def orbit(t: float) -> np.ndarray:
        pos = [0.5 * np.cos(t + phase), 0.35 * np.sin(t + phase), 1.4 + 0.08 * np.sin(1.3 * t)]
        pos += 0.004 * np.sin(2 * np.pi * np.array([2.3, 2.9, 3.1]) * t + shake[:3])
        jitter = 0.004 * np.sin(2 * np.pi * np.array([1.7, 2.1, 2.6]) * t + shake[3:])
        rot = look_rotation(yaw0 + 0.3 * t + 0.15 * np.sin(0.9 * t) + jitter[0],
                            -0.08 + 0.1 * np.sin(0.7 * t + 1.0) + jitter[1], 0.05 * np.sin(1.1 * t) + jitter[2])
        return _pose(rot, pos)

    def line(t: float) -> np.ndarray:
        return _pose(look_rotation(np.pi / 2, -0.05, 0.0), [0.8 * np.sin(0.25 * t), -0.5, 1.4])

    def still(t: float) -> np.ndarray:
        return _pose(look_rotation(np.pi / 2, -0.05, 0.0), [0.0, -0.9, 1.4])

    paths = {"orbit": orbit, "line": line, "still": still}
    if kind not in paths:
        raise ValueError(f"unknown camera path {kind!r}; expected one of {sorted(paths)}")
    return paths[kind]


def _pose(rot: np.ndarray, pos) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, pos
    return pose


def _box_hits(d: list[np.ndarray], ol: np.ndarray, half: np.ndarray, inside: bool) -> tuple[np.ndarray, np.ndarray]:
    """Slab test for all rays at once in the box frame: ray(t) = ol + t * d, d one array per axis.

    Returns (t, local face index); t = inf where the ray misses. Inside boxes report the exit face,
    outside boxes the entry face. Per-axis arrays and pairwise minimum/maximum instead of argmin over
    a (3, n) stack: several times faster in numpy.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        side = [np.copysign(np.float32(half[a]), d[a]) for a in range(3)]
        exit_t = [(side[a] - np.float32(ol[a])) / d[a] for a in range(3)]
        if inside:
            t = np.minimum(np.minimum(exit_t[0], exit_t[1]), exit_t[2])
            per_axis = exit_t
        else:
            per_axis = [(-side[a] - np.float32(ol[a])) / d[a] for a in range(3)]
            t = np.maximum(np.maximum(per_axis[0], per_axis[1]), per_axis[2])
            miss = (t > np.minimum(np.minimum(exit_t[0], exit_t[1]), exit_t[2])) | ~(t > 1e-4)
            t[miss] = np.inf
    on1 = t == per_axis[1]
    on2 = (t == per_axis[2]) & ~on1
    on0 = ~(on1 | on2)
    # a ray leaves an inside box through the face it points at, enters an outside box through the other
    positive = (on0 & (d[0] > 0)) | (on1 & (d[1] > 0)) | (on2 & (d[2] > 0))
    if not inside:
        positive = ~positive
    # int16: the int64 arithmetic over every pixel of the room box was a fifth of the ray cast (line profile)
    face = (on1.astype(np.int16) << 1) | (on2.astype(np.int16) << 2) | positive
    return t, face


class SyntheticSequence(DatasetDefaults):
    """A lazily rendered synthetic RGB-D sequence following the ``RGBDDataset`` protocol.

    ``intrinsics`` is (fx, fy, cx, cy) with no distortion; ``groundtruth()`` gives the exact poses.

    ``movers`` adds moving objects (see ``MOVER_PRESETS``): "none" (default; output identical to the
    generator without movers), "boxes" (two 0.4-0.6 m cardboard boxes floating at 0.3-0.8 m/s while
    tumbling at 25-60 deg/s), "people" (three 1.6-1.85 m walking figures at ~1 m/s with swinging
    limbs), "crowd" (both), "drag" (a chair that stands still for the first half, then is dragged off by
    a passing person), a single kind, or a list of these. Each mover walks (or floats) around its own
    rounded-rectangle loop and is planned, by seeded rejection sampling against the camera path, to cross
    the view at its own time spread over the sequence (so paths depend on ``n_frames``), to keep clear of
    the camera, the furniture and the other movers, and to keep the movers' screen rectangles under 40 %
    of the image in nearly all frames. Frames carry ``dynamic_mask``; ``dynamic_mask(i)``, ``mover_ids(i)``
    and ``mover_boxes(i)`` give the ground truth for one frame.
    """

    def __init__(self, n_frames: int = 120, width: int = 640, height: int = 480, fx: float = 525.0,
                 fy: float = 525.0, cx: float = 319.5, cy: float = 239.5, seed: int = 0, fps: float = 30.0,
                 path: str = "orbit", movers: Union[str, Sequence[str]] = "none") -> None:
        self.n_frames, self.width, self.height, self.fps, self.seed = n_frames, width, height, fps, seed
        self.intrinsics = (float(fx), float(fy), float(cx), float(cy))
        self.name = f"synthetic_{path}_seed{seed}"
        self.primitives = room_scene(np.random.default_rng(seed))
        self._path = camera_path(path, seed)
        u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
        self._rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)])  # (3,H,W), z = 1
        kinds = mover_kinds(movers)
        if kinds:
            self.name += "_" + (movers if isinstance(movers, str) else "+".join(movers))
        self.movers: list[Mover] = self._plan_movers(kinds) if kinds else []
        for mover in self.movers:
            mover.parts = list(range(len(self.primitives), len(self.primitives) + len(mover.boxes)))
            for k, box in enumerate(mover.boxes):
                box.pose_at = lambda time, m=mover, k=k: m.part_pose(k, time)
            self.primitives.extend(mover.boxes)
        self._build_atlas()
        primitive_mover = np.full(len(self.primitives) + 1, -1, np.int64)  # the last entry: no hit
        for i, mover in enumerate(self.movers):
            primitive_mover[mover.parts] = i
        self.face_mover = primitive_mover[self.face_primitive]
        """Global face index -> index into ``movers`` (-1: static scene or no hit)."""
        self.sensor_min_range_m = 0.0     # frames' depth: 0 nearer than this (synthetic_primitives.SENSOR_MIN_RANGE_M)
        self._casts: OrderedDict = OrderedDict()
        self._kept: Optional[dict[int, RGBDFrame]] = None   # keep_frames
        # Frame index -> (mover, visible pixels, x0, y0, x1, y1) of every mover in view, noted by every ray
        # cast: a detector standing in for YOLOX (frontend.dynamic.oracle) asks for each frame's boxes after
        # the frame is rendered, and a scene is run under several seeds; without this each question cast the
        # frame again (~30 ms, a sixth of a generated run's time).
        self._mover_extents: dict[int, tuple[tuple[int, int, int, int, int, int], ...]] = {}

    def _build_atlas(self) -> None:
        """Pack all face textures (with baked Lambert shading) into one flat texel array for one gather."""
        chunks, off, w, h = [], [], [], []
        for box in self.primitives:
            for f, tex in enumerate(box.textures):
                normal = np.zeros(3)
                normal[f // 2] = (1.0 if f % 2 else -1.0) * (-1.0 if box.inside else 1.0)
                shade = 0.6 + 0.4 * max(0.0, float(normal @ _LIGHT))
                off.append(sum(len(c) for c in chunks))
                tex = np.pad(tex, ((0, 1), (0, 1), (0, 0)), mode="edge")
                h.append(tex.shape[0])
                w.append(tex.shape[1])
                chunks.append((tex.astype(np.float32) * shade).astype(np.uint8).reshape(-1, 3))
        off.append(sum(len(c) for c in chunks))  # the last "face" is a black texel for rays that miss
        chunks.append(np.zeros((1, 3), np.uint8))
        w.append(1)
        h.append(1)
        self._atlas = np.concatenate(chunks)
        self._tex_off, self._tex_w, self._tex_h = (np.array(a, np.int64) for a in (off, w, h))
        self.face_primitive = np.repeat(np.arange(len(self.primitives) + 1), 6)[: len(w)]
        self.face_primitive[-1] = -1

    @property
    def timestamps(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps

    def __len__(self) -> int:
        return self.n_frames

    def pose(self, time: float) -> np.ndarray:
        """Camera-to-world pose at ``time`` seconds."""
        return self._path(time)

    def groundtruth(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact camera-to-world poses at the frame timestamps."""
        ts = self.timestamps
        return ts, np.stack([self.pose(t) for t in ts])

    def __iter__(self) -> Iterator[RGBDFrame]:
        # Rendering a frame costs about as much as tracking it (~40 % of a demo's main thread) and numpy
        # releases the GIL in its array loops: the next frames render on a reader thread (base.read_ahead).
        # A render is a function of the frame index alone, so the thread changes no pixel.
        yield from read_ahead((lambda i: self.frame(i, cache=False)) if self._kept is None else self._kept_frame,
                              self.n_frames)

    def _kept_frame(self, index: int) -> RGBDFrame:
        if index not in self._kept:
            frame = self.frame(index, cache=False)
            for array in (frame.rgb, frame.depth, frame.dynamic_mask):
                array.setflags(write=False)       # shared by every later pass: nobody may draw on it
            self._kept[index] = frame
        return self._kept[index]

    def keep_frames(self, keep: bool = True) -> None:
        """While on, iterating renders each frame once and keeps it (~2.5 MB at 640 x 480) for the next pass:
        runs of the same scene under several seeds render it once (rendering is ~60 % of a generated
        run's time: close_pass, 30 of 52 s for 150 frames). Off lets the kept frames go."""
        if not keep:
            self._kept = None
        elif self._kept is None:
            self._kept = {}

    def frame(self, index: int, cache: bool = True) -> RGBDFrame:
        """Frame ``index`` with its ground-truth ``dynamic_mask``; ``cache`` keeps its ray cast for the
        ``dynamic_mask``/``mover_ids``/``mover_boxes`` queries that may follow."""
        frames, depth, face = self._cast_frame(index, cache)
        time = float(self.timestamps[index])
        sensed = sensed_depth(depth.copy() if cache else depth, self.sensor_min_range_m)
        return RGBDFrame(index=index, timestamp=time, rgb=self._texture(frames, depth, face), depth=sensed,
                         dynamic_mask=self._mask(face, time))

    def moving(self, time: float) -> np.ndarray:
        """Per mover: whether it moves at ``time`` (a dragged chair is still until it is grabbed)."""
        return np.array([m.moving(time) for m in self.movers], bool)

    def dynamic_mask(self, index: int) -> np.ndarray:
        """HxW bool, True where a mover that is moving at frame ``index`` is the nearest surface."""
        return self._mask(self._cast_frame(index)[2], float(self.timestamps[index]))

    def mover_ids(self, index: int) -> np.ndarray:
        """HxW int64: the index into ``movers`` of the visible surface, -1 for the static scene."""
        return self.face_mover[self._cast_frame(index)[2]]

    def mover_boxes(self, index: int, moving_only: bool = False,
                    min_pixels: int = 1) -> list[tuple[int, int, int, int, str]]:
        """Detector-like ground truth: (x0, y0, x1, y1, kind) per mover with >= ``min_pixels`` visible
        pixels in frame ``index``; ``mask[y0:y1, x0:x1]`` holds all of them (x1, y1 exclusive). kind is
        "person", "box" or "chair" (a chair is listed while still too, unless ``moving_only``)."""
        if not self.movers:
            return []
        moving = self.moving(float(self.timestamps[index]))
        return [(x0, y0, x1, y1, self.movers[i].kind) for i, pixels, x0, y0, x1, y1 in self.mover_extents(index)
                if (moving[i] or not moving_only) and pixels >= max(1, min_pixels)]

    def mover_extents(self, index: int) -> tuple[tuple[int, int, int, int, int, int], ...]:
        """(mover, visible pixels, x0, y0, x1, y1) of every mover visible in frame ``index``, in mover order;
        ``mask[y0:y1, x0:x1]`` holds all its pixels. Noted whenever the frame is cast, so asking after the
        frame was rendered costs nothing."""
        if not self.movers:
            return ()
        if index not in self._mover_extents:
            self._cast_frame(index)      # a cast notes its frame's extents (_cast_frame)
        return self._mover_extents[index]

    def _note_mover_extents(self, index: int, face: np.ndarray) -> None:
        if not self.movers or index in self._mover_extents:
            return
        extents = []
        ids = self.face_mover[face]
        pixels = np.bincount(ids.reshape(-1) + 1, minlength=len(self.movers) + 1)[1:]
        for i in np.flatnonzero(pixels):
            hit = ids == i
            rows, cols = np.flatnonzero(hit.any(1)), np.flatnonzero(hit.any(0))
            extents.append((int(i), int(pixels[i]), int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1))
        self._mover_extents[index] = tuple(extents)

    def _mask(self, face: np.ndarray, time: float) -> np.ndarray:
        if not self.movers:
            return np.zeros(face.shape, bool)
        return np.r_[self.moving(time), False][self.face_mover[face]]

    def _cast_frame(self, index: int, cache: bool = True):
        """(box frames, depth, face) of frame ``index``; the last few are kept for the mask/box queries."""
        if index in self._casts:
            return self._casts[index]
        out = self._cast_at(index)
        self._note_mover_extents(index, out[2])
        if cache:
            self._casts[index] = out
            while len(self._casts) > 3:
                self._casts.popitem(last=False)
        return out

    def _cast_at(self, index: int):
        """(box frames, depth, face) of frame ``index``, uncached."""
        time = float(self.timestamps[index])
        frames = self._box_frames(self.pose(time), time)
        return (frames, *self._cast(frames))

    def render(self, pose: np.ndarray, time: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(BGR uint8 HxWx3, depth float32 HxW metres) seen from camera-to-world ``pose`` at ``time``."""
        frames = self._box_frames(pose, time)
        depth, face = self._cast(frames)
        return self._texture(frames, depth, face), depth

    def raycast(self, pose: np.ndarray, time: float = 0.0,
                primitives: Optional[Sequence[int]] = None) -> tuple[np.ndarray, np.ndarray]:
        """Depth (z of the nearest hit, 0 where nothing is hit) and the global face index per pixel;
        ``face_primitive[face]`` gives the primitive (-1: no hit), ``face_mover[face]`` the mover.
        ``primitives`` limits the cast to those primitive indices (e.g. the static scene only)."""
        return self._cast(self._box_frames(pose, time), primitives)

    def _box_frames(self, pose: np.ndarray, time: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per primitive: (M, ol) with M = R_box^T R_cam mapping camera rays to box axes, ol the camera
        centre in the box frame."""
        out = []
        for box in self.primitives:
            bp = box.pose_at(time)
            rb = bp[:3, :3].T
            out.append((rb @ pose[:3, :3], rb @ (pose[:3, 3] - bp[:3, 3])))
        return out

    def _cast(self, frames: list[tuple[np.ndarray, np.ndarray]],
              only: Optional[Sequence[int]] = None) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit over all primitives (or those in ``only``). Rays have camera z = 1, so a hit's ray
        parameter is its depth. Outside boxes are traced only inside their projected bounding rectangle."""
        best_t = np.full((self.height, self.width), np.inf, np.float32)
        best_f = np.full((self.height, self.width), len(self._tex_w) - 1, np.int64)
        only = None if only is None else set(int(p) for p in only)
        for p, (box, (m, ol)) in enumerate(zip(self.primitives, frames)):
            if only is not None and p not in only:
                continue
            win = (slice(None), slice(None)) if box.inside else self._window(m, ol, box.half)
            if win is None:
                continue
            x, y = self._rays[0][win], self._rays[1][win]
            m32 = m.astype(np.float32)  # elementwise, not BLAS: threaded matmul stalls on a busy machine
            d = [m32[a, 0] * x + m32[a, 1] * y + m32[a, 2] for a in range(3)]
            t, f = _box_hits(d, ol, box.half, box.inside)
            closer = t < best_t[win]
            np.copyto(best_t[win], t, where=closer)
            np.copyto(best_f[win], f + np.int16(6 * p), where=closer)
        best_t[~np.isfinite(best_t)] = 0.0
        return best_t, best_f

    def _window(self, m: np.ndarray, ol: np.ndarray, half: np.ndarray) -> Optional[tuple[slice, slice]]:
        """Image rectangle covering the part of a box in front of the near plane (None if none): its
        vertices are the corners in front plus the box edges' crossings of the near plane."""
        corners = (_SIGNS * half - ol) @ m  # camera frame, (8, 3)
        a, b = corners[_EDGES[:, 0]], corners[_EDGES[:, 1]]
        crossing = (a[:, 2] - _NEAR) * (b[:, 2] - _NEAR) < 0
        w = (_NEAR - a[crossing, 2]) / (b[crossing, 2] - a[crossing, 2])
        pts = np.vstack([corners[corners[:, 2] >= _NEAR], a[crossing] + w[:, None] * (b - a)[crossing]])
        if len(pts) == 0:
            return None
        fx, fy, cx, cy = self.intrinsics
        u = fx * pts[:, 0] / pts[:, 2] + cx
        v = fy * pts[:, 1] / pts[:, 2] + cy
        u0, u1 = max(0, int(np.floor(u.min()))), min(self.width, int(np.ceil(u.max())) + 1)
        v0, v1 = max(0, int(np.floor(v.min()))), min(self.height, int(np.ceil(v.max())) + 1)
        if u0 >= u1 or v0 >= v1:
            return None
        return slice(v0, v1), slice(u0, u1)

    def _texture(self, frames: list[tuple[np.ndarray, np.ndarray]], depth: np.ndarray,
                 face: np.ndarray) -> np.ndarray:
        """Nearest-texel colour of every hit: face-local texture coordinates are affine in (t*x, t*y, t),
        so eight small per-face coefficient tables and a handful of gathers do all pixels at once."""
        m = np.stack([box_m for box_m, _ in frames])                      # (P, 3, 3)
        start = np.stack([ol for _, ol in frames]) + np.stack([box.half for box in self.primitives])  # (P, 3)
        # rows 0-3: u = (start[a] + m[a] . ray * t) / TEXEL along axis a = _FACE_AXES[f, 0]; rows 4-7: v
        table = np.concatenate([start[:, _FACE_AXES, None], m[:, _FACE_AXES]], axis=-1) / TEXEL
        coef = np.zeros((8, len(self._tex_w)), np.float32)
        coef[:, :6 * len(frames)] = table.reshape(6 * len(frames), 8).T
        fl, t = face.ravel(), depth.ravel()
        x, y = self._rays[0].ravel(), self._rays[1].ravel()
        uv = []
        for row in (0, 4):
            c = [np.take(coef[row + k], fl) for k in range(4)]   # 1-D gathers: ~3x faster than coef[:, fl]
            # truncation maps the rounding-level negatives at face edges to 0; textures carry one
            # padding texel on the far edges for the other side, so no per-pixel clip is needed
            uv.append((c[0] + t * (c[1] * x + c[2] * y + c[3])).astype(np.int32))
        idx = np.take(self._tex_off, fl) + uv[1] * np.take(self._tex_w, fl) + uv[0]
        return np.take(self._atlas, idx, axis=0, mode="clip").reshape(self.height, self.width, 3)

    def _plan_movers(self, kinds: Sequence[str]) -> list[Mover]:
        """The movers of ``kinds``, planned against this sequence's camera path (see ``MoverPlanner``)."""
        return MoverPlanner(self).plan(kinds)
