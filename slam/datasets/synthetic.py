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
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional, Sequence, Union

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from .base import RGBDFrame
from .tum import CAMERA_FILE

TEXEL = 0.01
"""Texture resolution in metres: 1 cm is ~5 px at 1 m and ~1 px at 5 m, so nearest lookup stays crisp
without aliasing much at the far wall."""

_SHAPE_SCALES = ((0.3, 1.0, 2.0), (0.1, 0.3, 20.0), (0.03, 0.1, 110.0))
"""(min size m, max size m, shapes per square metre): corners at every ORB pyramid level and distance."""

_LIGHT = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])


def static_pose(center: tuple[float, float, float], yaw: float = 0.0) -> Callable[[float], np.ndarray]:
    """A constant box-to-world pose (rotation about world z by ``yaw`` radians)."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    pose[:3, 3] = center
    return lambda time: pose


@dataclass
class Box:
    """A textured box primitive; faces are ordered -x, +x, -y, +y, -z, +z in the box frame.

    ``inside`` boxes are seen from within (the room). ``pose_at(time)`` gives box-to-world, so a rigid
    moving object only needs a time-varying function; ``dynamic`` marks a part of a ``Mover``. Textures
    come from ``add_textures`` (or the mover painters) and are packed when the sequence is built.
    """

    half: np.ndarray
    pose_at: Callable[[float], np.ndarray]
    inside: bool = False
    dynamic: bool = False
    textures: list[np.ndarray] = field(default_factory=list)


def make_texture(rng: np.random.Generator, width_m: float, height_m: float, texel: float = TEXEL) -> np.ndarray:
    """Random overlapping rectangles, discs and triangles of random colours at three scales.

    Random (not periodic) placement keeps ORB descriptors distinctive; the scale mix puts corners in
    every pyramid level whether a wall is 1 m or 5 m away. A loop over shapes, not pixels.
    """
    nw, nh = max(1, int(round(width_m / texel))), max(1, int(round(height_m / texel)))
    img = np.empty((nh, nw, 3), np.uint8)
    img[:] = rng.integers(40, 216, 3)
    for lo, hi, density in _SHAPE_SCALES:
        n = rng.poisson(density * width_m * height_m) + 1
        size = rng.uniform(lo, hi, (n, 2)) / texel
        centre = rng.uniform(0.0, 1.0, (n, 2)) * (nw, nh)
        colour = rng.integers(0, 256, (n, 3))
        kind = rng.choice(3, n, p=(0.6, 0.2, 0.2))
        spin = rng.uniform(0, 2 * np.pi, n)
        for k in range(n):
            c, s, col = centre[k], size[k] / 2, tuple(int(x) for x in colour[k])
            if kind[k] == 0:
                cv2.rectangle(img, _pt(c - s), _pt(c + s), col, -1)
            elif kind[k] == 1:
                cv2.circle(img, _pt(c), max(1, int(s[0])), col, -1)
            else:
                ang = spin[k] + np.array([0.0, 2.1, 4.0])
                tri = np.stack([c[0] + s[0] * np.cos(ang), c[1] + s[1] * np.sin(ang)], 1)
                cv2.fillPoly(img, [np.round(tri).astype(np.int32)], col)
    return img


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(round(p[0])), int(round(p[1]))


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


def add_textures(box: Box, rng: np.random.Generator) -> Box:
    """Give each face of ``box`` its own random texture (face order -x, +x, -y, +y, -z, +z); a face on
    axis k is textured over the next two axes (k+1, k+2) mod 3, which is how the renderer looks it up."""
    box.textures = []
    for axis in range(3):
        i, j = (axis + 1) % 3, (axis + 2) % 3
        for _side in range(2):
            box.textures.append(make_texture(rng, 2 * box.half[i], 2 * box.half[j]))
    return box


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


_SIGNS = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
_EDGES = np.array([(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(_SIGNS[i] != _SIGNS[j]) == 1])
_NEAR = 0.05


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
    face = on1.astype(np.int64) * 2 + on2 * 4 + positive
    return t, face


# --- moving objects ----------------------------------------------------------------------------------

MOVER_PRESETS: dict[str, tuple[str, ...]] = {
    "none": (),
    "boxes": ("box", "box"),
    "people": ("person", "person", "person"),
    "crowd": ("person", "person", "person", "box", "box"),
    "drag": ("drag",),
}
"""Named mover sets. Elements are the single kinds "person", "box" and "drag" (a chair that stands still
for the first half of the sequence, then is dragged along by a person walking past it)."""


_PLAN_TRIES = 120
"""Candidate paths tried per mover at most (see ``SyntheticSequence._plan_movers``)."""


class WalkLoop:
    """A closed path in the floor plane: a rounded rectangle (straight runs joined by quarter circles of
    ``radius``) with half sizes ``half`` around ``centre``. ``at(s)`` gives position and heading (tangent
    angle for counter-clockwise travel, continuous) at any arc length, wrapping around."""

    def __init__(self, centre: tuple[float, float], half: tuple[float, float], radius: float) -> None:
        ax, ay = half
        self.r = r = min(radius, ax, ay)
        self.centre = np.asarray(centre, float)
        self.corners = np.array([(ax - r, ay - r), (r - ax, ay - r), (r - ax, r - ay), (ax - r, r - ay)])
        self.phi = np.arange(4) * np.pi / 2  # outward normal of straight k; its heading is phi + 90 deg
        normal = np.stack([np.cos(self.phi), np.sin(self.phi)], 1)
        self.start = np.roll(self.corners, 1, axis=0) + r * normal  # straight k runs to corners[k] + r n
        straight = np.linalg.norm(self.corners + r * normal - self.start, axis=1)
        self.lengths = np.stack([straight, np.full(4, r * np.pi / 2)], 1).ravel()  # straight, arc, ...
        self.breaks = np.r_[0.0, np.cumsum(self.lengths)]
        self.length = float(self.breaks[-1])

    def at(self, s) -> tuple[np.ndarray, np.ndarray]:
        """(xy (..., 2), heading (...)) at arc length(s) ``s``."""
        s = np.mod(np.asarray(s, float), self.length)
        piece = np.clip(np.searchsorted(self.breaks, s, side="right") - 1, 0, 7)
        k, along = piece // 2, s - self.breaks[piece]
        arc = piece % 2 == 1
        ang = self.phi[k] + np.where(arc, along / max(self.r, 1e-9), 0.0)
        direction = np.stack([np.cos(self.phi[k] + np.pi / 2), np.sin(self.phi[k] + np.pi / 2)], -1)
        on_arc = self.corners[k] + self.r * np.stack([np.cos(ang), np.sin(ang)], -1)
        on_line = self.start[k] + along[..., None] * direction
        return np.where(arc[..., None], on_arc, on_line) + self.centre, ang + np.pi / 2


def _rot_z(yaw) -> np.ndarray:
    """(..., 3, 3) rotations about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _local(offset, angle: float = 0.0, drop: float = 0.0) -> np.ndarray:
    """Part-to-root pose: translate to ``offset`` (a joint), rotate by ``angle`` about the root's y axis
    (a swing in the walking plane), then translate by ``drop`` down the part (joint to part centre)."""
    c, s = np.cos(angle), np.sin(angle)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose[:3, 3] = np.asarray(offset, float) + pose[:3, :3] @ [0.0, 0.0, -drop]
    return pose


def _clash(ca: np.ndarray, ra: np.ndarray, ha: np.ndarray, cb: np.ndarray, rb: np.ndarray, hb: np.ndarray,
           margin: float = 0.03) -> np.ndarray:
    """Per time, how far (metres) two oriented boxes come within ``margin`` of each other, 0 when they
    keep it: the separating-axis test over the 15 axes, on the times their bounding spheres meet.
    Centres (T, 3) or (3,), box-to-world rotations (T, 3, 3) or (3, 3), half sizes (3,)."""
    ca, cb = np.broadcast_arrays(ca, cb)
    n = len(ca)
    ra, rb = np.broadcast_to(ra, (n, 3, 3)), np.broadcast_to(rb, (n, 3, 3))
    out = np.zeros(n)
    near = np.linalg.norm(cb - ca, axis=1) < np.linalg.norm(ha) + np.linalg.norm(hb) + margin
    if not near.any():
        return out
    ca, cb, ra, rb = ca[near], cb[near], ra[near], rb[near]
    ea, eb = ra.transpose(0, 2, 1), rb.transpose(0, 2, 1)  # rows: the boxes' axes in the world
    axes = np.concatenate([ea, eb, np.cross(ea[:, :, None], eb[:, None]).reshape(-1, 9, 3)], axis=1)
    length = np.linalg.norm(axes, axis=2)
    unit = axes / np.maximum(length, 1e-9)[..., None]  # (M, 15, 3)
    reach = (np.abs(unit @ ra) @ ha + np.abs(unit @ rb) @ hb
             - np.abs(np.einsum("tki,ti->tk", unit, cb - ca)))
    depth = np.where(length > 1e-6, reach + margin, np.inf).min(axis=1)
    out[near] = np.maximum(depth, 0.0)
    return out


@dataclass(eq=False)
class Mover:
    """One moving object made of ``Box`` parts (a person has six, a box or chair one).

    ``track(times)`` is vectorised: (root positions (T,3), root rotations (T,3,3), gait phase (T,)); a
    part's pose is root @ ``part_local[k](gait)``. ``moving(time)`` says whether it moves at that time (a
    dragged chair stands still for a while: it is then no dynamic surface, but still a detectable object).
    For path planning only: ``radius`` is its clearance radius (floor plan; 3-d for a floating box) and
    ``envelope`` the half sizes of a box in the root frame, centred ``lift`` above the root, bounding it
    on screen. ``parts`` are its indices in ``SyntheticSequence.primitives``.
    """

    kind: str
    track: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
    boxes: list[Box]
    part_local: list[Callable[[float], np.ndarray]]
    moving: Callable[[float], bool]
    radius: float
    envelope: np.ndarray
    lift: float
    parts: list[int] = field(default_factory=list)
    _last: tuple = field(default=(None, None), repr=False)

    def root(self, time: float) -> tuple[np.ndarray, float]:
        if self._last[0] != time:
            pos, rot, gait = self.track(np.array([time], float))
            pose = np.eye(4)
            pose[:3, :3], pose[:3, 3] = rot[0], pos[0]
            self._last = (time, (pose, float(gait[0])))
        return self._last[1]

    def part_pose(self, k: int, time: float) -> np.ndarray:
        pose, gait = self.root(time)
        return pose @ self.part_local[k](gait)


def _paint(half: np.ndarray, colour: Callable[[np.ndarray, int], np.ndarray]) -> list[np.ndarray]:
    """Six face textures of a box whose texel colours are ``colour(points (h, w, 3) box frame, face)``;
    face f on axis f // 2 is textured over axes (f//2 + 1, f//2 + 2) mod 3 as the renderer reads it."""
    out = []
    for f in range(6):
        a = f // 2
        i, j = (a + 1) % 3, (a + 2) % 3
        nw, nh = max(1, int(round(2 * half[i] / TEXEL))), max(1, int(round(2 * half[j] / TEXEL)))
        pts = np.zeros((nh, nw, 3))
        pts[..., i] = (np.arange(nw) + 0.5) * TEXEL - half[i]
        pts[..., j] = ((np.arange(nh) + 0.5) * TEXEL - half[j])[:, None]
        pts[..., a] = half[a] if f % 2 else -half[a]
        out.append(np.ascontiguousarray(np.clip(colour(pts, f), 0, 255), np.uint8))
    return out


def _shapes(img: np.ndarray, rng: np.random.Generator, n: int, lo: float, hi: float,
            box: Optional[tuple[float, float, float, float]] = None) -> np.ndarray:
    """Draw ``n`` random rectangles/discs/triangles (sizes ``lo``-``hi`` metres) into a texture, inside
    the fractional region ``box`` (x0, y0, x1, y1) of it when given."""
    nh, nw = img.shape[:2]
    x0, y0, x1, y1 = box or (0.0, 0.0, 1.0, 1.0)
    for _ in range(n):
        c = rng.uniform((x0 * nw, y0 * nh), (x1 * nw, y1 * nh))
        s = rng.uniform(lo, hi, 2) / TEXEL / 2
        col = tuple(int(x) for x in rng.integers(0, 256, 3))
        kind = rng.integers(3)
        if kind == 0:
            cv2.rectangle(img, _pt(c - s), _pt(c + s), col, -1)
        elif kind == 1:
            cv2.circle(img, _pt(c), max(1, int(s[0])), col, -1)
        else:
            ang = rng.uniform(0, 2 * np.pi) + np.array([0.0, 2.1, 4.0])
            tri = np.stack([c[0] + s[0] * np.cos(ang), c[1] + s[1] * np.sin(ang)], 1)
            cv2.fillPoly(img, [np.round(tri).astype(np.int32)], col)
    return img


def _fabric(rng: np.random.Generator, base: np.ndarray, second: np.ndarray, pattern: str, period: float,
            noise: int = 12) -> Callable[[np.ndarray, int], np.ndarray]:
    """Cloth colouring in the part frame: plain, horizontal stripes or checks of ``period`` metres, with
    per-texel weave noise; offsets are random so parts of one garment do not line up exactly."""
    off = rng.uniform(0, period, 2)
    seed = int(rng.integers(2**31))

    def colour(p: np.ndarray, face: int) -> np.ndarray:
        band_z = np.floor((p[..., 2] + off[0]) / period) % 2 == 1
        across = p[..., 1] if face < 2 else p[..., 0]
        band_h = np.floor((across + off[1]) / period) % 2 == 1
        out = np.broadcast_to(base, p.shape).astype(np.float64)
        if pattern == "stripes":
            out = np.where(band_z[..., None], second, out)
        elif pattern == "checks":
            out = np.where((band_z ^ band_h)[..., None], second, out)
            out = np.where((band_z & band_h)[..., None], 0.6 * base, out)
        weave = np.random.default_rng([seed, face]).integers(-noise, noise + 1, p.shape[:2] + (1,))
        return out + weave

    return colour


_SKIN = np.array([[80, 110, 170], [100, 145, 205], [60, 90, 140], [130, 170, 225], [45, 65, 100]])  # BGR
_HAIR = np.array([[20, 25, 30], [40, 60, 90], [30, 40, 50], [90, 140, 180], [150, 150, 150]])
_TROUSERS = np.array([[110, 60, 30], [40, 40, 40], [90, 130, 160], [60, 70, 50], [140, 100, 70]])


def _person(rng: np.random.Generator, height: float) -> tuple[list[Box], list[Callable[[float], np.ndarray]]]:
    """A ~0.53 x 0.26 x ``height`` m walking figure in its root frame (x forward, y left, z up, origin on the
    floor): torso, head, two legs and two arms swinging with the gait phase; clothes-like textures
    (striped, checked or plain shirt with a print, trousers, skin and hair) unlike the room's."""
    k = height / 1.75
    leg_h, hip = 0.43 * k, 0.86 * k
    torso = np.array([0.13, 0.17, 0.31 * k])
    arm = np.array([0.05, 0.045, 0.29 * k])
    head = np.array([0.1, 0.085, 0.115 * k])
    shoulder, arm_y = hip + 0.58 * k, torso[1] + arm[1] + 0.005
    swing_leg, swing_arm = rng.uniform(0.3, 0.4), rng.uniform(0.2, 0.35)

    def bob(g: float) -> float:  # the hips drop as the legs spread, so both feet stay on the floor
        return 2 * leg_h * (np.cos(swing_leg * np.sin(g)) - 1)

    shirt_base = rng.integers(30, 230, 3).astype(float)
    shirt = _fabric(rng, shirt_base, rng.integers(0, 256, 3).astype(float),
                    ("plain", "stripes", "checks")[rng.integers(3)], rng.uniform(0.03, 0.09))
    trousers = _fabric(rng, _TROUSERS[rng.integers(len(_TROUSERS))].astype(float),
                       rng.integers(0, 256, 3).astype(float), "plain", 0.05, noise=8)
    skin, hair = _SKIN[rng.integers(len(_SKIN))].astype(float), _HAIR[rng.integers(len(_HAIR))].astype(float)
    hair_line = rng.uniform(0.3, 0.7) * head[2]

    def head_colour(p: np.ndarray, face: int) -> np.ndarray:
        out = np.where(((p[..., 2] > hair_line) | (p[..., 0] < -0.05))[..., None], hair, skin)
        eyes = (np.abs(np.abs(p[..., 1]) - 0.035) < 0.015) & (np.abs(p[..., 2] - 0.15 * head[2]) < 0.012)
        mouth = (np.abs(p[..., 1]) < 0.03) & (np.abs(p[..., 2] + 0.45 * head[2]) < 0.008)
        face_mark = ((eyes | mouth) & (p[..., 0] > head[0] - 1e-6))[..., None]
        return np.where(face_mark, 0.3 * skin, out) + rng.integers(-5, 6, p.shape[:2] + (1,))

    torso_tex = _paint(torso, shirt)
    _shapes(torso_tex[1], rng, int(rng.integers(1, 4)), 0.04, 0.14, (0.25, 0.3, 0.75, 0.8))  # front print
    boxes = [Box(torso, None, dynamic=True, textures=torso_tex),
             Box(head, None, dynamic=True, textures=_paint(head, head_colour))]
    locals_ = [lambda g: _local((0, 0, hip + torso[2] + bob(g))),
               lambda g: _local((0, 0, hip + 2 * torso[2] + 0.03 * k + head[2] + bob(g)))]
    for side in (1, -1):
        leg = np.array([0.085, 0.08, leg_h])
        boxes.append(Box(leg, None, dynamic=True, textures=_paint(leg, trousers)))
        locals_.append(lambda g, side=side: _local((0, 0.085 * side, hip + bob(g)), side * swing_leg * np.sin(g),
                                                   leg_h))
    for side in (1, -1):
        boxes.append(Box(arm, None, dynamic=True, textures=_paint(arm, shirt)))
        locals_.append(lambda g, side=side: _local((0, arm_y * side, shoulder + bob(g)),
                                                   -side * swing_arm * np.sin(g), arm[2]))
    return boxes, locals_


def _cardboard(rng: np.random.Generator, half: np.ndarray) -> list[np.ndarray]:
    """Printed cardboard: brown with weave noise, a tape band over the top and two sides, labels."""
    base = np.array([70, 120, 165], float) * rng.uniform(0.7, 1.15) + rng.integers(-15, 16, 3)
    tape = rng.uniform(0.025, 0.04)

    def colour(p: np.ndarray, face: int) -> np.ndarray:
        out = np.where((np.abs(p[..., 1]) < tape)[..., None] & (face not in (2, 3)), base * 1.25 + 20, base)
        return out + rng.integers(-8, 9, p.shape[:2] + (1,))

    tex = _paint(half, colour)
    for t in tex:
        _shapes(t, rng, int(rng.integers(3, 9)), 0.03, 0.2)
    return tex


def _chair(rng: np.random.Generator, half: np.ndarray) -> list[np.ndarray]:
    """A painted wooden chair-sized block: grain stripes along z and a few decals."""
    base = rng.integers(40, 200, 3).astype(float)
    grain = _fabric(rng, base, base * 0.75, "stripes", rng.uniform(0.02, 0.05), noise=6)
    tex = _paint(half, grain)
    for t in tex:
        _shapes(t, rng, int(rng.integers(2, 5)), 0.03, 0.12)
    return tex


def mover_kinds(movers: Union[str, Sequence[str]]) -> tuple[str, ...]:
    """Expand a preset name, a single kind ("person", "box", "drag") or a list of either into kinds."""
    if isinstance(movers, str):
        if movers in MOVER_PRESETS:
            return MOVER_PRESETS[movers]
        if movers in ("person", "box", "drag"):
            return (movers,)
        raise ValueError(f"unknown movers {movers!r}; expected one of {sorted(MOVER_PRESETS)}, "
                         "'person', 'box', 'drag' or a list of these")
    return tuple(k for m in movers for k in mover_kinds(m))


class SyntheticSequence:
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
        self._casts: OrderedDict = OrderedDict()

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
        for i in range(self.n_frames):
            yield self.frame(i, cache=False)

    def frame(self, index: int, cache: bool = True) -> RGBDFrame:
        """Frame ``index`` with its ground-truth ``dynamic_mask``; ``cache`` keeps its ray cast for the
        ``dynamic_mask``/``mover_ids``/``mover_boxes`` queries that may follow."""
        frames, depth, face = self._cast_frame(index, cache)
        time = float(self.timestamps[index])
        return RGBDFrame(index=index, timestamp=time, rgb=self._texture(frames, depth, face),
                         depth=depth.copy() if cache else depth, dynamic_mask=self._mask(face, time))

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
        ids = self.mover_ids(index)
        moving = self.moving(float(self.timestamps[index]))
        out = []
        for i, mover in enumerate(self.movers):
            if moving_only and not moving[i]:
                continue
            hit = ids == i
            if np.count_nonzero(hit) < max(1, min_pixels):
                continue
            rows, cols = np.flatnonzero(hit.any(1)), np.flatnonzero(hit.any(0))
            out.append((int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1, mover.kind))
        return out

    def _mask(self, face: np.ndarray, time: float) -> np.ndarray:
        if not self.movers:
            return np.zeros(face.shape, bool)
        return np.r_[self.moving(time), False][self.face_mover[face]]

    def _cast_frame(self, index: int, cache: bool = True):
        """(box frames, depth, face) of frame ``index``; the last few are kept for the mask/box queries."""
        if index in self._casts:
            return self._casts[index]
        time = float(self.timestamps[index])
        frames = self._box_frames(self.pose(time), time)
        out = (frames, *self._cast(frames))
        if cache:
            self._casts[index] = out
            while len(self._casts) > 3:
                self._casts.popitem(last=False)
        return out

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
            np.copyto(best_f[win], f + 6 * p, where=closer)
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
        coef = np.zeros((8, len(self._tex_w)), np.float32)
        for p, (box, (m, ol)) in enumerate(zip(self.primitives, frames)):
            for f in range(6):
                for row, a in ((0, (f // 2 + 1) % 3), (4, (f // 2 + 2) % 3)):
                    coef[row:row + 4, 6 * p + f] = np.r_[ol[a] + box.half[a], m[a]] / TEXEL
        fl, t = face.ravel(), depth.ravel()
        x, y = self._rays[0].ravel(), self._rays[1].ravel()
        uv = []
        for row in (0, 4):
            c = coef[row:row + 4, fl]
            # truncation maps the rounding-level negatives at face edges to 0; textures carry one
            # padding texel on the far edges for the other side, so no per-pixel clip is needed
            uv.append((c[0] + t * (c[1] * x + c[2] * y + c[3])).astype(np.int32))
        idx = np.take(self._tex_off, fl) + uv[1] * np.take(self._tex_w, fl) + uv[0]
        return np.take(self._atlas, idx, axis=0, mode="clip").reshape(self.height, self.width, 3)

    # --- mover planning ------------------------------------------------------------------------------

    def _plan_movers(self, kinds: Sequence[str]) -> list[Mover]:
        """Appearance from one seeded stream, paths from another. Mover k is made to cross the view
        (within +-20 deg of its centre) near its own time, spread over the sequence in a random order
        ("drag": the grab, mid-way). Movers are placed one after the other (greedy): the first of up to
        ``_PLAN_TRIES`` random candidate paths that meets all of ``_plan_cost``'s constraints is kept,
        else the cheapest, so crowded short sequences are a best effort."""
        look, shape = np.random.default_rng([self.seed, 31]), np.random.default_rng([self.seed, 37])
        duration = max(self.n_frames, 1) / self.fps
        times = np.arange(max(self.n_frames, 1))[:: max(1, -(-self.n_frames // 240))] / self.fps
        cams = np.stack([self.pose(float(t)) for t in times])
        furniture = [(box.pose_at(0.0), box.half) for box in self.primitives if not box.inside]
        slot, flow = duration / len(kinds), shape.choice([-1.0, 1.0])
        crossing = slot * (shape.permutation(len(kinds)) + 0.5)
        planned: list[tuple] = []  # (mover, rectangles, on screen, centres, rotations, distances) per time
        grid = np.zeros((len(times), 30, 40), bool)  # the planned movers' rectangles (coverage term)
        placed: dict[int, list[Mover]] = {}
        for j in range(len(kinds)):
            kind, tc = kinds[j], crossing[j]
            bodies = [_person(look, shape.uniform(1.6, 1.85))] if kind != "box" else []
            if kind == "box":
                half = shape.uniform(0.2, 0.3, 3)
                bodies.append(([Box(half, None, dynamic=True, textures=_cardboard(look, half))],
                               [lambda g: np.eye(4)]))
            if kind == "drag":
                half = np.array([0.22, 0.22, 0.45])
                bodies.append(([Box(half, None, dynamic=True, textures=_chair(look, half))],
                               [lambda g: _local((0.0, 0.0, 0.45))]))
            best = None
            for _ in range(_PLAN_TRIES):
                t = duration / 2 if kind == "drag" else tc + shape.uniform(-0.3, 0.3) * slot
                movers = self._candidate(kind, bodies, float(t), shape, cams[np.argmin(np.abs(times - t))], flow)
                cost, entries = self._plan_cost(movers, planned, grid, cams, times, furniture,
                                                np.inf if best is None else best[0])
                if best is None or cost < best[0]:
                    best = (cost, entries)
                if cost == 0:
                    break
            planned.extend(best[1])
            placed[j] = [entry[0] for entry in best[1]]
            for entry in best[1]:
                grid |= self._rect_cells(entry[1])
        return [m for j in range(len(kinds)) for m in placed[j]]

    def _candidate(self, kind: str, bodies: list, tc: float, rng: np.random.Generator, cam: np.ndarray,
                   flow: float = 1.0) -> list[Mover]:
        """A random loop and motion for one mover ("drag": person and chair) crossing the view at ``tc``."""
        radius = 0.3 if kind != "box" else float(np.linalg.norm(bodies[0][0][0].half))
        cx, cy = rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5)
        ax = rng.uniform(1.2, max(1.21, 2.9 - radius - abs(cx)))
        ay = rng.uniform(1.0, max(1.01, 2.4 - radius - abs(cy)))
        loop = WalkLoop((cx, cy), (ax, ay), rng.uniform(0.3, min(ax, ay)))
        # the loop point seen along the (jittered) horizontal view direction at the crossing time
        arc = np.linspace(0.0, loop.length, 400, endpoint=False)
        rel = loop.at(arc)[0] - cam[:2, 3]
        bearing = np.arctan2(cam[1, 2], cam[0, 2]) + rng.uniform(-0.35, 0.35)
        off = np.abs(np.angle(np.exp(1j * (np.arctan2(rel[:, 1], rel[:, 0]) - bearing))))
        s_hit = float(arc[np.argmin(off)])
        # people mostly walk the same way round (as in a corridor), so they seldom meet head-on
        if kind == "box":
            direction = 1.0 if rng.uniform() < 0.5 else -1.0
        else:
            direction = flow if rng.uniform() < 0.85 else -flow
        flip = np.pi if direction < 0 else 0.0
        if kind == "box":
            boxes, locals_ = bodies[0]
            v, z0 = rng.uniform(0.3, 0.8), rng.uniform(max(radius + 0.15, 0.8), min(2.85 - radius, 1.9))
            zamp, zw, zphi = rng.uniform(0.03, 0.12), rng.uniform(0.5, 1.5), rng.uniform(0, 2 * np.pi)
            axis = rng.normal(size=3)
            spin = axis / np.linalg.norm(axis) * np.radians(rng.uniform(25, 60)) * rng.choice([-1, 1])
            q = rng.normal(size=4)
            rot0 = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
            s0 = s_hit - direction * v * tc

            def box_track(ts: np.ndarray):
                xy, _ = loop.at(s0 + direction * v * ts)
                z = z0 + zamp * np.sin(zw * ts + zphi)
                return np.c_[xy, z], Rotation.from_rotvec(ts[:, None] * spin).as_matrix() @ rot0, 0 * ts

            return [Mover("box", box_track, boxes, locals_, lambda t: True, radius, boxes[0].half, 0.0)]

        boxes, locals_ = bodies[0]
        height = 1.75 * boxes[0].half[2] / 0.31  # the torso is scaled with the body height
        stride, gait0 = rng.uniform(1.2, 1.5), rng.uniform(0, 2 * np.pi)
        envelope = np.array([0.22, 0.28, height / 2])  # swinging limbs included
        if kind == "person":
            v, ww, wphi = rng.uniform(0.9, 1.2), rng.uniform(0.8, 2.0), rng.uniform(0, 2 * np.pi)
            wamp = 0.08 * v / ww

            def dist(ts):
                return v * ts + wamp * (np.sin(ww * ts + wphi) - np.sin(wphi))

            s0 = s_hit - direction * float(dist(np.array([tc]))[0])

            def person_track(ts: np.ndarray):
                d = dist(ts)
                xy, head = loop.at(s0 + direction * d)
                return np.c_[xy, 0 * ts], _rot_z(head + flip), gait0 + 2 * np.pi * d / stride

            return [Mover("person", person_track, boxes, locals_, lambda t: True, radius, envelope, height / 2)]

        # drag: the person walks at a steady pace; the chair stands beside the loop half a metre behind
        # the point the person reaches mid-sequence, and from then on follows it with a growing lag
        v, lag, relax, side = rng.uniform(0.6, 0.85), 0.55, 0.4, rng.choice([-1.0, 1.0])
        beside, turn, yaw0 = 0.65, rng.uniform(-0.5, 0.5), rng.uniform(-np.pi, np.pi)
        s_chair = s_hit - direction * lag

        def walker(ts: np.ndarray):
            d = v * (ts - tc)
            xy, head = loop.at(s_hit + direction * d)
            return np.c_[xy, 0 * ts], _rot_z(head + flip), gait0 + 2 * np.pi * d / stride

        def chair(ts: np.ndarray):
            tau = np.maximum(ts - tc, 0.0)
            xy, head = loop.at(s_chair + direction * v * (tau - relax * (1 - np.exp(-tau / relax))))
            xy = xy + side * beside * np.stack([-np.sin(head), np.cos(head)], -1)
            return np.c_[xy, 0 * ts], _rot_z(yaw0 + turn * (1 - np.exp(-tau / 0.6))), 0 * ts

        chair_boxes, chair_locals = bodies[1]
        return [Mover("person", walker, boxes, locals_, lambda t: True, radius, envelope, height / 2),
                Mover("chair", chair, chair_boxes, chair_locals, lambda t: t > tc, 0.32,
                      np.array([0.22, 0.22, 0.45]), 0.45)]

    def _plan_cost(self, movers: list[Mover], planned: list, grid: np.ndarray, cams: np.ndarray,
                   times: np.ndarray, furniture: list, bound: float = np.inf) -> tuple[float, list]:
        """Cost of candidate ``movers`` and their plan entries (mover, screen rectangles, on-screen flags,
        centres, rotations, camera distances per time). 0 when each keeps its centre >= ``radius`` +
        0.6 m from the camera centre, stays >= 3 cm clear of furniture while on screen and of the
        ``planned`` movers while either is on screen (out of view, nobody sees them pass through), its
        screen rectangle stays <= 35 % of the image, every mover stays seen long enough (``_unseen``),
        and the union of all movers' rectangles (``grid``: the planned ones) is <= 55 % of the image in
        >= 98 % of the frames and <= 75 % in all. Else a weighted sum of the shortfalls, or any value
        >= ``bound`` once the cost is sure to reach it. The rectangles overestimate the masks (about
        1.5-2x for a person), so the masks stay well under these shares."""
        cost, n, entries = 0.0, len(times), []
        area = self.width * self.height
        for m in movers:
            pos, rot, _ = m.track(times)
            centre = pos + rot @ [0.0, 0.0, m.lift]
            axes = 3 if m.kind == "box" else 2  # the camera may pass right above or below a floating box
            gap = np.linalg.norm(centre[:, :axes] - cams[:, :axes, 3], axis=1)
            cost += 1000 * np.maximum(m.radius + 0.6 - gap, 0).sum()
            if cost >= bound:
                return float(cost), entries
            rect = self._rects(cams, pos, rot, m.envelope, m.lift)
            share = (rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1]) / area
            seen = share > 0
            cost += 10 * np.maximum(share - 0.35, 0.0).sum()
            for pose, half in furniture:
                cost += 10 * _clash(centre[seen], rot[seen], m.envelope, pose[:3, 3], pose[:3, :3], half).sum()
            for other, _, other_seen, other_centre, other_rot, _ in planned:
                shown = seen | other_seen
                cost += 10 * _clash(centre[shown], rot[shown], m.envelope,
                                    other_centre[shown], other_rot[shown], other.envelope).sum()
            local = np.einsum("ti,tij->tj", centre - cams[:, :3, 3], cams[:, :3, :3])  # camera frame
            fx, fy, cx, cy = self.intrinsics
            z = np.maximum(local[:, 2], _NEAR)
            u, v = fx * local[:, 0] / z + cx, fy * local[:, 1] / z + cy
            centred = (local[:, 2] > _NEAR) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
            entries.append((m, rect, seen, centre, rot, np.where(centred, np.linalg.norm(local, axis=1), np.inf)))
        # visibility, with nearer movers' rectangles hiding farther ones; the newcomers must not hide the
        # planned movers any more than they already are
        for entry in entries:
            cost += self._unseen(entry, planned + entries, times)
        for entry in planned:
            cost += self._unseen(entry, planned + entries, times) - self._unseen(entry, planned, times)
        if cost >= bound:
            return float(cost), entries
        cells = grid.copy()
        for entry in entries:
            cells |= self._rect_cells(entry[1])
        cover = cells.mean(axis=(1, 2))
        cost += 100 * max(np.mean(cover > 0.55) - 0.02, 0.0) + 10 * max(cover.max() - 0.75, 0.0)
        return float(cost), entries

    def _unseen(self, entry: tuple, others: list, times: np.ndarray) -> float:
        """100 x the fraction of the frames that a planned mover lacks from being seen (its centre in the
        image and its rectangle, less those of nearer movers, >= 0.3 % of the image) in 30 % of the
        frames or for 1 s (a chair: 30 % of each half of the sequence). ``entry[5]`` holds the camera
        distance of its centre, inf where that is off screen."""
        m, rect, _, _, _, dist = entry
        shown = (rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1])
        for other in others:
            if other[0] is not m:
                r = other[1]
                w = np.minimum(rect[:, 2], r[:, 2]) - np.maximum(rect[:, 0], r[:, 0])
                h = np.minimum(rect[:, 3], r[:, 3]) - np.maximum(rect[:, 1], r[:, 1])
                shown = shown - np.maximum(w, 0) * np.maximum(h, 0) * (other[5] < dist)
        seen = (shown > 0.003 * self.width * self.height) & np.isfinite(dist)
        n = len(times)
        if m.kind == "chair":
            halves = (times < times[-1] / 2, times >= times[-1] / 2)
            return 100 * sum(max(0.3 - seen[h].mean(), 0.0) for h in halves if h.any())
        need = min(0.3 * n, 1.0 / (times[1] - times[0]) if n > 1 else 1.0)
        return 100 * max(need - seen.sum(), 0.0) / n

    def _rect_cells(self, rect: np.ndarray) -> np.ndarray:
        """(T, 30, 40) bool: the cells of a 30 x 40 grid over the image whose centres the rectangles cover."""
        gv = (np.arange(30) + 0.5) * self.height / 30
        gu = (np.arange(40) + 0.5) * self.width / 40
        cols = (gu >= rect[:, :1]) & (gu < rect[:, 2:3])
        rows = (gv >= rect[:, 1:2]) & (gv < rect[:, 3:4])
        return rows[:, :, None] & cols[:, None, :]

    def _rects(self, cams: np.ndarray, pos: np.ndarray, rot: np.ndarray, half: np.ndarray,
               lift: float = 0.0) -> np.ndarray:
        """Screen rectangles (T, 4: u0, v0, u1, v1 clipped to the image; all 0 when off screen) of boxes
        +- ``half`` about ``lift`` above poses (``pos`` (T, 3), ``rot`` (T, 3, 3)) seen from camera poses
        ``cams`` (T, 4, 4); like ``_window``, the part behind the near plane is cut off."""
        corners = pos[:, None, :] + np.einsum("tij,kj->tki", rot, _SIGNS * half + [0.0, 0.0, lift])
        cam = np.einsum("tki,tij->tkj", corners - cams[:, None, :3, 3], cams[:, :3, :3])
        a, b = cam[:, _EDGES[:, 0]], cam[:, _EDGES[:, 1]]
        za, zb = a[..., 2] - _NEAR, b[..., 2] - _NEAR
        crossing = za * zb < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(crossing, za / (za - zb), 0.0)
        pts = np.concatenate([cam, a + w[..., None] * (b - a)], axis=1)
        valid = np.concatenate([cam[..., 2] >= _NEAR, crossing], axis=1)
        z = np.where(valid, pts[..., 2], 1.0)
        fx, fy, cx, cy = self.intrinsics
        u, v = fx * pts[..., 0] / z + cx, fy * pts[..., 1] / z + cy
        out = np.stack([np.where(valid, u, np.inf).min(1), np.where(valid, v, np.inf).min(1),
                        np.where(valid, u, -np.inf).max(1), np.where(valid, v, -np.inf).max(1)], 1)
        out = np.clip(out, 0, [self.width, self.height, self.width, self.height])
        out[(out[:, 2] <= out[:, 0]) | (out[:, 3] <= out[:, 1])] = 0.0
        return out


def write_tum_layout(seq: SyntheticSequence, folder: Union[str, Path], depth_scale: float = 5000.0) -> Path:
    """Write ``seq`` as a TUM RGB-D folder (rgb/, depth/, lists, groundtruth.txt, camera.yaml) so the CLI
    and TumDataset can run it like a real recording. Depth is 16-bit PNG, ``depth_scale`` units per metre."""
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines, assoc_lines = [], [], []
    for frame in seq:
        stamp = f"{frame.timestamp:.6f}"
        raw = np.clip(np.round(frame.depth.astype(np.float64) * depth_scale), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(folder / "rgb" / f"{stamp}.png"), frame.rgb)
        cv2.imwrite(str(folder / "depth" / f"{stamp}.png"), raw)
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
        depth_lines.append(f"{stamp} depth/{stamp}.png")
        assoc_lines.append(f"{stamp} rgb/{stamp}.png {stamp} depth/{stamp}.png")
    header = f"# {seq.name} (synthetic, dynslam)\n"
    (folder / "rgb.txt").write_text(header + "# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text(header + "# timestamp filename\n" + "\n".join(depth_lines) + "\n")
    (folder / "associations.txt").write_text("\n".join(assoc_lines) + "\n")
    ts, poses = seq.groundtruth()
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w, TUM's order
    gt = [f"{t:.6f} " + " ".join(f"{x:.9f}" for x in (*p[:3, 3], *q)) for t, p, q in zip(ts, poses, quats)]
    (folder / "groundtruth.txt").write_text(header + "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt) + "\n")
    fx, fy, cx, cy = seq.intrinsics
    camera = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": seq.width, "height": seq.height,
              "depth_scale": float(depth_scale)}
    (folder / CAMERA_FILE).write_text(yaml.safe_dump(camera, sort_keys=False))
    return folder
