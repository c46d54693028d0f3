"""What the synthetic movers look like: the parts of a walking person, a cardboard box and a chair, with
their part-to-root poses over the gait phase and their clothes-, cardboard- and wood-like textures.

Why unlike the room: the textures are meant to look like the objects a detector is trained on (cloth
patterns, skin and hair, printed cardboard), not like the room's random shapes.
"""
from __future__ import annotations

from typing import Callable, Optional

import cv2
import numpy as np

from .synthetic_primitives import TEXEL, Box, _pt

Body = tuple[list[Box], list[Callable[[float], np.ndarray]]]
"""A mover's parts and, per part, its part-to-root pose as a function of the gait phase."""


def mover_bodies(kind: str, look: np.random.Generator, shape: np.random.Generator) -> list[Body]:
    """The bodies of one mover of ``kind``: [person] ("person"), [box] ("box") or [person, chair] ("drag").
    Textures draw from ``look``, sizes from ``shape`` (the planner's path stream, whose draw order this
    keeps, so seeded sequences do not change)."""
    bodies = [_person(look, shape.uniform(1.6, 1.85))] if kind != "box" else []
    if kind == "box":
        half = shape.uniform(0.2, 0.3, 3)
        bodies.append(([Box(half, None, dynamic=True, textures=_cardboard(look, half))],
                       [lambda g: np.eye(4)]))
    if kind == "drag":
        half = np.array([0.22, 0.22, 0.45])
        bodies.append(([Box(half, None, dynamic=True, textures=_chair(look, half))],
                       [lambda g: _local((0.0, 0.0, 0.45))]))
    return bodies


def _local(offset, angle: float = 0.0, drop: float = 0.0) -> np.ndarray:
    """Part-to-root pose: translate to ``offset`` (a joint), rotate by ``angle`` about the root's y axis
    (a swing in the walking plane), then translate by ``drop`` down the part (joint to part centre)."""
    c, s = np.cos(angle), np.sin(angle)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose[:3, 3] = np.asarray(offset, float) + pose[:3, :3] @ [0.0, 0.0, -drop]
    return pose


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
    # Folds, seams, buttons and logos: real clothes carry corners that ORB finds, which the methods
    # relying on the person's own features (depth layers, flow) need.
    details = np.random.default_rng(int(rng.integers(2**31)))
    for face in torso_tex:
        _shapes(face, details, 12, 0.01, 0.04)
    boxes = [Box(torso, None, dynamic=True, textures=torso_tex),
             Box(head, None, dynamic=True, textures=_paint(head, head_colour))]
    locals_ = [lambda g: _local((0, 0, hip + torso[2] + bob(g))),
               lambda g: _local((0, 0, hip + 2 * torso[2] + head[2] + bob(g)))]  # head on the shoulders: no gap
    for side in (1, -1):
        leg = np.array([0.085, 0.08, leg_h])
        leg_tex = _paint(leg, trousers)
        for face in leg_tex:
            _shapes(face, details, 6, 0.01, 0.03)
        boxes.append(Box(leg, None, dynamic=True, textures=leg_tex))
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
