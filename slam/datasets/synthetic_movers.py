"""Moving objects of the synthetic generator: the named mover sets, the ``Mover`` model, the loops they
walk (or float) around, and random candidate paths that cross the camera's view at a given time.

Where they go is chosen in ``synthetic_planning`` (which tries candidates from here against the camera
path), what they look like in ``synthetic_bodies``; ``SyntheticSequence(movers=...)`` ties them together.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence, Union

import numpy as np
from scipy.spatial.transform import Rotation

from .synthetic_bodies import Body
from .synthetic_primitives import Box

MOVER_PRESETS: dict[str, tuple[str, ...]] = {
    "none": (),
    "boxes": ("box", "box"),
    "people": ("person", "person", "person"),
    "crowd": ("person", "person", "person", "box", "box"),
    "drag": ("drag",),
}
"""Named mover sets. Elements are the single kinds "person", "box" and "drag" (a chair that stands still
for the first half of the sequence, then is dragged along by a person walking past it)."""


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
        last = self._last     # read once: a reader thread may render another time meanwhile
        if last[0] != time:
            pos, rot, gait = self.track(np.array([time], float))
            pose = np.eye(4)
            pose[:3, :3], pose[:3, 3] = rot[0], pos[0]
            last = (time, (pose, float(gait[0])))
            self._last = last
        return last[1]

    def part_pose(self, k: int, time: float) -> np.ndarray:
        pose, gait = self.root(time)
        return pose @ self.part_local[k](gait)


@dataclass
class _Route:
    """Where a candidate mover travels: around ``loop``, reaching arc length ``s_hit`` (in view) at the
    crossing time ``tc``, in ``direction`` (+1 counter-clockwise, -1 clockwise; a float, or a numpy
    float for the shared flow, kept as drawn so the paths stay bit-identical)."""

    loop: WalkLoop
    s_hit: float
    direction: float
    tc: float
    radius: float

    @property
    def flip(self) -> float:
        """Yaw added to the loop heading so that a figure faces the way it walks."""
        return np.pi if self.direction < 0 else 0.0


@dataclass
class _Gait:
    """A walking figure's size and stride: body ``height``, ``stride`` length (m per gait cycle), gait
    phase ``gait0`` at time 0, and the ``envelope`` half sizes that bound it with its limbs swinging."""

    height: float
    stride: float
    gait0: float
    envelope: np.ndarray


def candidate_movers(kind: str, bodies: list[Body], tc: float, rng: np.random.Generator, cam: np.ndarray,
                     flow: float = 1.0) -> list[Mover]:
    """A random loop and motion for one mover ("drag": person and chair) crossing the view at ``tc`` seen
    from camera pose ``cam``; ``flow`` is the way most people walk round. The ``rng`` draws keep one
    fixed order (loop, crossing, direction, then the kind's motion), which seeded sequences rely on."""
    radius = 0.3 if kind != "box" else float(np.linalg.norm(bodies[0][0][0].half))
    loop = _random_loop(rng, radius)
    s_hit = _arc_in_view(loop, cam, rng)
    route = _Route(loop, s_hit, _travel_direction(kind, rng, flow), tc, radius)
    if kind == "box":
        return [_floating_box(bodies[0], route, rng)]
    gait = _random_gait(bodies[0], rng)
    if kind == "person":
        return [_walking_person(bodies[0], gait, route, rng)]
    return _dragging_person(bodies, gait, route, rng)


def _random_loop(rng: np.random.Generator, radius: float) -> WalkLoop:
    """A rounded rectangle around a point near the room centre that keeps ``radius`` from the walls."""
    cx, cy = rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5)
    ax = rng.uniform(1.2, max(1.21, 2.9 - radius - abs(cx)))
    ay = rng.uniform(1.0, max(1.01, 2.4 - radius - abs(cy)))
    return WalkLoop((cx, cy), (ax, ay), rng.uniform(0.3, min(ax, ay)))


def _arc_in_view(loop: WalkLoop, cam: np.ndarray, rng: np.random.Generator) -> float:
    """Arc length of the loop point seen along the (jittered) horizontal view direction of ``cam``."""
    arc = np.linspace(0.0, loop.length, 400, endpoint=False)
    rel = loop.at(arc)[0] - cam[:2, 3]
    bearing = np.arctan2(cam[1, 2], cam[0, 2]) + rng.uniform(-0.35, 0.35)
    off = np.abs(np.angle(np.exp(1j * (np.arctan2(rel[:, 1], rel[:, 0]) - bearing))))
    return float(arc[np.argmin(off)])


def _travel_direction(kind: str, rng: np.random.Generator, flow: float) -> float:
    """+1 or -1 (counter-clockwise or not); people mostly walk the same way round (``flow``, as in a
    corridor), so they seldom meet head-on; boxes go either way."""
    if kind == "box":
        return 1.0 if rng.uniform() < 0.5 else -1.0
    return flow if rng.uniform() < 0.85 else -flow


def _floating_box(body: Body, route: _Route, rng: np.random.Generator) -> Mover:
    """A box floating round the loop at 0.3-0.8 m/s, bobbing up and down and tumbling at 25-60 deg/s."""
    boxes, locals_ = body
    loop, direction, tc, radius = route.loop, route.direction, route.tc, route.radius
    v, z0 = rng.uniform(0.3, 0.8), rng.uniform(max(radius + 0.15, 0.8), min(2.85 - radius, 1.9))
    zamp, zw, zphi = rng.uniform(0.03, 0.12), rng.uniform(0.5, 1.5), rng.uniform(0, 2 * np.pi)
    axis = rng.normal(size=3)
    spin = axis / np.linalg.norm(axis) * np.radians(rng.uniform(25, 60)) * rng.choice([-1, 1])
    q = rng.normal(size=4)
    rot0 = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    s0 = route.s_hit - direction * v * tc

    def box_track(ts: np.ndarray):
        xy, _ = loop.at(s0 + direction * v * ts)
        z = z0 + zamp * np.sin(zw * ts + zphi)
        return np.c_[xy, z], Rotation.from_rotvec(ts[:, None] * spin).as_matrix() @ rot0, 0 * ts

    return Mover("box", box_track, boxes, locals_, lambda t: True, radius, boxes[0].half, 0.0)


def _random_gait(body: Body, rng: np.random.Generator) -> _Gait:
    """Height (from the torso, which is scaled with it), stride and starting gait phase of a figure."""
    boxes, _ = body
    height = 1.75 * boxes[0].half[2] / 0.31
    stride, gait0 = rng.uniform(1.2, 1.5), rng.uniform(0, 2 * np.pi)
    envelope = np.array([0.22, 0.28, height / 2])  # swinging limbs included
    return _Gait(height, stride, gait0, envelope)


def _walking_person(body: Body, gait: _Gait, route: _Route, rng: np.random.Generator) -> Mover:
    """A person walking round the loop at 0.9-1.2 m/s, the pace wavering a little."""
    boxes, locals_ = body
    loop, direction, tc, flip = route.loop, route.direction, route.tc, route.flip
    stride, gait0 = gait.stride, gait.gait0
    v, ww, wphi = rng.uniform(0.9, 1.2), rng.uniform(0.8, 2.0), rng.uniform(0, 2 * np.pi)
    wamp = 0.08 * v / ww

    def dist(ts):
        return v * ts + wamp * (np.sin(ww * ts + wphi) - np.sin(wphi))

    s0 = route.s_hit - direction * float(dist(np.array([tc]))[0])

    def person_track(ts: np.ndarray):
        d = dist(ts)
        xy, head = loop.at(s0 + direction * d)
        return np.c_[xy, 0 * ts], _rot_z(head + flip), gait0 + 2 * np.pi * d / stride

    return Mover("person", person_track, boxes, locals_, lambda t: True, route.radius, gait.envelope,
                 gait.height / 2)


def _dragging_person(bodies: list[Body], gait: _Gait, route: _Route, rng: np.random.Generator) -> list[Mover]:
    """A person walking at a steady pace and the chair they drag: the chair stands beside the loop half a
    metre behind the point the person reaches mid-sequence, and from then on follows with a growing lag."""
    (boxes, locals_), (chair_boxes, chair_locals) = bodies
    loop, s_hit, direction, tc, flip = route.loop, route.s_hit, route.direction, route.tc, route.flip
    stride, gait0 = gait.stride, gait.gait0
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

    return [Mover("person", walker, boxes, locals_, lambda t: True, route.radius, gait.envelope,
                  gait.height / 2),
            Mover("chair", chair, chair_boxes, chair_locals, lambda t: t > tc, 0.32,
                  np.array([0.22, 0.22, 0.45]), 0.45)]
