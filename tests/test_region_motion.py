"""Who stands still (frontend/dynamic/region_motion.py): a person's torso followed in world coordinates."""
from __future__ import annotations

import numpy as np
import pytest

from frontend.dynamic.region_motion import RegionCarry, RegionMotion, box_centre, confirmed_regions, front_depth
from slam.core.camera import PinholeCamera

FPS = 30.0
CAMERA = PinholeCamera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)


def _T_cw(x: float) -> np.ndarray:
    """A camera at (x, 0, 0) looking along +z (world -> camera)."""
    T = np.eye(4)
    T[0, 3] = -x
    return T


def _run(world_positions: list[np.ndarray], camera_x: list[float], motion: RegionMotion) -> list[bool]:
    """Feed one person per frame (world position seen from a moving camera); the still flag per frame."""
    flags = []
    for k, (p_w, x) in enumerate(zip(world_positions, camera_x)):
        T = _T_cw(x)
        centre_c = T[:3, :3] @ p_w + T[:3, 3]
        flags.append(bool(motion.classify([centre_c], T, k / FPS)[0]))
        motion.commit(T)
    return flags


def test_a_person_standing_still_is_still_once_followed_for_the_window_while_the_camera_moves():
    n = 40
    camera_x = list(np.linspace(0.0, 0.8, n))            # the camera moves 0.6 m/s: the image position changes
    person = [np.array([0.5, 0.0, 2.0])] * n
    flags = _run(person, camera_x, RegionMotion(0.5, 0.15))
    window_frames = int(np.ceil(0.5 * FPS))
    assert not any(flags[:window_frames])                # not followed long enough yet: moving (the safe side)
    assert all(flags[window_frames + 1:])


def test_sway_stays_still_and_walking_never_is():
    n = 60
    rng = np.random.default_rng(0)
    sway = [np.array([0.5, 0.0, 2.0]) + rng.normal(0, 0.02, 3) for _ in range(n)]   # 2 cm jitter per axis
    assert all(_run(sway, [0.0] * n, RegionMotion(0.5, 0.15))[20:])
    slow_walk = [np.array([0.5 + 0.5 * k / FPS, 0.0, 2.0]) for k in range(n)]      # 0.5 m/s
    assert not any(_run(slow_walk, [0.0] * n, RegionMotion(0.5, 0.15)))


def test_a_person_who_starts_walking_is_moving_again_within_a_few_frames():
    n, start = 60, 30
    path = [np.array([0.5 + max(k - start, 0) * 1.0 / FPS, 0.0, 2.0]) for k in range(n)]   # then 1 m/s
    flags = _run(path, [0.0] * n, RegionMotion(0.5, 0.15))
    assert flags[start - 1]
    first_moving = start + flags[start:].index(False)
    assert first_moving - start <= 5                      # 0.15 m at 1 m/s: ~4.5 frames
    assert not any(flags[first_moving:])


def test_a_lost_frame_or_a_missing_prediction_forgets_who_stood_still():
    motion = RegionMotion(0.5, 0.15)
    person = [np.array([0.0, 0.0, 2.0])] * 30
    assert _run(person, [0.0] * 30, motion)[-1]
    centre = person[0]
    assert not motion.classify([centre], None, 1.0)[0]  # no predicted pose: nothing to compare in the world
    motion.commit(None)                                  # lost: the tracks end
    assert not motion.classify([centre], np.eye(4), 1.05)[0]


def test_two_people_keep_their_own_tracks_and_a_new_one_starts_as_moving():
    motion = RegionMotion(0.5, 0.15)
    standing = np.array([-0.6, 0.0, 2.0])
    for k in range(30):
        walker = np.array([0.6, 0.0, 2.0 + k / FPS])   # walking away at 1 m/s beside them
        still = motion.classify([walker, standing], np.eye(4), k / FPS)
        motion.commit(np.eye(4))
    assert still.tolist() == [False, True]
    newcomer = np.array([0.0, 0.0, 3.0])
    assert motion.classify([standing, newcomer], np.eye(4), 1.0).tolist() == [True, False]


def test_off_and_without_depth_nobody_is_still():
    off = RegionMotion(0.0, 0.15)
    assert not off.enabled
    assert not any(_run([np.zeros(3)] * 30, [0.0] * 30, off))
    on = RegionMotion(0.5, 0.15)
    assert on.classify([None], np.eye(4), 0.0).tolist() == [False]


def test_box_centre_is_the_torso_not_the_background_seen_beside_it():
    depth = np.full((480, 640), 4.0, np.float32)
    depth[100:400, 280:360] = 2.0                        # the body: the middle third of a wider box
    depth[200:220, 300:310] = 0.0                        # a hole without depth is skipped
    centre = box_centre((220, 100, 420, 400), depth, CAMERA)
    assert centre[2] == pytest.approx(2.0)
    assert centre[0] == pytest.approx((320 - CAMERA.cx) * 2.0 / CAMERA.fx, abs=0.01)
    assert box_centre((5, 5, 5, 9), depth, CAMERA) is None                 # an empty box
    assert box_centre((220, 100, 420, 400), np.zeros_like(depth), CAMERA) is None


# --- regions that move where no detector looks --------------------------------------------------------

def _tracks_in(x0: int, y0: int, x1: int, y1: int, n: int, rng) -> np.ndarray:
    return np.c_[rng.uniform(x0, x1 - 1, n), rng.uniform(y0, y1 - 1, n)]


def test_a_cpr_region_with_enough_moving_tracks_is_confirmed_whole():
    rng = np.random.default_rng(0)
    candidates = np.zeros((480, 640), bool)
    candidates[100:300, 50:150] = True        # a walker cpr flags
    candidates[200:400, 400:600] = True       # a static sub-cloud cpr flags too (its MAD threshold)
    walker, wall = _tracks_in(50, 100, 150, 300, 20, rng), _tracks_in(400, 200, 600, 400, 100, rng)
    tracks = np.vstack([walker, wall, _tracks_in(0, 0, 640, 80, 400, rng)])  # and tracks outside both
    moving = np.zeros(len(tracks), bool)
    moving[:5] = True                          # 5 of the walker's 20 tracks are off their epipolar lines
    moving[20:23] = True                       # 3 RANSAC outliers among the wall's 100
    moving[120:130] = True                     # moving tracks outside every cpr region count for nothing
    assert moving.mean() < 0.05                # 18 of 520: the frame's epipolar test is trustworthy
    depth = np.full((480, 640), 4.0, np.float32)
    depth[100:300, 50:150] = 2.0              # the walker stands in front of the wall
    depth[250:300, 50:150] = 4.0              # their region also holds some wall behind them
    region = confirmed_regions(candidates, tracks, moving, depth, 3, 0.2)
    assert region is not None and region.dtype == np.float32
    # The walker's pixels, not the wall their sub-cloud also holds, nor the static sub-cloud.
    assert region[100:250, 50:150].all() and region.sum() == 150 * 100


def test_too_few_votes_confirm_nothing_and_off_means_none():
    rng = np.random.default_rng(1)
    candidates = np.zeros((480, 640), bool)
    candidates[100:300, 50:150] = True
    tracks = np.vstack([_tracks_in(50, 100, 150, 300, 8, rng), _tracks_in(200, 0, 640, 480, 200, rng)])
    depth = np.full((480, 640), 2.0, np.float32)
    moving = np.zeros(len(tracks), bool)
    moving[:2] = True                          # a quarter of the region's tracks, but only two
    assert confirmed_regions(candidates, tracks, moving, depth, 3, 0.2) is None
    moving[:3] = True
    assert confirmed_regions(candidates, tracks, moving, depth, 3, 0.2) is not None
    assert confirmed_regions(np.zeros_like(candidates), tracks, moving, depth, 3, 0.2) is None
    assert confirmed_regions(candidates, np.zeros((0, 2)), np.zeros(0, bool), depth, 3, 0.2) is None


def test_a_frame_whose_tracks_fail_the_epipolar_test_everywhere_confirms_nothing():
    """Motion blur and fast turns make LK tracks fail F all over the frame (fr1/rpy: up to a third):
    then the test is no evidence of anything moving."""
    rng = np.random.default_rng(2)
    candidates = np.zeros((480, 640), bool)
    candidates[100:300, 50:150] = True
    tracks = np.vstack([_tracks_in(50, 100, 150, 300, 20, rng), _tracks_in(200, 0, 640, 480, 80, rng)])
    moving = np.zeros(len(tracks), bool)
    moving[:5] = True
    depth = np.full((480, 640), 2.0, np.float32)
    assert confirmed_regions(candidates, tracks, moving, depth, 3, 0.2) is not None     # 5 %: trusted
    moving[20:30] = True                                                               # 15 %: blur
    assert confirmed_regions(candidates, tracks, moving, depth, 3, 0.2) is None


def test_a_region_joining_a_walker_to_the_wall_is_decided_on_the_walkers_depth():
    """cpr's sub-cloud can join a person to the wall behind them: the wall's many still tracks must not
    outvote the person's (5 of 110 tracks move, 5 of the person's 10)."""
    rng = np.random.default_rng(3)
    candidates = np.zeros((480, 640), bool)
    candidates[100:400, 50:450] = True
    depth = np.full((480, 640), 3.0, np.float32)
    depth[100:300, 50:150] = 1.0                                   # the walker, in front of the wall
    tracks = np.vstack([_tracks_in(50, 100, 150, 300, 10, rng), _tracks_in(160, 100, 450, 400, 100, rng)])
    moving = np.zeros(len(tracks), bool)
    moving[:5] = True
    region = confirmed_regions(candidates, tracks, moving, depth, 3, 0.2)
    assert region is not None and region.sum() == 200 * 100 and region[100:300, 50:150].all()


def test_front_depth_is_the_mover_not_the_background_its_silhouette_drags():
    # Three tracks on a person at ~0.8 m and five on the wall just behind their silhouette.
    assert front_depth(np.array([2.5, 0.82, 2.52, 0.8, 2.55, 2.6, 0.85, 2.61, 0.0]), 3, 0.5) == pytest.approx(0.82)
    assert front_depth(np.array([2.5, 0.82, 2.52, 0.8, 2.55]), 3, 0.5) == pytest.approx(2.52)   # two: no group
    assert front_depth(np.array([1.0, 2.0]), 3, 0.5) is None


def _person_frame(x0: int, depth_m: float = 1.0) -> np.ndarray:
    depth = np.full((480, 640), 3.0, np.float32)
    depth[100:300, x0:x0 + 100] = depth_m
    return depth


def test_a_confirmed_region_is_carried_along_its_own_tracks_for_a_few_frames_of_thin_evidence():
    rng = np.random.default_rng(4)
    carry = RegionCarry(hold_frames=3)
    allowed = np.ones((480, 640), bool)
    confirmed = np.zeros((480, 640), np.float32)
    confirmed[100:300, 100:200] = 1.0
    assert carry.update(confirmed, None, None, None, _person_frame(100), allowed) is confirmed
    x0, carried = 100, []
    for _ in range(5):                                              # the person moves 20 px per frame
        person = _tracks_in(x0, 100, x0 + 100, 300, 6, rng)
        # Tracks that start on the person's edge and end on the wall beside them (an occluding edge
        # drags LK windows): they must not pull the shift or the depth band.
        edge = _tracks_in(x0 + 90, 100, x0 + 100, 300, 6, rng)
        origins = np.vstack([person, edge, _tracks_in(400, 0, 640, 480, 50, rng)])
        tracks = origins + np.r_[np.tile([20.0, 0.0], (6, 1)), np.tile([45.0, 0.0], (6, 1)), np.zeros((50, 2))]
        moving = np.zeros(len(tracks), bool)
        moving[0] = True                                            # one of the person's tracks fails F
        moving[6:9] = True                                          # and three dragged ones
        x0 += 20
        region = carry.update(None, origins, tracks, moving, _person_frame(x0), allowed)
        carried.append(None if region is None else region.astype(bool))
    # Carried three frames (the hold), shifted with the person, the wall behind left out.
    for k in range(3):
        x = 120 + 20 * k
        assert carried[k] is not None and carried[k][100:300, x:x + 80].all() and carried[k].sum() <= 200 * 100
    assert carried[3] is None and carried[4] is None


def test_a_region_whose_own_tracks_stopped_moving_or_left_is_not_carried():
    rng = np.random.default_rng(5)
    allowed = np.ones((480, 640), bool)
    confirmed = np.zeros((480, 640), np.float32)
    confirmed[100:300, 100:200] = 1.0
    origins = np.vstack([_tracks_in(100, 100, 200, 300, 6, rng), _tracks_in(300, 0, 640, 480, 50, rng)])
    still = np.zeros(len(origins), bool)
    carry = RegionCarry(hold_frames=5)
    carry.update(confirmed, None, None, None, _person_frame(100), allowed)
    assert carry.update(None, origins, origins, still, _person_frame(100), allowed) is None   # no motion left
    carry.update(confirmed, None, None, None, _person_frame(100), allowed)
    moving = still.copy()
    moving[0] = True
    assert carry.update(None, origins, origins, moving, _person_frame(100), allowed) is not None
    # Inside a person box (not allowed) the box methods decide, not the carry.
    carry.update(confirmed, None, None, None, _person_frame(100), allowed)
    assert carry.update(None, origins, origins, moving, _person_frame(100), np.zeros_like(allowed)) is None


# --- people followed for less than a window -------------------------------------------------------------

def _short_track(motion: RegionMotion, positions: list[np.ndarray], start: int = 0) -> list:
    """Feed one person for len(positions) frames (still camera), then a frame without them; returns the
    ``ended_still`` of every commit."""
    ended = []
    for k, p_w in enumerate(positions + [None]):
        motion.classify([] if p_w is None else [p_w], np.eye(4), (start + k) / FPS)
        motion.commit(np.eye(4))
        ended.append(list(motion.ended_still))
    return ended


def test_a_box_that_came_and_went_without_moving_is_still_over_its_life():
    """A detection on something static (YOLOX-Nano's 'person' on fr1/rpy's desk) lasts a few frames: it
    never reaches a whole window, and is judged over its own life when its track ends."""
    rng = np.random.default_rng(6)
    static = [np.array([0.3, 0.2, 1.5]) + rng.normal(0, 0.01, 3) for _ in range(6)]   # 0.17 s, 1 cm jitter
    ended = _short_track(RegionMotion(0.5, 0.15), static)
    assert not any(ended[:-1]) and len(ended[-1]) == 1        # judged when it ends, not before
    # A slow walker (0.5 m/s) over the same life is not still; nor is a track too short to judge (0.1 s).
    walker = [np.array([0.3 + 0.5 * k / FPS, 0.2, 1.5]) for k in range(6)]
    assert not any(_short_track(RegionMotion(0.5, 0.15), walker))
    assert not any(_short_track(RegionMotion(0.5, 0.15), static[:3]))
    # Still going at the end of the run: finish() judges it the same way.
    motion = RegionMotion(0.5, 0.15)
    for k, p_w in enumerate(static):
        motion.classify([p_w], np.eye(4), k / FPS)
        motion.commit(np.eye(4))
    assert len(motion.finish()) == 1
    assert RegionMotion(0.0, 0.15).finish() == []
