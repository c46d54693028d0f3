"""The textured box primitive of the synthetic generator, its random textures, and the box corner/edge
tables shared by the renderer (``synthetic``) and the mover planner (``synthetic_planning``).

Why a module of its own: both the scene renderer and the moving objects build on ``Box``; keeping it
below both avoids an import cycle between ``synthetic`` and the mover modules.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

TEXEL = 0.01
"""Texture resolution in metres: 1 cm is ~5 px at 1 m and ~1 px at 5 m, so nearest lookup stays crisp
without aliasing much at the far wall."""

_SHAPE_SCALES = ((0.3, 1.0, 2.0), (0.1, 0.3, 20.0), (0.03, 0.1, 110.0))
"""(min size m, max size m, shapes per square metre): corners at every ORB pyramid level and distance."""


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


def add_textures(box: Box, rng: np.random.Generator) -> Box:
    """Give each face of ``box`` its own random texture (face order -x, +x, -y, +y, -z, +z); a face on
    axis k is textured over the next two axes (k+1, k+2) mod 3, which is how the renderer looks it up."""
    box.textures = []
    for axis in range(3):
        i, j = (axis + 1) % 3, (axis + 2) % 3
        for _side in range(2):
            box.textures.append(make_texture(rng, 2 * box.half[i], 2 * box.half[j]))
    return box


# Box corners (8, 3) as +-1 signs, the 12 edges as corner index pairs, and the near plane (m).
_SIGNS = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
_EDGES = np.array([(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(_SIGNS[i] != _SIGNS[j]) == 1])
_NEAR = 0.05
_FACE_AXES = np.array([[(f // 2 + 1) % 3, (f // 2 + 2) % 3] for f in range(6)])
"""Per box face (f // 2 is its normal's axis): the box axes along its texture's u and v."""

SENSOR_MIN_RANGE_M = 0.5
"""Nearer than this a structured-light RGB-D camera measures nothing: the Kinect v1 of TUM and the Xtion of
Bonn (specified from ~0.5 m; the nearest valid depth in fr1/rpy's first 400 frames is 0.58 m, in Bonn crowd's
first 480 0.75 m). ``SyntheticSequence.sensor_min_range_m`` set to it shows a person who comes nearer in
colour, without depth; its default (0) keeps the exact depth (docs/dynamic.md, "Nearer than the sensor
ranges")."""


def sensed_depth(depth: np.ndarray, min_range_m: float) -> np.ndarray:
    """``depth`` as a sensor with that minimum range reports it: 0 (no measurement) where the nearest surface
    is nearer; a new array when the range is set, ``depth`` itself otherwise."""
    return np.where(depth < min_range_m, np.float32(0), depth) if min_range_m > 0 else depth
