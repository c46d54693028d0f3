"""Keyframe masks composed and revised once a person in them is found standing still
(frontend/dynamic/keyframe_masks.py); through a run and its mask files: tests/test_keyframe_mask_runs.py."""
from __future__ import annotations

import numpy as np

from frontend.dynamic.base import MethodOutput
from frontend.dynamic.keyframe_masks import KeyframeMaskLedger, MaskParts, compose_mask, still_region
from frontend.dynamic.region_motion import PersonTrack, RegionMotion

SHAPE = (48, 64)
FPS = 30.0
PERSON = (10, 8, 30, 40)         # x0, y0, x1, y1
WALKER = (40, 8, 60, 40)


def _box_mask(*boxes) -> np.ndarray:
    mask = np.zeros(SHAPE, np.float32)
    for x0, y0, x1, y1 in boxes:
        mask[y0:y1, x0:x1] = 1.0
    return mask


def _parts(person_mask: np.ndarray, motion_mask: np.ndarray) -> MaskParts:
    """A person-segmenting method (box_depth-like) and a motion-measuring one (cpr-like), fused by max."""
    outputs = {"box_depth": MethodOutput(np.zeros(0), person_mask), "cpr": MethodOutput(np.zeros(0), motion_mask)}
    return MaskParts(outputs, [1.0, 1.0], [1], "max", SHAPE, None, None)


def test_in_a_standing_persons_box_only_motion_evidence_counts_and_a_walker_keeps_everything():
    parts = _parts(_box_mask(PERSON, WALKER), np.zeros(SHAPE, np.float32))
    parts.still_region = still_region(SHAPE, [PERSON, WALKER], [True, False])
    mask, still_people = compose_mask(parts)
    assert not (mask[8:40, 10:30] >= 0.5).any()                    # the standing person left the mask
    assert (mask[8:40, 40:60] >= 0.5).all()                        # the walker did not
    assert still_people[8:40, 10:30].all() and still_people.sum() == 20 * 32   # ... and went to _still
    assert still_region(SHAPE, [PERSON], [False]) is None
    # A walker overlapping a standing person keeps the overlap.
    overlap = still_region(SHAPE, [PERSON, (20, 8, 40, 40)], [True, False])
    assert overlap[8:40, 10:20].all() and not overlap[8:40, 20:40].any()



def test_the_free_space_regions_leave_a_person_shown_standing_and_still_raise_a_walker():
    """A walker who has just stopped stands where the frames a quarter to a whole second back saw through:
    the free-space test calls that region moved, while the standing rule has seen them still over its
    window. Over the standing person the region raises nothing; over the walker it does."""
    parts = _parts(_box_mask(PERSON, WALKER), np.zeros(SHAPE, np.float32))
    parts.still_region = still_region(SHAPE, [PERSON, WALKER], [True, False])
    seen_through = _box_mask(PERSON, WALKER) > 0
    parts.free_space = (seen_through, seen_through, seen_through)     # moving, known, moved region
    mask, still_people = compose_mask(parts)
    assert not (mask[8:40, 10:30] >= 0.5).any() and still_people[8:40, 10:30].all()
    assert (mask[8:40, 40:60] >= 0.5).all()
    parts.still_region = None                                          # nobody shown standing: both raised
    assert (compose_mask(parts)[0][seen_through] >= 0.5).all()

def test_a_motion_methods_detections_only_output_is_no_evidence_of_motion_in_the_masks():
    """flow_epipolar on its first frame (or without a fundamental matrix) flags every person box from the
    detections alone; with a segmenting method at 0.45 the noisy-OR would pass 0.5 on a person who may
    stand. Measured, the same output counts."""
    segment = _box_mask(PERSON)                                # depth_sdf's segment, trusted 0.45
    for measured, flagged in ((False, False), (True, True)):
        outputs = {"depth_sdf": MethodOutput(np.zeros(0), segment),
                   "flow_epipolar": MethodOutput(np.zeros(0), _box_mask(PERSON), motion_measured=measured)}
        parts = MaskParts(outputs, [0.45, 0.45], [1], "noisy_or", SHAPE, None, None)
        mask, _ = compose_mask(parts)
        # depth_sdf's segment counts either way: 0.45 alone (under the bar), 0.70 with a measured flow_epipolar
        assert np.allclose(mask[8:40, 10:30], 1 - 0.55 ** 2 if measured else 0.45)
        assert (mask[8:40, 10:30] >= 0.5).all() == flagged
        assert (parts.motion is None) != measured                # the motion methods' own mask too


def _people_over(frames: int, motion: RegionMotion, ledger: KeyframeMaskLedger, keyframe_every: int = 5):
    """One person standing 2 m in front of a still camera; a keyframe every ``keyframe_every`` frames.
    Returns the revisions per frame and the still flag per frame."""
    T = np.eye(4)
    revisions, flags = [], []
    for i in range(frames):
        still = motion.classify([np.array([0.0, 0.0, 2.0])], T, i / FPS)
        tracks = motion.commit(T)
        keyframe = (i, _parts(_box_mask(PERSON), np.zeros(SHAPE, np.float32)), [PERSON]) \
            if i % keyframe_every == 0 else None
        revisions.append(ledger.advance(i / FPS, tracks, still, keyframe))
        flags.append(bool(still[0]))
    return revisions, flags


def test_the_keyframes_of_the_first_window_are_revised_when_the_person_is_found_standing():
    motion, ledger = RegionMotion(0.5, 0.15), KeyframeMaskLedger(0.5)
    revisions, flags = _people_over(30, motion, ledger)
    first_still = flags.index(True)
    assert first_still == 15                                        # followed for 0.5 s at 30 fps
    assert not any(revisions[:first_still])
    revised = revisions[first_still]
    assert [r.frame_index for r in revised] == [0, 5, 10]           # every keyframe of the window [0, 0.5 s]
    for r in revised:
        assert not (r.mask >= 0.5).any() and r.still_people.sum() == 20 * 32
    # Each keyframe is revised once; keyframes made while the person is known to stand are never pending.
    assert not any(revisions[first_still + 1:])


def test_a_keyframe_older_than_the_tracks_span_and_another_persons_track_are_not_revised():
    ledger = KeyframeMaskLedger(0.5)
    other, person = PersonTrack([0.4], still_since=0.4), PersonTrack([0.0])
    parts = _parts(_box_mask(PERSON), np.zeros(SHAPE, np.float32))
    assert ledger.advance(0.0, [person], np.array([False]), (0, parts, [PERSON])) == []
    assert ledger.advance(0.4, [other], np.array([True]), None) == []          # not the keyframe's person
    person.times[:] = [0.1, 0.6]                  # the span kept at 0.6 s starts after keyframe 0
    person.still_since = 0.1
    assert ledger.advance(0.6, [person], np.array([True]), None) == []         # keyframe 0 is final
    ledger.reset()
    person.times[:], person.still_since = [0.0], None
    assert ledger.advance(0.0, [person], np.array([False]), (3, parts, [PERSON])) == []
    person.times[:], person.still_since = [0.0, 0.5], 0.0
    (revised,) = ledger.advance(0.5, [person], np.array([True]), None)
    assert revised.frame_index == 3 and revised.timestamp == 0.0


def test_a_keyframe_at_the_start_of_the_tracks_span_is_revised_though_a_window_and_a_bit_old():
    """A track keeps the newest entry at least a window old: a stillness found now covers a keyframe
    0.500012 s back (composited two_walk, keyframe 39), which a cut at exactly the window dropped."""
    ledger = KeyframeMaskLedger(0.5)
    person = PersonTrack([0.0])
    parts = _parts(_box_mask(PERSON), np.zeros(SHAPE, np.float32))
    assert ledger.advance(0.0, [person], np.array([False]), (39, parts, [PERSON])) == []
    person.times[:], person.still_since = [0.0, 0.25, 0.500012], 0.0
    (revised,) = ledger.advance(0.500012, [person], np.array([True]), None)
    assert revised.frame_index == 39
    # Off (still_window_s = 0): nothing is kept, nothing revised.
    off = KeyframeMaskLedger(0.0)
    assert off.advance(0.0, [person], np.array([False]), (0, parts, [PERSON])) == []
    assert off.advance(0.1, [person], np.array([True]), None) == []


def test_a_stillness_revises_only_the_keyframes_of_the_span_it_was_shown_over():
    """A track keeps a surface window (1 s) for the surface's test; the centre's test shows the person still
    over the last 0.5 s only, so a keyframe 0.8 s back, when they may still have walked, stays as it was,
    while one 0.3 s back is revised."""
    ledger = KeyframeMaskLedger(0.5)
    person = PersonTrack([0.0])
    parts = _parts(_box_mask(PERSON), np.zeros(SHAPE, np.float32))
    assert ledger.advance(0.2, [person], np.array([False]), (6, parts, [PERSON])) == []
    assert ledger.advance(0.7, [person], np.array([False]), (21, parts, [PERSON])) == []
    person.times[:], person.still_since = [0.0, 0.2, 0.5, 0.7, 1.0], 0.5
    (revised,) = ledger.advance(1.0, [person], np.array([True]), None)
    assert revised.frame_index == 21
    person.still_since = 0.0                     # now shown still over the whole span: keyframe 6 as well
    (revised,) = ledger.advance(1.03, [person], np.array([True]), None)
    assert revised.frame_index == 6


def _final_masks(motion: RegionMotion, ledger: KeyframeMaskLedger, centre_at, frames: int) -> dict[int, np.ndarray]:
    """A still camera, one person at ``centre_at(i)`` (camera frame) on frame i, a keyframe every 5 frames
    whose motion-measuring method flags the whole person; each keyframe's mask after every revision,
    with the run's end."""
    T, masks = np.eye(4), {}
    for i in range(frames):
        still = motion.classify([centre_at(i)], T, i / FPS)
        tracks = motion.commit(T)
        keyframe = None
        if i % 5 == 0:
            parts = _parts(_box_mask(PERSON), _box_mask(PERSON))
            parts.still_region = still_region(SHAPE, [PERSON], still)
            masks[i] = compose_mask(parts)[0]
            keyframe = (i, parts, [PERSON])
        for r in ledger.advance(i / FPS, tracks, still, keyframe):
            masks[r.frame_index] = r.mask
    last = frames - 1
    for r in ledger.advance(last / FPS, tracks, still, None, final=True):
        masks[r.frame_index] = r.mask
    return masks


def test_a_person_shown_still_a_window_past_a_keyframe_leaves_its_motion_flags_and_a_starting_walk_keeps_them():
    """In a standing person's box only motion evidence counts, and it may be the first steps of a walk,
    which the centre's test sees only once the person is past the bound. A keyframe the person stayed still
    a whole window past has false alarms there, and they leave its mask; one made within a window before
    the walk keeps them."""
    walk_from = 45                                  # the person walks sideways at 1 m/s after frame 45

    def centre_at(i):
        return np.array([max(0, i - walk_from) / FPS, 0.0, 2.0])
    masks = _final_masks(RegionMotion(0.5, 0.15), KeyframeMaskLedger(0.5), centre_at, 80)
    person = (slice(PERSON[1], PERSON[3]), slice(PERSON[0], PERSON[2]))
    settled = [i for i, m in sorted(masks.items()) if not (m[person] >= 0.5).any()]
    assert settled == [0, 5, 10, 15, 20, 25, 30]    # still until 1.5 s: keyframes up to 1.0 s
    # Standing to the end: the run's end settles the keyframes of its last window as well.
    masks = _final_masks(RegionMotion(0.5, 0.15), KeyframeMaskLedger(0.5), lambda i: np.array([0.0, 0.0, 2.0]), 40)
    assert all(not (m[person] >= 0.5).any() for m in masks.values())


def test_the_desk_and_wall_in_a_persons_box_leave_the_mask_and_the_person_stays():
    """box_depth's fill runs on over a desk that touches a person in depth (composited fr1/rpy, people behind
    the desk: most false pixels of the masks lay in a box, far in depth from the person): what lies more than
    a body's reach from the box's person layer keeps only the motion-measuring methods' evidence."""
    from frontend.dynamic.keyframe_masks import off_body_region

    shape = (480, 640)
    depth = np.full(shape, 3.5, np.float32)                 # the wall
    depth[100:400, 270:360] = 2.0                           # the person
    depth[330:480, :] = np.linspace(1.25, 0.8, 150, dtype=np.float32)[:, None]   # a desk in front of their legs
    box = (262, 92, 368, 408)
    walker = (340, 150, 410, 330)                           # a walker nearer, partly in the person's box
    depth[150:330, 340:410] = np.linspace(1.1, 1.3, 70, dtype=np.float32)[None, :]
    x0, y0, x1, y1 = box
    leaky = np.zeros(shape, np.float32)
    leaky[y0:y1, x0:x1] = 1.0                               # a segmentation that filled the whole box
    leaky[150:330, 340:410] = 1.0
    motion = np.zeros(shape, np.float32)
    motion[350:380, 280:300] = 1.0                          # a motion method saw the desk move there
    outputs = {"box_depth": MethodOutput(np.zeros(0), leaky), "cpr": MethodOutput(np.zeros(0), motion)}
    parts = MaskParts(outputs, [1.0, 1.0], [1], "max", shape, None, None, [box, walker], depth)
    mask, still = compose_mask(parts)
    person = depth == 2.0
    walker_px = np.zeros(shape, bool)
    walker_px[150:330, 340:410] = True
    assert (mask[person] >= 0.5).all() and (mask[walker_px] >= 0.5).all()      # both people stay
    desk_or_wall = np.zeros(shape, bool)
    desk_or_wall[y0:y1, x0:x1] = ~person[y0:y1, x0:x1] & ~walker_px[y0:y1, x0:x1]
    desk_or_wall[350:380, 280:300] = False                  # ... except where motion was seen
    assert not (mask[desk_or_wall] >= 0.5).any() and still[desk_or_wall].all()
    assert (mask[350:380, 280:300] >= 0.5).all()
    # A box without enough depth for a layer, or no box: nothing is cut.
    assert off_body_region([box], np.zeros(shape, np.float32)) is None and off_body_region([], depth) is None


def test_a_held_box_the_person_left_for_a_box_inside_it_leaves_the_mask():
    """A person half hidden as the camera turns gets a box inside their last one, too small an overlap for
    the detector memory to match: the last box is held beside the new one, over nobody (composited fr1/rpy
    two_walk: 27 k of the masks' false pixels). Its rest keeps only motion evidence; a box held because the
    detector missed the person (nothing fresh inside it) keeps everything."""
    from frontend.dynamic.box_memory import BoxMemory
    from frontend.dynamic.keyframe_masks import vacated_region

    memory = BoxMemory(5, {0}, width=SHAPE[1], height=SHAPE[0])
    memory.update([_detection(2, 2, 40, 46)])
    now = memory.update([_detection(20, 10, 34, 40)])        # IoU 0.25 with the last box: not matched
    assert len(now) == 2 and len(memory.carried) == 1
    held = [(int(d.x0), int(d.y0), int(d.x1), int(d.y1)) for d in memory.carried]
    region = vacated_region(SHAPE, [(20, 10, 34, 40)], held)
    assert region[2:46, 2:20].all() and not region[10:40, 20:34].any()
    segmented = _box_mask((2, 2, 40, 46))                    # a fill over the whole held box
    parts = _parts(segmented, np.zeros(SHAPE, np.float32))
    parts.vacated = region
    mask, still = compose_mask(parts)
    assert (mask[10:40, 20:34] >= 0.5).all() and not (mask[region] >= 0.5).any() and still[region].all()
    # Missed by the detector: nothing fresh inside the held box, nothing vacated.
    assert vacated_region(SHAPE, [], held) is None and vacated_region(SHAPE, [(50, 2, 60, 20)], held) is None


def _detection(x0, y0, x1, y1):
    from frontend.dynamic.base import Detection
    return Detection(float(x0), float(y0), float(x1), float(y1), 0, 0.9)
