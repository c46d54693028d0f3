"""Placing the synthetic movers: each is made to cross the camera's view at its own time while keeping
clear of the camera, the furniture and the other movers, and without hiding the scene.

Why planned against the camera path: random paths in a 6 x 5 m room mostly stay out of view or block
it; tests and evaluations need movers that are seen, but leave enough static scene to track.
"""
from __future__ import annotations

from typing import Callable, Protocol, Sequence

import numpy as np

from .synthetic_bodies import mover_bodies
from .synthetic_movers import Mover, candidate_movers
from .synthetic_primitives import _EDGES, _NEAR, _SIGNS


_PLAN_TRIES = 120
"""Candidate paths tried per mover at most (see ``MoverPlanner.plan``)."""


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


class PlannedScene(Protocol):
    """What the planner reads of a ``SyntheticSequence``: image size, intrinsics, seed, frame count and
    rate, the camera path and the static scene (a Protocol, so this module does not import that one)."""

    width: int
    height: int
    intrinsics: tuple[float, float, float, float]
    seed: int
    n_frames: int
    fps: float
    pose: Callable[[float], np.ndarray]
    primitives: list


class MoverPlanner:
    """Plans the movers of one ``SyntheticSequence`` (its image size, intrinsics, camera path, seed, frame
    count and static scene); ``plan(kinds)`` gives the movers in the order of ``kinds``."""

    def __init__(self, seq: PlannedScene) -> None:
        self.width, self.height, self.intrinsics = seq.width, seq.height, seq.intrinsics
        self.seed, self.n_frames, self.fps = seq.seed, seq.n_frames, seq.fps
        self.pose, self.primitives = seq.pose, seq.primitives

    def plan(self, kinds: Sequence[str]) -> list[Mover]:
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
            bodies = mover_bodies(kind, look, shape)
            best = None
            for _ in range(_PLAN_TRIES):
                t = duration / 2 if kind == "drag" else tc + shape.uniform(-0.3, 0.3) * slot
                movers = candidate_movers(kind, bodies, float(t), shape, cams[np.argmin(np.abs(times - t))],
                                          flow)
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
        # the terms are added one by one, in a fixed order, so that equal inputs give bit-equal costs
        cost, entries = 0.0, []
        for m in movers:
            pos, rot, _ = m.track(times)
            centre = pos + rot @ [0.0, 0.0, m.lift]
            cost += self._camera_gap_cost(m, centre, cams)
            if cost >= bound:
                return float(cost), entries
            rect = self._rects(cams, pos, rot, m.envelope, m.lift)
            cost, seen = self._screen_and_clearance_cost(cost, m, rect, centre, rot, planned, furniture)
            entries.append((m, rect, seen, centre, rot, self._centre_distance(centre, cams)))
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

    def _camera_gap_cost(self, m: Mover, centre: np.ndarray, cams: np.ndarray) -> float:
        """1000 x how far (summed over time, metres) the mover's centre comes closer than ``radius`` + 0.6 m
        to the camera centre."""
        axes = 3 if m.kind == "box" else 2  # the camera may pass right above or below a floating box
        gap = np.linalg.norm(centre[:, :axes] - cams[:, :axes, 3], axis=1)
        return 1000 * np.maximum(m.radius + 0.6 - gap, 0).sum()

    def _screen_and_clearance_cost(self, cost: float, m: Mover, rect: np.ndarray, centre: np.ndarray,
                                   rot: np.ndarray, planned: list, furniture: list) -> tuple[float, np.ndarray]:
        """``cost`` plus the screen-share and clearance (furniture, planned movers) terms of one mover, and
        its on-screen flags per time."""
        area = self.width * self.height
        share = (rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1]) / area
        seen = share > 0
        cost += 10 * np.maximum(share - 0.35, 0.0).sum()
        for pose, half in furniture:
            cost += 10 * _clash(centre[seen], rot[seen], m.envelope, pose[:3, 3], pose[:3, :3], half).sum()
        for other, _, other_seen, other_centre, other_rot, _ in planned:
            shown = seen | other_seen
            cost += 10 * _clash(centre[shown], rot[shown], m.envelope,
                                other_centre[shown], other_rot[shown], other.envelope).sum()
        return cost, seen

    def _centre_distance(self, centre: np.ndarray, cams: np.ndarray) -> np.ndarray:
        """Per time, the camera distance of the mover's centre; inf where the centre is off screen."""
        local = np.einsum("ti,tij->tj", centre - cams[:, :3, 3], cams[:, :3, :3])  # camera frame
        fx, fy, cx, cy = self.intrinsics
        z = np.maximum(local[:, 2], _NEAR)
        u, v = fx * local[:, 0] / z + cx, fy * local[:, 1] / z + cy
        centred = (local[:, 2] > _NEAR) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        return np.where(centred, np.linalg.norm(local, axis=1), np.inf)

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
        ``cams`` (T, 4, 4); like ``SyntheticSequence._window``, the part behind the near plane is cut off."""
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

