"""Tests for the dataset readers: TUM layout (fake folders and the real shared sequences) and synthetic."""
from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.datasets import (DatasetError, DatasetWarning, SyntheticSequence, TumDataset, associate,
                           guess_camera, open_dataset, read_intrinsics, write_tum_layout)
from slam.datasets.tum import quat_to_matrix

from conftest import real_sequence as real


def make_tum(root: Path, t_rgb, t_depth, ext: str = ".png", present=None, assoc=None) -> Path:
    """A tiny TUM folder: 8x6 images, depth raw value 5000 * (i + 1) and a 0 in the corner.

    present: indices of listed frames whose files are written (default all). assoc: list of
    (rgb index, depth index) to write as associations.txt.
    """
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    for i, t in enumerate(t_rgb):
        name = f"rgb/{t:.6f}{ext if isinstance(ext, str) else ext[i]}"
        rgb_lines.append(f"{t:.6f} {name}")
        if present is None or i in present:
            cv2.imwrite(str(root / name), np.full((6, 8, 3), 10 * i + 5, np.uint8))
    for i, t in enumerate(t_depth):
        name = f"depth/{t:.6f}.png"
        depth_lines.append(f"{t:.6f} {name}")
        if present is None or i in present:
            raw = np.full((6, 8), 5000 * (i + 1), np.uint16)
            raw[0, 0] = 0
            cv2.imwrite(str(root / name), raw)
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if assoc is not None:
        rows = [f"{t_rgb[a]:.6f} {rgb_lines[a + 2].split()[1]} {t_depth[b]:.6f} depth/{t_depth[b]:.6f}.png"
                for a, b in assoc]
        (root / "associations.txt").write_text("\n".join(rows) + "\n")
    return root


# --- association -------------------------------------------------------------------------------------

def test_associate_nearest_within_max_dt_and_rejects_beyond():
    t_rgb = np.array([0.0, 1.0, 2.0, 3.0])
    t_depth = np.array([2.019, 0.005, 1.012, 0.995, 3.025])  # unsorted on purpose
    ia, ib = associate(t_rgb, t_depth, 0.02)
    assert ia.tolist() == [0, 1, 2]          # 3.0 has only a depth 25 ms away
    assert ib.tolist() == [1, 3, 0]          # 1.0 takes 0.995 (5 ms), not 1.012 (12 ms)


def test_associate_is_one_to_one():
    ia, ib = associate(np.array([1.0, 1.004]), np.array([1.003]), 0.02)
    assert ia.tolist() == [1] and ib.tolist() == [0]  # the closer rgb wins, the depth is used once


def test_associate_keeps_most_pairs_where_greedy_loses_one():
    # depth ~18 ms before colour, 32 ms period: greedy pairs rgb0 with depth1 (14 ms) and loses a frame
    t_rgb = np.array([0.018, 0.050])
    t_depth = np.array([0.000, 0.032])
    assert len(associate(t_rgb, t_depth, 0.02, greedy=True)[0]) == 1
    ia, ib = associate(t_rgb, t_depth, 0.02)
    assert ia.tolist() == [0, 1] and ib.tolist() == [0, 1]


# --- fake TUM folders ----------------------------------------------------------------------------------

def test_reads_png_frames_lazily_with_metric_depth(tmp_path):
    root = make_tum(tmp_path / "seq", [0.0, 0.033, 0.066], [0.004, 0.031, 0.07])
    ds = TumDataset(root)
    assert len(ds) == 3 and ds.name == "seq"
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.033, 0.066])
    frames = list(ds)
    assert [f.index for f in frames] == [0, 1, 2]
    f = frames[1]
    assert f.rgb.shape == (6, 8, 3) and f.rgb.dtype == np.uint8 and f.rgb[0, 0, 0] == 15
    assert f.depth.dtype == np.float32 and f.depth[1, 1] == 2.0 and f.depth[0, 0] == 0.0
    assert f.depth_path == root / "depth/0.031000.png"
    assert ds[2].depth[1, 1] == 3.0
    assert TumDataset(root, depth_scale=1000.0)[0].depth[1, 1] == 5.0


def test_associations_txt_is_preferred(tmp_path):
    root = make_tum(tmp_path / "seq", [0.0, 0.033], [0.001, 0.034], assoc=[(0, 1), (1, 0)])
    ds = TumDataset(root)
    assert ds.association_source == "associations.txt"
    assert [f.depth_path.name for f in ds] == ["0.034000.png", "0.001000.png"]


def test_jpeg_and_png_colour(tmp_path):
    root = make_tum(tmp_path / "seq", [0.0, 0.033], [0.0, 0.033], ext=[".jpg", ".png"])
    frames = list(TumDataset(root))
    assert [f.rgb_path.suffix for f in frames] == [".jpg", ".png"]
    assert all(f.rgb.shape == (6, 8, 3) for f in frames)
    assert abs(int(frames[0].rgb[3, 3, 0]) - 5) <= 3  # JPEG is lossy


def test_missing_files_one_warning_listing_names(tmp_path):
    ts = [i / 30 for i in range(15)]
    root = make_tum(tmp_path / "seq", ts, ts, present={0, 1, 2})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = TumDataset(root)
    msgs = [str(w.message) for w in caught if issubclass(w.category, DatasetWarning)]
    assert len(msgs) == 1
    msg = msgs[0]
    assert "12 of 15 listed rgb files" in msg and "12 of 15 listed depth files" in msg
    assert "rgb/0.100000.png" in msg and "and 14 more" in msg  # 10 names shown out of 24 missing
    assert len(ds) == 3 and len(ds.missing) == 24


def test_corrupt_files_are_skipped_with_warning(tmp_path):
    ts = [0.0, 0.033, 0.066, 0.1]
    root = make_tum(tmp_path / "seq", ts, ts)
    (root / "rgb/0.033000.png").write_bytes(b"not an image")
    cv2.imwrite(str(root / "depth/0.066000.png"), np.zeros((6, 8), np.uint8))  # 8-bit depth
    ds = TumDataset(root)
    with pytest.warns(DatasetWarning) as record:
        frames = list(ds)
    assert [f.index for f in frames] == [0, 3]
    text = " ".join(str(w.message) for w in record)
    assert "rgb/0.033000.png" in text and "depth/0.066000.png" in text and "16-bit" in text
    assert [p.name for p, _ in ds.skipped] == ["0.033000.png", "0.066000.png"]
    with pytest.raises(DatasetError):
        ds[1]


def test_missing_root_and_missing_lists_raise(tmp_path):
    with pytest.raises(DatasetError, match="does not exist") as err:
        TumDataset(tmp_path / "nope")
    assert str(tmp_path / "nope") in str(err.value) and "rgb.txt" in str(err.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no rgb.txt"):
        TumDataset(tmp_path / "empty")
    assert issubclass(DatasetError, ValueError)


def test_guess_camera():
    assert guess_camera("/x/rgbd_dataset_freiburg1_xyz") == "tum_fr1"
    assert guess_camera(Path("rgbd_dataset_freiburg2_desk/")) == "tum_fr2"
    assert guess_camera("rgbd_dataset_freiburg3_walking_xyz") == "tum_fr3"
    assert guess_camera("rgbd_bonn_crowd") == "bonn"
    assert guess_camera("/data/my_sequence") is None


def test_groundtruth_parsing(tmp_path):
    root = make_tum(tmp_path / "seq", [0.0], [0.0])
    assert TumDataset(root).groundtruth() is None
    s = np.sqrt(0.5)
    (root / "groundtruth.txt").write_text(
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
        f"1.5 1 2 3 0 0 {s} {s}\n1.6 0 0 0 0 0 0 1\n")
    ts, poses = TumDataset(root).groundtruth()
    np.testing.assert_allclose(ts, [1.5, 1.6])
    expected = np.eye(4)
    expected[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 degrees about z
    expected[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(poses[0], expected, atol=1e-12)
    np.testing.assert_allclose(poses[1], np.eye(4))
    q = np.random.default_rng(0).normal(size=(20, 4))
    np.testing.assert_allclose(quat_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)


# --- real sequences ---------------------------------------------------------------------------------

@pytest.mark.real
def test_real_desk_9frames_skips_listed_but_missing():
    root = real("rgbd_dataset_freiburg1_desk_9frames")
    with pytest.warns(DatasetWarning, match=r"604 of 613 listed rgb files") as record:
        ds = TumDataset(root)
    assert len(record) == 1 and "and 1180 more" in str(record[0].message)
    frames = list(ds)
    assert len(frames) == 9 and all(f.rgb.shape == (480, 640, 3) for f in frames)
    assert all(f.depth.dtype == np.float32 and 0.3 < np.median(f.depth[f.depth > 0]) < 5 for f in frames)
    assert guess_camera(root) == "tum_fr1"
    ts, poses = ds.groundtruth()
    assert ts[0] <= ds.timestamps[0] and ts[-1] >= ds.timestamps[-1] and poses.shape == (len(ts), 4, 4)


@pytest.mark.real
def test_real_xyz_first37_associates_from_lists():
    root = real("rgbd_dataset_freiburg1_xyz_first37")
    assert not (root / "associations.txt").exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error", DatasetWarning)  # every listed file is present
        ds = TumDataset(root)
    # 37 files of each, but one colour/depth pair is 20.2 ms apart: 36 pairs within 20 ms
    assert len(ds) == 36 and ds.unmatched_rgb == 1
    assert len(TumDataset(root, max_dt=0.021)) == 37
    assert np.all(np.abs(ds.timestamps - ds._t_depth) <= 0.02)
    frames = list(ds)
    assert len(frames) == 36 and frames[0].rgb.shape == (480, 640, 3)
    assert frames[0].timestamp == pytest.approx(1305031102.175304)


@pytest.mark.real
@pytest.mark.parametrize("name, n, camera", [("rgbd_dataset_freiburg1_rpy_first400", 400, "tum_fr1"),
                                             ("rgbd_bonn_crowd_first480", 480, "bonn")])
def test_real_sequences_with_associations(name, n, camera):
    root = real(name)
    ds = TumDataset(root)
    assert len(ds) == n and ds.association_source == "associations.txt" and guess_camera(root) == camera
    assert ds[0].rgb_path.suffix == ".jpg" and ds[0].depth.shape == (480, 640)
    assert ds.groundtruth()[1].shape[1:] == (4, 4)


# --- synthetic ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def seq() -> SyntheticSequence:
    return SyntheticSequence(n_frames=120)


def test_synthetic_is_deterministic_for_a_seed():
    kw = dict(n_frames=3, width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
    a, b = list(SyntheticSequence(seed=3, **kw)), list(SyntheticSequence(seed=3, **kw))
    c = next(iter(SyntheticSequence(seed=4, **kw)))
    for fa, fb in zip(a, b):
        assert np.array_equal(fa.rgb, fb.rgb) and np.array_equal(fa.depth, fb.depth)
    assert not np.array_equal(a[0].rgb, c.rgb)


def test_kept_frames_are_rendered_once_read_only_and_the_same_as_fresh_ones():
    kw = dict(n_frames=3, width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5, movers="people")
    kept, fresh = SyntheticSequence(seed=3, **kw), list(SyntheticSequence(seed=3, **kw))
    kept.keep_frames()
    first, second = list(kept), list(kept)
    assert all(a is b for a, b in zip(first, second))              # the second pass renders nothing
    for a, f in zip(first, fresh):
        assert np.array_equal(a.rgb, f.rgb) and np.array_equal(a.depth, f.depth)
        assert np.array_equal(a.dynamic_mask, f.dynamic_mask)
        with pytest.raises(ValueError, match="read-only"):
            a.depth[0, 0] = 1.0                                    # a pass cannot change what the next sees
    kept.keep_frames(False)
    assert next(iter(kept)) is not first[0]


def test_synthetic_depth_is_exact(seq):
    """Back-projected pixels of the room lie on its walls; a fronto-parallel wall has constant depth."""
    fx, fy, cx, cy = seq.intrinsics
    ts, poses = seq.groundtruth()
    depth, face = seq.raycast(poses[30], ts[30])
    v, u = np.nonzero(seq.face_primitive[face] == 0)
    z = depth[v, u].astype(np.float64)
    pts = poses[30] @ np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z, np.ones_like(z)])
    half, centre = seq.primitives[0].half, np.array([0.0, 0.0, 1.5])
    gap = np.min(np.abs(np.abs(pts[:3].T - centre) - half), axis=1)
    assert len(z) > 100_000 and gap.max() < 1e-4
    assert np.all(np.abs(pts[:3].T - centre) <= half + 1e-4)
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # looking along +x, y down = -z
    pose[:3, 3] = [0.0, 0.0, 1.5]
    _, depth = seq.render(pose)
    assert np.all(depth[200:280, 280:360] == np.float32(3.0))


def test_synthetic_orb_features_spread(seq):
    ts, poses = seq.groundtruth()
    orb = cv2.ORB_create(nfeatures=2000)
    for i in (0, 60, 119):
        rgb, _ = seq.render(poses[i], ts[i])
        kps = orb.detect(cv2.cvtColor(rgb, cv2.COLOR_BGR2GRAY), None)
        pts = np.array([k.pt for k in kps])
        grid, _, _ = np.histogram2d(pts[:, 1], pts[:, 0], bins=4, range=[[0, 480], [0, 640]])
        assert len(kps) >= 800 and grid.min() >= 1, (i, len(kps), grid)


def test_synthetic_motion_is_smooth_and_in_range(seq):
    ts, poses = seq.groundtruth()
    speed = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * seq.fps
    rel = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    rate = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=1)) * seq.fps
    assert 0.2 < speed.min() and speed.max() < 0.7 and rate.max() < 35
    for i in (0, 45, 90):
        depth, _ = seq.raycast(poses[i], ts[i])
        assert 0.5 < depth.min() and depth.max() < 5.0


def test_synthetic_box_culling_matches_full_trace(seq, monkeypatch):
    ts, poses = seq.groundtruth()
    culled = [seq.raycast(poses[i], ts[i]) for i in (10, 70)]
    monkeypatch.setattr(seq, "_window", lambda *a: (slice(None), slice(None)))
    for i, (depth, face) in zip((10, 70), culled):
        full_depth, full_face = seq.raycast(poses[i], ts[i])
        assert np.array_equal(depth, full_depth) and np.array_equal(face, full_face)


def test_synthetic_line_path(seq):
    line = SyntheticSequence(n_frames=60, path="line", width=160, height=120, fx=131.25, fy=131.25,
                             cx=79.5, cy=59.5)
    ts, poses = line.groundtruth()
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert np.allclose(poses[:, :3, :3], poses[0, :3, :3]) and 0.004 < step.min() and step.max() < 0.01
    with pytest.raises(ValueError, match="unknown camera path"):
        SyntheticSequence(path="spiral")


def test_write_tum_layout_reads_back(tmp_path):
    seq = SyntheticSequence(n_frames=3, width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)
    folder = write_tum_layout(seq, tmp_path / "synthetic_seq")
    ds = TumDataset(folder)
    assert len(ds) == 3 and guess_camera(folder) is None
    for orig, back in zip(seq, ds):
        assert np.array_equal(orig.rgb, back.rgb)
        assert np.abs(orig.depth - back.depth).max() <= 1 / 5000 + 1e-6
        assert back.timestamp == pytest.approx(orig.timestamp, abs=1e-6)
    ts, poses = ds.groundtruth()
    np.testing.assert_allclose(poses, seq.groundtruth()[1], atol=1e-6)
    cam = read_intrinsics(folder)
    assert cam == ds.intrinsics and (cam["fx"], cam["width"], cam["depth_scale"]) == (131.25, 160, 5000.0)


def test_open_dataset(tmp_path):
    assert isinstance(open_dataset("synthetic"), SyntheticSequence)
    root = make_tum(tmp_path / "seq", [0.0], [0.0])
    assert isinstance(open_dataset(root), TumDataset) and isinstance(open_dataset(str(root)), TumDataset)
