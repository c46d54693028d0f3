"""Moving objects in the synthetic generator: exact ground-truth dynamic masks and mover boxes, presets that
cross the view without hiding it, determinism, a still camera, and a static scene left untouched."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontend.dynamic.oracle import synthetic_oracle
from slam.datasets import RGBDFrame, SyntheticSequence
from slam.datasets.synthetic import MOVER_PRESETS, mover_kinds

SMALL = dict(width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
N_STATIC = 5  # the room and four furniture boxes come first in ``primitives``


@pytest.fixture(scope="module")
def crowd() -> SyntheticSequence:
    return SyntheticSequence(n_frames=90, movers="crowd", seed=1)


def mover_frames(seq: SyntheticSequence, count: int) -> list[int]:
    """Up to ``count`` frame indices, spread over the sequence, in which some mover is visible."""
    shown = [i for i in range(0, len(seq), 3) if seq.dynamic_mask(i).any()]
    return [shown[k] for k in np.linspace(0, len(shown) - 1, min(count, len(shown))).astype(int)]


def test_frame_dynamic_mask_is_optional():
    frame = RGBDFrame(index=0, timestamp=0.0, rgb=np.zeros((2, 2, 3), np.uint8), depth=np.zeros((2, 2), np.float32))
    assert frame.dynamic_mask is None


def test_mover_kinds_and_unknown_names():
    assert mover_kinds("none") == () and mover_kinds("people") == ("person",) * 3
    assert mover_kinds("crowd") == MOVER_PRESETS["people"] + MOVER_PRESETS["boxes"]
    assert mover_kinds(["boxes", "person", "drag"]) == ("box", "box", "person", "drag")
    with pytest.raises(ValueError, match="unknown movers"):
        SyntheticSequence(n_frames=2, movers="zombies", **SMALL)


def test_none_preset_is_the_old_scene_and_movers_leave_it_untouched():
    default = SyntheticSequence(n_frames=4, **SMALL)
    none = SyntheticSequence(n_frames=4, movers="none", **SMALL)
    assert none.name == default.name and len(none.primitives) == N_STATIC and none.movers == []
    for a, b in zip(default, none):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
        assert b.dynamic_mask.shape == b.depth.shape and not b.dynamic_mask.any()
    # with movers, the static scene renders exactly as before wherever no mover is in front of it
    crowd = SyntheticSequence(n_frames=4, movers="crowd", **SMALL)
    assert crowd.name.endswith("_crowd") and len(crowd.movers) == 5
    for i, (plain, busy) in enumerate(zip(default, crowd)):
        ts, pose = plain.timestamp, default.pose(plain.timestamp)
        static = crowd.raycast(pose, ts, primitives=range(N_STATIC))
        assert all(np.array_equal(x, y) for x, y in zip(static, default.raycast(pose, ts)))
        free = crowd.mover_ids(i) < 0
        assert busy.dynamic_mask.any() and np.array_equal(busy.dynamic_mask, ~free)
        assert np.array_equal(busy.rgb[free], plain.rgb[free]) and np.array_equal(busy.depth[free], plain.depth[free])


def test_mask_is_exactly_where_a_mover_is_the_nearest_surface(crowd):
    fx, fy, cx, cy = crowd.intrinsics
    parts = [p for m in crowd.movers for p in m.parts]
    none = SyntheticSequence(n_frames=1, movers="none", seed=1)
    for i in mover_frames(crowd, 3):
        t, pose = crowd.timestamps[i], crowd.pose(crowd.timestamps[i])
        frame = crowd.frame(i)
        static_depth, _ = crowd.raycast(pose, t, primitives=range(N_STATIC))
        mover_depth, mover_face = crowd.raycast(pose, t, primitives=parts)
        mask = frame.dynamic_mask
        assert np.array_equal(mask, (mover_depth > 0) & (mover_depth < static_depth))
        assert np.array_equal(frame.depth, np.where(mask, mover_depth, static_depth))
        # the background behind a mover is hidden: colour differs from the mover-free render there
        plain_rgb, _ = none.render(pose, t)
        assert np.array_equal(frame.rgb[~mask], plain_rgb[~mask])
        assert np.mean(np.any(frame.rgb[mask] != plain_rgb[mask], axis=1)) > 0.9
        # independent geometry: every mover pixel back-projects onto the face of the part it names
        v, u = np.nonzero(mask)
        z = frame.depth[v, u].astype(np.float64)
        world = pose @ np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z, np.ones_like(z)])
        face = mover_face[v, u]
        for p in np.unique(crowd.face_primitive[face]):
            box, on = crowd.primitives[p], crowd.face_primitive[face] == p
            local = np.linalg.inv(box.pose_at(t)) @ world[:, on]
            axis, sign = face[on] % 6 // 2, np.where(face[on] % 2 == 1, 1.0, -1.0)
            on_plane = local[axis, np.arange(on.sum())] - sign * box.half[axis]
            assert np.abs(on_plane).max() < 1e-4 * z[on].max() + 1e-5
            assert np.all(np.abs(local[:3]).T <= box.half + 1e-4 * z[on, None] + 1e-5)


def test_mover_boxes_are_tight_and_hold_every_pixel_of_their_mover(crowd):
    kinds = [m.kind for m in crowd.movers]
    assert kinds.count("person") == 3 and kinds.count("box") == 2
    for i in mover_frames(crowd, 6):
        ids = crowd.mover_ids(i)
        boxes = crowd.mover_boxes(i)
        present = [k for k in range(len(crowd.movers)) if (ids == k).any()]
        assert len(boxes) == len(present)
        for k, (x0, y0, x1, y1, kind) in zip(present, boxes):
            assert kind == crowd.movers[k].kind
            hit = ids == k
            inside = np.zeros_like(hit)
            inside[y0:y1, x0:x1] = True
            assert not (hit & ~inside).any()
            assert hit[y0].any() and hit[y1 - 1].any() and hit[:, x0].any() and hit[:, x1 - 1].any()
        big = crowd.mover_boxes(i, min_pixels=2000)
        assert set(big) <= set(boxes)
        assert len(big) == sum(np.count_nonzero(ids == k) >= 2000 for k in present)


def test_frames_rendered_ahead_on_a_reader_thread_are_those_rendered_one_by_one():
    """Iterating renders the next frames on a reader thread while the caller works; the caller may render
    other times of the same sequence meanwhile (the movers keep their last pose): no pixel may change."""
    seq, ref = (SyntheticSequence(n_frames=12, movers="people", seed=2, **SMALL) for _ in range(2))
    count = 0
    for i, frame in enumerate(seq):
        seq.render(seq.pose(0.5), 0.5)
        expected = ref.frame(i, cache=False)
        assert frame.index == i
        assert np.array_equal(frame.rgb, expected.rgb) and np.array_equal(frame.depth, expected.depth)
        assert np.array_equal(frame.dynamic_mask, expected.dynamic_mask)
        count += 1
    assert count == 12


def test_boxes_noted_while_rendering_are_a_fresh_casts_and_the_oracle_casts_nothing_more(monkeypatch):
    """The ground-truth detector reads each frame's boxes when the frame is detected: they are noted as the
    frame is rendered (every frame of a run is), so a run asks the ray caster for nothing more, and they
    are the boxes a separate cast of the same frame gives."""
    rendered, fresh = (SyntheticSequence(n_frames=20, movers="people", seed=1, **SMALL) for _ in range(2))
    for _ in rendered:
        pass
    oracle = synthetic_oracle(rendered, kinds={"person": 0}, margin_px=3, skip_frames=[5])

    def no_cast(index):
        raise AssertionError(f"frame {index} cast again")

    monkeypatch.setattr(rendered, "_cast_at", no_cast)
    seen = 0
    for i, t in enumerate(rendered.timestamps):
        boxes = rendered.mover_boxes(i)
        assert boxes == fresh.mover_boxes(i)
        w, h = rendered.width, rendered.height
        widened = [(max(x0 - 3, 0), max(y0 - 3, 0), min(x1 + 3, w), min(y1 + 3, h), 0) for x0, y0, x1, y1, _ in boxes]
        got = [(d.x0, d.y0, d.x1, d.y1, d.class_id) for d in oracle.detect(None, float(t))]
        assert got == ([] if i == 5 else widened)
        seen += bool(boxes)
    assert seen >= 10                                # frames with movers in view were compared
    empty = SyntheticSequence(n_frames=3, **SMALL)   # no movers: nothing to cast for
    monkeypatch.setattr(empty, "_cast_at", no_cast)
    assert empty.mover_boxes(1) == [] and synthetic_oracle(empty).detect(None, 0.0) == []


@pytest.mark.parametrize("movers, path", [("people", "orbit"), ("boxes", "line"), ("crowd", "orbit")])
def test_presets_cross_the_view_without_hiding_it(movers, path, crowd):
    seq = crowd if movers == "crowd" else SyntheticSequence(n_frames=90, movers=movers, path=path)
    sampled = range(0, len(seq), 2)
    cover, seen = [], np.zeros(len(seq.movers))
    for i in sampled:
        ids = seq.mover_ids(i)
        cover.append(np.mean(ids >= 0))
        seen += np.bincount(ids[ids >= 0], minlength=len(seq.movers)) >= 50
    cover = np.array(cover)
    assert np.mean(cover > 0) >= 0.6, cover  # some mover in most frames ...
    assert np.all(seen >= 0.15 * len(sampled)), seen  # ... and each one in a fair share of them
    assert np.mean(cover < 0.4) >= 0.9 and cover.max() < 0.6, cover.max()


def test_deterministic_for_a_seed():
    a, b = (SyntheticSequence(n_frames=6, movers="crowd", seed=2, **SMALL) for _ in range(2))
    for fa, fb in zip(a, b):
        assert np.array_equal(fa.rgb, fb.rgb) and np.array_equal(fa.depth, fb.depth)
        assert np.array_equal(fa.dynamic_mask, fb.dynamic_mask)
    assert a.mover_boxes(3) == b.mover_boxes(3)
    c = SyntheticSequence(n_frames=6, movers="person", seed=3, **SMALL)
    times = np.linspace(0, 0.2, 5)
    assert not np.allclose(a.movers[0].track(times)[0], c.movers[0].track(times)[0])


def test_still_camera_changes_only_under_movers():
    seq = SyntheticSequence(n_frames=61, path="still", movers="crowd", seed=4)
    assert np.array_equal(seq.pose(0.0), seq.pose(2.0))
    frames = [seq.frame(i, cache=False) for i in (0, 30, 60)]
    for a, b in zip(frames, frames[1:]):
        changed = np.any(a.rgb != b.rgb, axis=2) | (a.depth != b.depth)
        union = a.dynamic_mask | b.dynamic_mask
        assert changed.any() and not (changed & ~union).any()
        assert np.all((a.depth != b.depth)[a.dynamic_mask ^ b.dynamic_mask])  # a mover came or went there


def test_mover_motion_is_plausible(crowd):
    times = np.arange(len(crowd)) / crowd.fps
    cams = np.stack([crowd.pose(t) for t in times])
    for mover in crowd.movers:
        pos, rot, _ = mover.track(times)
        speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) * crowd.fps
        if mover.kind == "person":  # walking upright on the floor at ~1 m/s, feet on the ground
            assert np.all(pos[:, 2] == 0) and np.allclose(rot[:, 2], [0, 0, 1])
            assert 0.8 < speed.min() and speed.max() < 1.35
            for t in times[::10]:
                for k in (2, 3):  # legs: the bottom face centre touches the floor
                    leg = mover.boxes[k]
                    assert abs((leg.pose_at(t) @ [0, 0, -leg.half[2], 1])[2]) < 1e-9
            gap = np.linalg.norm(pos[:, :2] - cams[:, :2, 3], axis=1)
        else:  # floating and tumbling, clear of the floor
            assert 0.25 < speed.min() and speed.max() < 0.9
            rel = np.einsum("nji,njk->nik", rot[:-1], rot[1:])
            rate = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=1)) * crowd.fps
            assert 20 < rate.min() and rate.max() < 65
            assert pos[:, 2].min() - np.linalg.norm(mover.boxes[0].half) > 0
            gap = np.linalg.norm(pos - cams[:, :3, 3], axis=1)
        assert gap.min() > 0.55 + mover.radius  # planned for >= 0.6 m


def test_dragged_chair_is_still_then_moves():
    seq = SyntheticSequence(n_frames=60, movers="drag", **SMALL)
    person, chair = seq.movers
    assert (person.kind, chair.kind) == ("person", "chair")
    half = 30  # grabbed at the middle of the sequence
    poses = [chair.boxes[0].pose_at(t) for t in seq.timestamps]
    assert all(np.array_equal(p, poses[0]) for p in poses[:half])
    assert not np.allclose(poses[-1][:3, 3], poses[0][:3, 3], atol=0.3)
    assert not seq.moving(seq.timestamps[half - 1])[1] and seq.moving(seq.timestamps[half + 1])[1]
    chair_seen = [i for i in range(len(seq)) if (seq.mover_ids(i) == 1).any()]
    assert any(i < half for i in chair_seen) and any(i > half for i in chair_seen)
    for i in chair_seen:
        on_chair = seq.mover_ids(i) == 1
        assert np.array_equal(seq.dynamic_mask(i)[on_chair], np.full(on_chair.sum(), i > half))
        kinds = [b[4] for b in seq.mover_boxes(i)]
        moving_kinds = [b[4] for b in seq.mover_boxes(i, moving_only=True)]
        assert "chair" in kinds and ("chair" in moving_kinds) == (i > half)


def test_culling_matches_full_trace_with_movers(crowd, monkeypatch):
    frames = mover_frames(crowd, 2)
    culled = [crowd.raycast(crowd.pose(crowd.timestamps[i]), crowd.timestamps[i]) for i in frames]
    monkeypatch.setattr(crowd, "_window", lambda *a: (slice(None), slice(None)))
    for i, (depth, face) in zip(frames, culled):
        full_depth, full_face = crowd.raycast(crowd.pose(crowd.timestamps[i]), crowd.timestamps[i])
        assert np.array_equal(depth, full_depth) and np.array_equal(face, full_face)
