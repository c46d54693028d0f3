"""The free-space test of the keyframe masks (frontend/dynamic/free_space.py): a surface standing where an
earlier frame saw through to a farther one moved in; one consistent with the earlier frames did not; one
the earlier frame could not see gives no evidence."""
import cv2
import numpy as np
import pytest

from frontend.dynamic.base import MethodOutput
from frontend.dynamic.free_space import Evidence, FreeSpaceCheck
from frontend.dynamic.keyframe_masks import MaskParts, compose_mask
from slam.core.camera import PinholeCamera

CAMERA = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
WALL_M = 3.0


def pose_cw(x: float) -> np.ndarray:
    """World-to-camera of a camera at (x, 0, 0) looking along +z."""
    T = np.eye(4)
    T[0, 3] = -x
    return T


def wall(box: tuple[int, int, int, int] = None, box_depth: float = 1.5) -> np.ndarray:
    depth = np.full((480, 640), WALL_M, np.float32)
    if box is not None:
        x0, y0, x1, y1 = box
        depth[y0:y1, x0:x1] = box_depth
    return depth


def check(lags=(0.5, 1.0), region_lags=(), clear_lags=()) -> FreeSpaceCheck:
    return FreeSpaceCheck(CAMERA, lags, margin_m=0.1, window_px=20, region_lags_s=region_lags,
                          clear_lags_s=clear_lags)


def blind() -> np.ndarray:
    """A frame that saw nothing where the keyframe looks (turned away, or no depth): no evidence from it."""
    return np.zeros((480, 640), np.float32)


def test_a_surface_that_moved_in_front_of_the_wall_is_moving_and_the_wall_is_not():
    fs = check()
    fs.remember(0.0, wall(), pose_cw(0.0))                      # the wall alone, 1 s before
    fs.remember(0.5, wall(), pose_cw(0.05))
    box = (200, 100, 360, 400)
    moving, known, region = fs.keyframe(None, 1.0, wall(box), pose_cw(0.1))  # the camera moved 10 cm sideways too
    inner = (slice(box[1] + 10, box[3] - 10), slice(box[0] + 10, box[2] - 10))
    assert moving[inner].all() and known[inner].all()
    assert region[inner].all() and not region.any(axis=0)[400:].any()     # a whole region moved in
    far = (slice(0, 480), slice(420, 600))                       # wall, away from the box, in both views
    assert known[far].all() and not moving.any(axis=0)[400:].any()


def test_a_surface_that_was_there_before_is_consistent():
    fs = check()
    box = (200, 100, 360, 400)
    fs.remember(0.0, wall(box), pose_cw(0.0))                    # the box stood there 1 s ago too
    fs.remember(0.5, wall(box), pose_cw(0.0))
    moving, known, region = fs.keyframe(None, 1.0, wall(box), pose_cw(0.0))
    assert not region.any()
    assert not moving[110:390, 210:350].any() and known[110:390, 210:350].all()


def test_what_the_earlier_frames_could_not_see_gives_no_evidence():
    fs = check()
    near = (100, 100, 540, 380)                                  # a large near board hid the wall behind it
    fs.remember(0.0, wall(near, 1.0), pose_cw(0.0))
    fs.remember(0.5, wall(near, 1.0), pose_cw(0.0))
    moving, known, region = fs.keyframe(None, 1.0, wall(), pose_cw(0.0))       # the board is gone: the wall is seen again
    assert not known[150:330, 150:490].any() and not moving[150:330, 150:490].any()


def test_no_earlier_frame_far_enough_back_no_evidence_and_the_memory_is_bounded():
    fs = check()
    assert fs.keyframe(None, 0.0, wall(), pose_cw(0.0)) is None
    fs.remember(0.0, wall(), pose_cw(0.0))
    assert fs.keyframe(None, 0.1, wall(), pose_cw(0.0)) is None       # 0.1 s is under half of either lag
    for k in range(1, 200):
        fs.remember(k / 30, wall(), pose_cw(0.0))
    assert len(fs._frames) <= 1.5 * 30 + 2                       # 1.5 x the longest lag at 30 Hz
    assert check(lags=()).enabled is False


def test_the_masks_keep_as_moving_only_what_the_evidence_does_not_contradict():
    shape = (480, 640)
    flagged = np.zeros(shape, np.float32)
    flagged[100:300, 100:300] = 0.9
    nothing_else = {"box_depth": MethodOutput(np.zeros(0), np.zeros(shape, np.float32))}   # no method flags it
    parts = MaskParts(nothing_else, [1.0], [], "noisy_or", shape, motion_region=flagged, prior=None)
    moving = np.zeros(shape, bool)
    moving[100:200, 100:300] = True                              # the upper half moved in
    known = np.ones(shape, bool)
    known[250:300] = False                                       # the bottom rows: no evidence
    region = np.zeros(shape, bool)
    region[400:450, 500:600] = True                              # moved as a whole, though nothing flagged it
    parts.free_space = Evidence(moving | region, known, region)
    mask, unmoved = compose_mask(parts)
    assert (mask[400:450, 500:600] >= 0.5).all() and (mask >= 0.5).sum() == 100 * 200 + 50 * 200 + 50 * 100
    assert (mask[100:200, 100:300] >= 0.5).all()
    assert (mask[200:250, 100:300] < 0.5).all() and unmoved[200:250, 100:300].all()
    assert (mask[250:300, 100:300] >= 0.5).all()
    assert unmoved.sum() == 50 * 200


def test_a_thin_band_of_apparent_motion_is_no_region():
    """A depth edge misplaced by a pose error or the rolling shutter looks moved along a band narrower than
    the min filter's window: it may stay in a flagged mask, but is never a moving region of its own (here
    16 px, 4 cells: wide enough to count as moving evidence; see the next test for a narrower one)."""
    fs = check(lags=(0.5,))
    fs.remember(0.0, wall((300, 0, 640, 480), 1.0), pose_cw(0.0))   # a near board's edge at x = 300 ...
    moved_edge = wall((272, 0, 640, 480), 1.0)                      # ... seen 28 px further left
    moving, known, region = fs.keyframe(None, 0.5, moved_edge, pose_cw(0.0))
    assert moving[:, 272:288].all() and not region.any()


def test_a_depth_edge_shifted_just_past_the_window_is_not_grown_into_moving_evidence():
    """A near board's edge seen 20 px off where the other frame saw it (a pose error, the colour/depth delay
    on a turn) lies 10 px beyond the min filter's reach: one or two cells of evidence along the edge. Grown
    over the board (24 px), such a line kept every false flag beside it as moving; it is no moving surface
    (a body part is wider than 3 cells), so the board there is known and unmoved, and a flag on it goes.
    The 28-px shift of the test above leaves a band 4 cells wide, which still counts."""
    fs = check(lags=(0.5,))
    fs.remember(0.0, wall((300, 0, 640, 480), 1.0), pose_cw(0.0))
    moving, known, region = fs.keyframe(None, 0.5, wall((280, 0, 640, 480), 1.0), pose_cw(0.0))
    assert not moving.any() and not region.any() and known[:, 280:330].all()
    shape = (480, 640)
    flagged = np.zeros(shape, np.float32)
    flagged[100:300, 270:330] = 0.9                               # a method's false flag over the edge
    nothing_else = {"box_depth": MethodOutput(np.zeros(0), np.zeros(shape, np.float32))}   # no method flags it
    parts = MaskParts(nothing_else, [1.0], [], "noisy_or", shape, motion_region=flagged, prior=None)
    parts.free_space = Evidence(moving, known, region)
    mask, unmoved = compose_mask(parts)
    assert not (mask >= 0.5).any() and unmoved[100:300, 270:330].all()


@pytest.mark.parametrize("lags", [[-0.5], [0.0]])
def test_config_rejects_lags_that_are_not_positive(lags):
    from slam.core.config import SlamConfig, apply_overrides
    from slam.core.config_base import ConfigError
    with pytest.raises(ConfigError, match=r"dynamic\.mask_free_space_lags_s"):
        apply_overrides(SlamConfig(), {"dynamic.mask_free_space_lags_s": lags})


def test_later_frames_grow_a_keyframes_evidence_and_hand_it_back_after_the_last_lag():
    """The masks can wait: a keyframe with no earlier frame (the run's start) is tested against the frames
    0.5 and 1 s after it as they come; the box that stood in front of the wall is gone from them. The evidence
    comes back once, after the last lag (each hand-over is a mask composed and written again)."""
    fs = check()
    box = (200, 100, 360, 400)
    assert fs.keyframe("kf", 0.0, wall(box), pose_cw(0.0)) is None
    fs.remember(0.0, wall(box), pose_cw(0.0))
    handed = []
    for k in range(1, 40):                                        # 30 Hz, 1.3 s; the box left at once
        handed.append((k, fs.remember(k / 30, wall(), pose_cw(0.0))))
    got = [(k, items) for k, items in handed if items]
    assert [k for k, _ in got] == [30]                            # the first frame 1 s later: the last lag
    (key, (moving, known, _)), = got[0][1]
    assert key == "kf" and moving[110:390, 210:350].all() and known.mean() > 0.95
    assert not moving[:, 420:].any()
    assert fs._pending == [] and fs.flush() == []                 # done after its last lag


def test_the_runs_end_hands_back_the_evidence_of_a_keyframe_whose_last_lag_never_came():
    """A keyframe 0.7 s before the run's end has had its 0.5 s frame, not its 1 s one: ``flush`` hands back
    what that frame added, once: the evidence a 1 s frame that tells nothing more would have handed back. A
    keyframe that no later frame has told anything yet is not handed back."""
    box = (200, 100, 360, 400)
    ended, whole = check(), check()
    for fs in (ended, whole):
        assert fs.keyframe("kf", 0.0, wall(box), pose_cw(0.0)) is None
        fs.remember(0.0, wall(box), pose_cw(0.0))
        assert not any(fs.remember(k / 30, wall(), pose_cw(0.0)) for k in range(1, 22))
    assert ended.keyframe("late", 22 / 30, wall(box), pose_cw(0.0)) is not None   # its earlier frames told
    flushed = ended.flush()
    assert [key for key, _ in flushed] == ["kf"] and ended.flush() == []
    handed = [whole.remember(k / 30, blind(), pose_cw(0.0)) for k in range(22, 40)]   # the 1 s frame sees nothing
    (key, evidence), = [item for items in handed for item in items]
    assert key == "kf"
    for got, expected in zip(flushed[0][1], evidence):
        np.testing.assert_array_equal(got, expected)
    moving, known, _ = evidence
    assert moving[110:390, 210:350].all() and known.mean() > 0.95


def test_the_moving_evidence_grows_over_the_moving_surface_not_onto_the_wall_beside_it():
    """The min filter leaves a blind band at the edges of a surface that moved in; the evidence grows over
    that band along the surface (depth within the test's margin), not onto the wall around it."""
    fs = check()
    fs.remember(0.0, wall(), pose_cw(0.0))
    fs.remember(0.5, wall(), pose_cw(0.0))
    box = (200, 100, 360, 400)
    moving, known, _ = fs.keyframe(None, 1.0, wall(box), pose_cw(0.0))
    assert moving[box[1]:box[3], box[0]:box[2]].all()               # the whole box, its edges included
    assert known[:, 370:400].all() and not moving[:, 368:].any()    # the wall right beside it: static
    assert not moving[:, :192].any() and not moving[:92].any()



def test_a_short_lag_finds_a_region_that_moved_in_where_the_long_lags_were_turned_away():
    """On a fast turn the frames 0.5 and 1 s back did not see the part of the view a person walked into;
    the frame 0.25 s back saw the wall there: the person is a moving region only with the short lag."""
    box = (200, 100, 360, 400)
    inner = (slice(box[1] + 10, box[3] - 10), slice(box[0] + 10, box[2] - 10))
    found = {}
    for region_lags in ((), (0.25,)):
        fs = check(region_lags=region_lags)
        fs.remember(0.0, blind(), pose_cw(0.0))
        fs.remember(0.5, blind(), pose_cw(0.0))
        fs.remember(0.75, wall(), pose_cw(0.0))
        found[region_lags] = fs.keyframe(None, 1.0, wall(box), pose_cw(0.0))
    assert found[()] is None                                     # nobody could tell
    moving, known, region = found[(0.25,)]
    assert region[inner].all() and not region.any(axis=0)[400:].any()
    assert not known.any() and not moving.any()                  # the long lags' evidence alone


def test_a_short_lag_never_shows_a_surface_unmoved():
    """0.25 s back a walker's body still covers much of where it is now (1.2 m/s: 0.3 m, half a body): the
    short lag may find a region that moved in, never say "was there", so it cannot take a walker out of the
    masks."""
    box = (200, 100, 360, 400)
    fs = check(region_lags=(0.25,))
    fs.remember(0.0, blind(), pose_cw(0.0))
    fs.remember(0.5, blind(), pose_cw(0.0))
    fs.remember(0.75, wall((240, 100, 400, 400)), pose_cw(0.0))   # the body 40 px to the right then
    moving, known, region = fs.keyframe(None, 1.0, wall(box), pose_cw(0.0))
    assert region[110:390, 200:224].all()                         # where the wall was seen: moved in
    assert not known.any()


def test_region_lags_need_the_free_space_test_and_a_long_one_is_remembered():
    assert check(lags=(), region_lags=(0.25,)).region_lags_s == ()
    fs = check(region_lags=(2.0,))                               # longer than the long lags: frames kept for it
    for k in range(0, 100):
        fs.remember(k / 30, wall(), pose_cw(0.0))
    assert fs._frames[0].timestamp <= 99 / 30 - 2.0


def test_a_fast_turn_makes_no_region_but_keeps_its_evidence():
    """At 3 rad/s a depth image taken 20 ms from its colour lies ~31 px off where the pose puts it, more than
    the regions' opening removes: such a frame's evidence still keeps flagged pixels, but makes no region."""
    box = (200, 100, 360, 400)
    inner = (slice(box[1] + 10, box[3] - 10), slice(box[0] + 10, box[2] - 10))
    found = {}
    for turn_rad in (0.0, 0.1):                                   # over the last 1/30 s: 0 or 3 rad/s
        fs = check()
        fs.remember(0.0, wall(), pose_cw(0.0))
        fs.remember(0.5, wall(), pose_cw(0.0))
        turned = pose_cw(0.0)
        turned[:3, :3] = cv2.Rodrigues(np.array([0.0, turn_rad, 0.0]))[0]
        fs.remember(1.0 - 1 / 30, blind(), turned)                # the frame just before: no depth, its pose only
        found[turn_rad] = fs.keyframe(None, 1.0, wall(box), pose_cw(0.0))
    assert found[0.0].region[inner].all()
    moving, known, region = found[0.1]
    assert moving[inner].all() and known[inner].all() and not region.any()


def test_a_far_frame_clears_what_the_near_ones_could_not_see_and_never_adds_motion():
    """On a turn the frames 0.5 and 1 s back saw nothing where the keyframe looks; the frame 2 s back did.
    Where it saw the same surface, the clear-only lag says "unmoved" (known, not moving); where it saw the
    wall behind today's box (a walker then 1 m away, or its own drifted pose), it says nothing at all."""
    box = (200, 100, 360, 400)
    inner = (slice(box[1] + 10, box[3] - 10), slice(box[0] + 10, box[2] - 10))
    wall_part = (slice(0, 480), slice(420, 600))
    found = {}
    for clear_lags in ((), (2.0,)):
        fs = check(clear_lags=clear_lags)
        fs.remember(0.0, wall(), pose_cw(0.0))                   # 2 s back: the wall, nothing in front
        fs.remember(1.0, blind(), pose_cw(0.0))
        fs.remember(1.5, blind(), pose_cw(0.0))
        found[clear_lags] = fs.keyframe(None, 2.0, wall(box), pose_cw(0.0))
    assert found[()] is None                                     # the near lags could not tell
    moving, known, region = found[(2.0,)]
    assert known[wall_part].all() and not moving.any() and not region.any()
    assert not known[inner].any()                                # the box: in front of the far wall, no say


def test_a_far_frame_never_takes_back_what_the_near_ones_saw():
    """Near frames show the box where it stands now (known, unmoved); a far frame that saw the wall there
    leaves that as it was, and where near frames saw the box move in, it stays moving."""
    box = (200, 100, 360, 400)
    inner = (slice(box[1] + 10, box[3] - 10), slice(box[0] + 10, box[2] - 10))
    fs = check(clear_lags=(2.0,))
    fs.remember(0.0, wall(), pose_cw(0.0))                       # 2 s back: no box
    fs.remember(1.0, wall(box), pose_cw(0.0))
    fs.remember(1.5, wall(box), pose_cw(0.0))
    moving, known, _ = fs.keyframe(None, 2.0, wall(box), pose_cw(0.0))
    assert known[inner].all() and not moving[inner].any()
    fs = check(clear_lags=(2.0,))
    fs.remember(0.0, wall(box), pose_cw(0.0))                    # 2 s back the box stood there already ...
    fs.remember(1.0, wall(), pose_cw(0.0))                       # ... then it was gone ...
    fs.remember(1.5, wall(), pose_cw(0.0))
    moving, known, _ = fs.keyframe(None, 2.0, wall(box), pose_cw(0.0))   # ... and is back: it moves
    assert moving[inner].all()


def test_a_later_far_frame_clears_a_keyframe_once_it_comes():
    """A keyframe that no frame within a second could tell about (the camera turned away and back) is cleared
    by the frame 2 s after it, handed back then; the frames kept cover the longest lag."""
    fs = check(clear_lags=(2.0,))
    assert fs.keyframe("kf", 0.0, wall(), pose_cw(0.0)) is None
    fs.remember(0.0, wall(), pose_cw(0.0))
    handed = []
    for k in range(1, 70):                                        # 30 Hz; blind until 2 s, then the wall
        handed.append((k, fs.remember(k / 30, blind() if k < 60 else wall(), pose_cw(0.0))))
    got = [k for k, items in handed if items]
    assert got == [60]
    (key, (moving, known, _)), = handed[59][1]
    assert key == "kf" and known.mean() > 0.95 and not moving.any()
    assert fs._pending == [] and fs._frames[0].timestamp <= 69 / 30 - 2.0
