"""People composited into a real sequence (slam/datasets/composite.py): the real frames stay untouched
outside the people, the people are where their depth says, and the poses are the motion capture's."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import XYZ, real_sequence
from slam.datasets import DatasetError, TumDataset, load_groundtruth
from slam.datasets.composite import COMPOSITE_SCENES, CompositeScene

FR1 = (517.306408, 516.469215, 318.643040, 255.313989)


@pytest.fixture(scope="module")
def xyz():
    return real_sequence(XYZ)


FRAMES = 12      # fr1/xyz's first 12 frames (0.4 s): the scripts put the people mid-way, in view throughout


@pytest.fixture(scope="module")
def three_close(xyz):
    return CompositeScene("three_close", xyz, FR1, n_frames=FRAMES)


def test_people_replace_the_real_pixels_only_where_they_are_in_front(xyz, three_close):
    base = TumDataset(xyz)
    seen = 0
    for i in range(len(three_close)):
        real, frame = base[i], three_close.frame(i)
        person = three_close.mover_ids(i) >= 0
        seen += int(person.sum())
        # Outside the people: the real frame, bit for bit.
        np.testing.assert_array_equal(frame.rgb[~person], real.rgb[~person])
        np.testing.assert_array_equal(frame.depth[~person], real.depth[~person])
        # On them: nearer than the real surface there, or where the sensor had no depth.
        d, r = frame.depth[person], real.depth[person]
        assert np.all(d > 0) and np.all((r <= 0) | (d < r))
        # Walking people are the moving surface: the exact mask is the people's pixels.
        np.testing.assert_array_equal(frame.dynamic_mask, person)
    # The three walk at 1.1-1.9 m through the middle of the frames: in view on every frame,
    # each ~0.5 m wide at under 2 m (> 1/8 of the image's width), the desk hiding their lower half.
    assert (three_close.coverage > 0.1).all()
    assert seen > 0


def test_a_person_behind_a_real_surface_is_hidden_by_it(xyz, three_close):
    """Cast alone (no real scene), the people cover more pixels than composited: the desk and monitor of
    fr1/xyz are nearer than parts of them."""
    hidden = 0
    for i in np.flatnonzero(three_close.coverage > 0):
        time = float(three_close.timestamps[i])
        _, alone = three_close.render(three_close.pose(time), time)      # the people alone, no real scene
        hidden += int(np.sum(alone > 0)) - int(np.sum(three_close.mover_ids(i) >= 0))
    assert hidden > 0


def test_poses_are_the_motion_capture_interpolated_to_each_frame(xyz, three_close):
    gt_t, gt_T = load_groundtruth(xyz / "groundtruth.txt")
    base = TumDataset(xyz)
    stamps, poses = three_close.groundtruth()
    np.testing.assert_allclose(stamps, base.timestamps[:FRAMES] - base.timestamps[0])
    for t, pose in zip(base.timestamps, poses):
        k = int(np.searchsorted(gt_t, t))          # the capture samples either side of the frame
        a, b = gt_T[k - 1], gt_T[k]
        w = (t - gt_t[k - 1]) / (gt_t[k] - gt_t[k - 1])
        np.testing.assert_allclose(pose[:3, 3], (1 - w) * a[:3, 3] + w * b[:3, 3], atol=1e-9)
        # The rotation lies between the two samples' (slerp): within their angle of each.
        gap = np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1))
        for s in (a, b):
            assert np.arccos(np.clip((np.trace(s[:3, :3].T @ pose[:3, :3]) - 1) / 2, -1, 1)) <= gap + 1e-9


def test_real_holes_are_where_the_real_frame_has_no_depth_and_people_are_drawn_there(xyz, three_close):
    base = TumDataset(xyz)
    drawn = 0
    for i in range(len(three_close)):
        holes = three_close.real_holes(i)
        np.testing.assert_array_equal(holes, ~(base[i].depth > 0))
        drawn += int(np.count_nonzero(holes & three_close.dynamic_mask(i)))
    assert drawn > 0      # fr1's holes around the desk: the people are drawn into them


def test_the_clean_scene_is_the_real_sequence(xyz):
    clean, base = CompositeScene("none", xyz, FR1, n_frames=FRAMES), TumDataset(xyz)
    assert not clean.movers and clean.coverage.max() == 0
    for i in (0, FRAMES - 1):
        frame, real = clean.frame(i), base[i]
        np.testing.assert_array_equal(frame.rgb, real.rgb)
        np.testing.assert_array_equal(frame.depth, real.depth)
        assert not frame.dynamic_mask.any()


def test_composites_are_deterministic(xyz):
    a, b = CompositeScene("walk_stand", xyz, FR1, n_frames=FRAMES), CompositeScene("walk_stand", xyz, FR1, n_frames=FRAMES)
    for i in (2, 9):
        np.testing.assert_array_equal(a.frame(i).rgb, b.frame(i).rgb)


def test_the_standing_person_of_walk_stand_is_in_view_but_never_moving(xyz):
    scene = CompositeScene("walk_stand", xyz, FR1, n_frames=FRAMES)
    standing = 0
    for i in range(len(scene)):
        ids, moving = scene.mover_ids(i), scene.dynamic_mask(i)
        assert not np.any(moving & (ids == 0))       # mover 0 stands the whole sequence
        standing += int(np.sum(ids == 0))
    assert standing > 0


def test_bad_inputs_say_what_is_wrong(xyz, tmp_path):
    with pytest.raises(ValueError, match="unknown composite scene 'stampede'.*two_walk"):
        CompositeScene("stampede", xyz, FR1)
    for name in ("rgb", "depth"):
        (tmp_path / name).mkdir()
    (tmp_path / "rgb.txt").write_text("")
    (tmp_path / "depth.txt").write_text("")
    with pytest.raises(DatasetError):
        CompositeScene("two_walk", tmp_path, FR1)
    assert set(COMPOSITE_SCENES) >= {"none", "two_walk", "walk_stand", "three_close"}


# --- SLAM on people composited into fr1/rpy (slow) -----------------------------------------------------

RPY = "rgbd_dataset_freiburg1_rpy_first400"
COMPOSITE_FRAMES = 150     # the scripts time the people around the middle: frames ~40-110 here
MAX_ATE_RATIO = 1.5        # the bar for generated hard scenes, against the same frames without people

# two_walk at these 150 frames is a known failure, not run here (~25 s): it drifted to 20 cm at frame 54 while the
# box prior kept the person boxes that span most of the rolled view out of the map through fr1/rpy's fastest turn
# (docs/dynamic.md, "People composited into real sequences"). The prior off the body in boxes their person fills
# sparsely (dynamic.box_prior_on_body, on since 2026-12-01) fixes seeds 0 and 1 but not seed 2 (231 mm), so it is
# not asserted (`python tools/hard_scenes.py --composite <rpy folder> --frames 150 two_walk --repeats 3`).


@pytest.fixture(scope="module")
def rpy_composite_runs():
    from slam.run.dynamic_eval import evaluate_synthetic, scene_detector
    from slam.run.demo import DEMO_ORACLE_MARGIN_PX
    from slam.run.run_config import resolve_run_config

    folder = real_sequence(RPY)
    config = resolve_run_config(folder, ["dynamic_all"], {})
    camera = config.camera
    runs = {}

    def run(name: str):
        if name not in runs:
            scene = CompositeScene(name, folder, (camera.fx, camera.fy, camera.cx, camera.cy),
                                   n_frames=COMPOSITE_FRAMES)
            runs[name] = evaluate_synthetic(scene, resolve_run_config(folder, ["dynamic_all"], {}),
                                            detector=scene_detector(scene, DEMO_ORACLE_MARGIN_PX),
                                            split=("real depth missing", scene.real_holes))
        return runs[name]
    return run


@pytest.mark.slow
def test_slam_with_three_people_composited_into_a_real_sequence_stays_near_it(rpy_composite_runs):
    clean, result = rpy_composite_runs("none"), rpy_composite_runs("three_close")
    assert not clean.lost_frames
    assert result.ate_rmse <= MAX_ATE_RATIO * clean.ate_rmse, \
        f"ATE {result.ate_rmse:.4f} m vs {clean.ate_rmse:.4f} m on the same frames without people"
    # The keyframe masks scored apart where the real frames had no depth and elsewhere: the two parts make the whole.
    whole, holes = result.keyframe_masks["fused"], result.keyframe_masks["fused, real depth missing"]
    rest = result.keyframe_masks["fused, not real depth missing"]
    assert holes.dynamic > 0 and rest.dynamic > 0
    for count in ("true_positive", "flagged", "dynamic"):
        assert getattr(holes, count) + getattr(rest, count) == getattr(whole, count)


@pytest.mark.slow
def test_the_border_walker_is_in_view_while_walking():
    """fr1/rpy looks down at the desk at mid-sequence, where the border's line of sight projected on the
    floor leaves the view: placed then, the walker was out of view for the whole walk (moving pixels on 9 of
    its 121 frames, 76 at most). Placed when that line is nearest to level, they are in view over 0.5 % of
    the image on 90 of them (2026-12-01); at least half is the bar of a scene about a person cut by the
    border while walking."""
    scene = CompositeScene("border", real_sequence(RPY), FR1)
    walking = [i for i in range(len(scene)) if scene.moving(float(scene.timestamps[i])).any()]
    in_view = [i for i in walking if scene.coverage[i] > 0.005]
    assert len(walking) > 60 and len(in_view) >= len(walking) / 2, (len(in_view), len(walking))
