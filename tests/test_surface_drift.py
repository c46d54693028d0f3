"""A person's surface followed by the point tracks on it (frontend/dynamic/surface_drift.py) and the standing
test it adds to region_motion: still where the torso centre jumps (a monitor over part of the person), not
for a walker whose box holds static surfaces at their depth."""
from __future__ import annotations

import numpy as np

from frontend.dynamic.region_motion import RegionMotion
from frontend.dynamic.surface_drift import FrameTracks, PersonView, SurfaceTracker, surface_still
from slam.core.camera import PinholeCamera

FPS = 30.0
CAMERA = PinholeCamera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
Z = 2.0                                      # the person (and everything beside them) on a plane 2 m ahead


def _T_cw(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = -x
    return T


def _grid(x0: int, x1: int, y0: int, y1: int, step: int = 20) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.stack([xs.ravel(), ys.ravel()], axis=1).astype(float)


def test_a_step_is_the_surfaces_world_displacement_whatever_the_camera_does():
    """The camera moves 1 cm per frame along x; a static surface steps 0, one moving 3 cm per frame
    steps 3 cm, and the share of moved tracks tells the two apart."""
    depth = np.full((480, 640), Z, np.float32)
    origins = _grid(200, 440, 100, 400)
    shift_static = -0.01 * CAMERA.fx / Z                  # the image moves against the camera
    view = PersonView((150, 50, 500, 450), Z)
    for world_step, expect_share in ((0.0, 0.0), (0.03, 1.0)):
        tracks = origins + [shift_static + world_step * CAMERA.fx / Z, 0.0]
        surface = SurfaceTracker(FrameTracks(origins, tracks, depth), depth)
        on = surface.shared(view, view)
        assert on.all()
        step = surface.step(on, CAMERA, _T_cw(0.0), _T_cw(0.01))
        assert np.allclose(step.displacement, [world_step, 0.0, 0.0], atol=1e-9)
        assert step.moved_share == expect_share
    # Depth readings that differ by +-4 cm between the frames (noise along the line of sight) move no track.
    noisy = depth.copy()
    band = (np.arange(480) // 20) % 2 == 0                # every other row of tracks nearer, the rest farther
    noisy[band] += 0.04
    noisy[~band] -= 0.04
    tracks = origins + [shift_static, 0.0]
    surface = SurfaceTracker(FrameTracks(origins, tracks, noisy), depth)
    assert surface.step(surface.shared(view, view), CAMERA, _T_cw(0.0), _T_cw(0.01)).moved_share == 0.0
    # Too few tracks on the person, or a median step no person makes in 1/30 s: no step.
    few = SurfaceTracker(FrameTracks(origins[:4], origins[:4], depth), depth)
    assert few.step(np.ones(4, bool), CAMERA, np.eye(4), np.eye(4)) is None
    jump = SurfaceTracker(FrameTracks(origins, origins + [0.2 * CAMERA.fx / Z, 0.0], depth), depth)
    assert jump.step(np.ones(len(origins), bool), CAMERA, np.eye(4), np.eye(4)) is None


def test_tracks_off_the_persons_layer_or_box_are_not_theirs():
    depth = np.full((480, 640), 4.0, np.float32)
    depth[100:400, 250:390] = Z                           # the person; the wall 2 m behind them
    origins = _grid(200, 440, 50, 450)
    surface = SurfaceTracker(FrameTracks(origins, origins, depth), depth)
    on = surface.shared(PersonView((240, 90, 400, 410), Z), PersonView((240, 90, 400, 410), Z))
    inside = (origins[:, 0] >= 250) & (origins[:, 0] < 390) & (origins[:, 1] >= 100) & (origins[:, 1] < 400)
    assert np.array_equal(on, inside)
    assert not surface.shared(PersonView((240, 90, 400, 410), None), PersonView((240, 90, 400, 410), Z)).any()


def test_surface_still_needs_measured_steps_a_short_drift_and_few_moved_tracks():
    at = [np.zeros(3)] * 10
    assert surface_still(at, [False] + [True] * 9, [np.nan] + [0.1] * 9, 0.15)
    assert not surface_still(at, [False] * 5 + [True] * 5, [np.nan] * 5 + [0.1] * 5, 0.15)   # half measured
    assert not surface_still(at, [False] + [True] * 9, [np.nan] + [0.5] * 9, 0.15)           # tracks move
    walked = [np.array([0.02 * k, 0.0, 0.0]) for k in range(10)]
    assert not surface_still(walked, [False] + [True] * 9, [np.nan] + [0.1] * 9, 0.15)


def _run_person(frames: int, motion: RegionMotion, walker_step_m: float, clutter: int, centres) -> list[bool]:
    """A person on the 2 m plane, seen by a static camera: ``walker_step_m`` per frame along x (0: standing),
    with ``clutter`` static tracks at their depth inside their box (a desk beside them); the torso centre
    given to the test is ``centres(k)`` (camera frame)."""
    depth = np.full((480, 640), Z, np.float32)
    body = _grid(280, 360, 120, 380)                       # 52 tracks
    desk = _grid(150, 270, 300, 420, step=10)[:clutter]     # the same static ones in the box on every frame
    shift = walker_step_m * CAMERA.fx / Z
    flags = []
    for k in range(frames):
        box = (int(140 + k * shift), 100, int(380 + k * shift), 430)
        views = [PersonView(box, Z)]
        origins = np.vstack([body + [(k - 1) * shift, 0.0], desk + [(k - 1) * shift, 0.0]])
        tracks = np.vstack([body + [k * shift, 0.0], desk + [(k - 1) * shift, 0.0]])
        flow = FrameTracks(origins, tracks, depth)
        flags.append(bool(motion.classify([centres(k)], _T_cw(0.0), k / FPS, views, flow if k else None)[0]))
        motion.commit(_T_cw(0.0))
    return flags


def test_a_person_whose_centre_jumps_between_a_monitor_and_them_is_found_still_by_their_surface():
    """Behind a monitor the torso centre is the monitor (0.8 m) on some frames and the person (2 m) on
    others: the centre's test never holds, and the track goes on only through the surface's tracks."""
    jumping = lambda k: np.array([0.0, 0.0, 0.8 if (k // 5) % 2 else Z])     # noqa: E731
    flags = _run_person(60, RegionMotion(0.5, 0.15, CAMERA), 0.0, 0, jumping)
    assert not any(flags[:30])                    # the surface's window: twice the centre's (1 s)
    assert all(flags[31:])
    assert not any(_run_person(60, RegionMotion(0.5, 0.15), 0.0, 0, jumping))   # centres alone: never


def test_a_walker_is_not_found_still_though_the_static_tracks_at_their_depth_outvote_theirs():
    """A walker (1.2 m/s) whose box holds more static tracks at their depth than their own: the median
    step is the desk's, but the share of moved tracks shows the walk."""
    centre = lambda k: np.array([0.04 * k, 0.0, Z]) if k % 10 < 5 else np.array([0.04 * k, 0.0, 0.8])  # noqa: E731
    motion = RegionMotion(0.5, 0.15, CAMERA)
    assert not any(_run_person(60, motion, 0.04, 78, centre))
    track = motion._tracks[0]
    assert np.median(track.shares[1:]) == 0.4 and np.linalg.norm(track.surface[-1] - track.surface[0]) < 0.1
