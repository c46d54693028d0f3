"""Maps (issue 5): the sparse landmark PLY, the dense TSDF map without movers' ghosts, ``dynslam export``.

A generated room with people walking (exact static geometry known) checks the dense mesh lies on the
true static surfaces and that the masks are what keeps the people out; the real Bonn ``crowd``
sequence checks the same on real data with the "ghost" measure: mesh vertices the camera sees
through in later frames (free space) are remnants of something that moved.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from backend.map_io import load_map
from frontend.dynamic.oracle import synthetic_oracle
from slam.run import pipeline as pipeline_module
from slam.cli import main
from slam.core.config import ConfigError, load_config
from slam.datasets import SyntheticSequence, TumDataset
from slam.run.dynamic_eval import synthetic_config
from slam.run.map_export import (ExportRequest, dynamic_colors, dynamic_evidence, ghost_fraction,
                                 load_keyframe_set)
from slam.run.trajectory import read_tum
from slam.run.tsdf import BYTES_PER_VOXEL, VolumeSizeWarning, fuse_keyframes, plan_grid

from conftest import ACCURACY_GROUP, report_figures


def o3d():
    """open3d, imported by the tests that read its files back: imported at collection it cost every pytest
    process ~2.6 s (open3d imports dash, whose ~200 files pytest then rewrites as a plugin's)."""
    import open3d
    return open3d


PEOPLE_FROM_FRAME = 230          # Bonn crowd: people walk into view from about here
MESH, CLOUD, SPARSE = "map_dense_mesh.ply", "map_dense_cloud.ply", "map_sparse.ply"


@pytest.fixture(autouse=True)
def _restore_warning_format(monkeypatch):
    """main() installs its own warnings.formatwarning; keep it from leaking into other tests."""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)


def export(*argv) -> int:
    return main(["export", *map(str, argv)])


def mesh_vertices(path: Path) -> np.ndarray:
    mesh = o3d().io.read_triangle_mesh(str(path))
    assert len(mesh.triangles) > 0, f"{path} has no triangles"
    return np.asarray(mesh.vertices)


def ghost_share(vertices: np.ndarray, frames, poses_by_time, camera) -> float:
    """Share of the checked vertices seen through (free space) over ``frames``."""
    ghosts = checked = 0
    for frame in frames:
        g, c = ghost_fraction(vertices, poses_by_time(frame.timestamp), frame.depth, camera)
        ghosts, checked = ghosts + g, checked + c
    assert checked > 1000, "too few vertices project onto valid depth to judge"
    return ghosts / checked


# ------------------------------------------------------------------------------- generated people
@pytest.fixture(scope="module")
def people_run(tmp_path_factory):
    """60 frames of the room with three people walking, dynamic_all with ground-truth person boxes."""
    seq = SyntheticSequence(n_frames=60, movers="people", seed=0)
    config = synthetic_config(seq, preset="dynamic_all")
    out = tmp_path_factory.mktemp("maps") / "people"
    # The generated people are not COCO-like: ground-truth boxes stand in for the detector.
    summary = pipeline_module.Pipeline(seq, config, out, detector=synthetic_oracle(seq)).run()
    assert summary.lost == 0
    assert export(out) == 0
    return seq, out, summary


@pytest.mark.slow
def test_run_leaves_export_inputs(people_run):
    seq, out, summary = people_run
    masks = sorted(p for p in (out / "masks").glob("*.png") if not p.stem.endswith("_still"))
    assert len(masks) == summary.keyframes
    assert json.loads((out / "summary.json").read_text())["dataset_path"] is None
    listed = [line.split() for line in (out / "keyframes" / "frames.txt").read_text().splitlines()
              if not line.startswith("#")]
    assert len(listed) == summary.keyframes
    index = int(listed[-1][0])
    depth = o3d().io.read_image(str(out / "keyframes" / "depth" / f"{index:06d}.png"))
    np.testing.assert_allclose(np.asarray(depth) / 1000.0, seq.frame(index).depth, atol=6e-4)
    assert (out / "map.npz").is_file() and (out / SPARSE).is_file()


@pytest.mark.slow
def test_sparse_ply_holds_the_good_landmarks_with_their_colours(people_run):
    _seq, out, _summary = people_run
    landmarks = load_map(out / "map.npz")[0].landmarks
    good = ~landmarks.bad
    cloud = o3d().io.read_point_cloud(str(out / SPARSE))
    np.testing.assert_allclose(np.asarray(cloud.points), landmarks.xyz[good], atol=1e-5)
    rgb = np.round(np.asarray(cloud.colors) * 255).astype(np.uint8)
    np.testing.assert_array_equal(rgb, landmarks.color[good][:, ::-1])
    assert len(np.unique(rgb, axis=0)) > 20, "landmark colours should come from the textured image"


@pytest.mark.slow
def test_sparse_ply_by_dynamic_evidence(people_run, tmp_path):
    _seq, out, _summary = people_run
    assert export(out, "--sparse", "--by-dynamic", "--out", tmp_path) == 0
    assert not (tmp_path / MESH).exists()
    landmarks = load_map(out / "map.npz")[0].landmarks
    good = ~landmarks.bad
    rgb = np.round(np.asarray(o3d().io.read_point_cloud(str(tmp_path / "map_sparse_dynamic.ply")).colors) * 255)
    np.testing.assert_array_equal(rgb.astype(np.uint8), dynamic_colors(dynamic_evidence(landmarks)[good]))
    np.testing.assert_array_equal(dynamic_colors(np.array([0.0, 1.0])), [[0, 0, 128], [128, 0, 0]])


def _aligned_vertices(seq, out, path: Path) -> np.ndarray:
    """Mesh vertices in the generator's world (the run's world is its first keyframe's camera)."""
    keyframes, _config = load_keyframe_set(ExportRequest(results_dir=out))
    gt = seq.groundtruth()[1]
    align = gt[int(keyframes.frame_index[0])] @ np.linalg.inv(keyframes.T_wc[0])
    return mesh_vertices(path) @ align[:3, :3].T + align[:3, 3]


def _static_surface_distance(seq, vertices: np.ndarray, frames) -> np.ndarray:
    """Per vertex, the smallest |depth - true static depth| over the ground-truth frames it projects into."""
    static = [i for i in range(len(seq.primitives)) if all(i not in m.parts for m in seq.movers)]
    fx, fy, cx, cy = seq.intrinsics
    gt = seq.groundtruth()[1]
    best = np.full(len(vertices), np.inf)
    for i in frames:
        depth, _faces = seq.raycast(gt[i], float(seq.timestamps[i]), primitives=static)
        T_cw = np.linalg.inv(gt[i])
        p = vertices @ T_cw[:3, :3].T + T_cw[:3, 3]
        z = np.where(p[:, 2] > 0.1, p[:, 2], np.nan)
        u, v = np.round(fx * p[:, 0] / z + cx), np.round(fy * p[:, 1] / z + cy)
        ok = (u >= 0) & (u < seq.width) & (v >= 0) & (v < seq.height)
        measured = np.zeros(len(p))
        measured[ok] = depth[v[ok].astype(int), u[ok].astype(int)]
        ok &= measured > 0
        best[ok] = np.minimum(best[ok], np.abs(z[ok] - measured[ok]))
    return best


@pytest.mark.slow
def test_dense_mesh_lies_on_the_static_surfaces(people_run, tmp_path):
    """Measured (printed at the end of the run): 95 % of the vertices within 5.7 mm of the true static
    surface and 99 % within 8.1 mm with masks; the gates are 15 % above (the regression margin of every
    accuracy gate). Without masks the people stay in the mesh: its 99th percentile is metres off, so
    'more than 0.3 m' (a person's depth, the smallest thing that can be left in) tells them apart."""
    seq, out, _summary = people_run
    frames = range(0, seq.n_frames, 3)
    masked = _static_surface_distance(seq, _aligned_vertices(seq, out, out / MESH), frames)
    p95, p99 = np.percentile(masked[np.isfinite(masked)], [95, 99])
    assert export(out, "--dense", "--no-masks", "--out", tmp_path) == 0
    unmasked = _static_surface_distance(seq, _aligned_vertices(seq, out, tmp_path / MESH), frames)
    unmasked_p99 = np.percentile(unmasked[np.isfinite(unmasked)], 99)
    report_figures("generated room with people, dense mesh vs the true static surfaces",
                   f"with masks: 95 % within {p95 * 1000:.1f} mm, 99 % within {p99 * 1000:.1f} mm; "
                   f"without masks: 99 % within {unmasked_p99:.2f} m")
    assert np.isfinite(masked).mean() > 0.98
    assert p95 < 0.0057 * 1.15 and p99 < 0.0081 * 1.15, (p95, p99)
    assert unmasked_p99 > 0.3, "the people should be in an unmasked mesh"
    cloud = o3d().io.read_point_cloud(str(out / CLOUD))
    assert len(cloud.points) > 1000 and cloud.has_colors()


@pytest.mark.slow
def test_export_from_a_map_file(people_run, tmp_path):
    _seq, out, _summary = people_run
    assert export("--map", out / "map.npz", "--out", tmp_path) == 0
    assert len(mesh_vertices(tmp_path / MESH)) > 1000
    assert (tmp_path / SPARSE).read_bytes() == (out / SPARSE).read_bytes()


@pytest.mark.slow
def test_voxel_cap_coarsens_the_grid_with_a_warning(people_run, tmp_path):
    _seq, out, _summary = people_run
    keyframes, config = load_keyframe_set(ExportRequest(results_dir=out, overrides={"export.max_voxels": 64_000}))
    with pytest.warns(VolumeSizeWarning, match="max_voxels"):
        result = fuse_keyframes(keyframes.subset([0, 1]), config.export)
    assert result.grid.voxels <= 64_000 and result.grid.voxel_size > config.export.voxel_size
    assert result.grid.truncation >= 2 * result.grid.voxel_size
    assert len(result.mesh.vertices) > 0


def test_plan_grid_bounds_memory_whatever_the_scene():
    with pytest.warns(VolumeSizeWarning):
        grid = plan_grid(np.array([-50.0, -50, -5]), np.array([50.0, 50, 5]), 0.02, 0.08, 8_000_000)
    assert grid.voxels <= 8_000_000 and grid.voxels * BYTES_PER_VOXEL < 400e6
    assert grid.length >= 100.0 and np.all(grid.origin <= -50.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        small = plan_grid(np.zeros(3), np.ones(3), 0.02, 0.08, 8_000_000)
    assert small.voxel_size == 0.02 and small.length >= 1.16


@pytest.mark.parametrize("key, value, message", [
    ("export.voxel_size", 0.0, "'export.voxel_size' must be > 0"),
    ("export.voxel_size", -0.01, "'export.voxel_size' must be > 0"),
    ("export.truncation", 0.01, "'export.truncation' (0.01) must be at least twice"),
    ("export.max_voxels", 0, "'export.max_voxels' must be >= 1"),
    ("export.mask_threshold", 1.5, "'export.mask_threshold' must be within [0, 1]"),
    ("export.mask_dilate_px", -1, "'export.mask_dilate_px' must be >= 0"),
    ("export.depth_edge_ratio", -0.1, "'export.depth_edge_ratio' must be >= 0"),
])
def test_bad_export_config_names_the_key(key, value, message):
    with pytest.raises(ConfigError) as info:
        load_config(overrides={key: value})
    assert message in str(info.value)


@pytest.mark.slow
def test_cli_errors_are_one_clear_line(people_run, tmp_path, capsys):
    _seq, out, _summary = people_run
    assert export(out, "--voxel", "-0.1") == 2
    assert "'export.voxel_size' must be > 0" in capsys.readouterr().err
    assert export(tmp_path) == 2
    assert "not a dynslam results folder (no config.yaml)" in capsys.readouterr().err
    for name in ("config.yaml", "keyframes.txt", "summary.json"):
        (tmp_path / name).write_bytes((out / name).read_bytes())
    assert export(tmp_path, "--dense") == 2
    assert "no keyframes/ folder and no dataset_path" in capsys.readouterr().err


# ------------------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def bonn_run(accuracy_runs):
    """The default (dynamic) run on Bonn crowd that the accuracy gates make (one per test session, the
    real detector), as ``dynslam run ../shared/data/rgbd_bonn_crowd_first480``."""
    result = accuracy_runs.get("bonn")["bonn"]
    assert result.returncode == 0, result.stderr
    out = result.results
    config = load_config(out / "config.yaml")
    dataset = TumDataset(json.loads((out / "summary.json").read_text())["dataset_path"],
                         depth_scale=config.camera.depth_scale)
    stamps, poses = read_tum(out / "trajectory.txt")

    def pose_at(t: float) -> np.ndarray:
        i = int(np.argmin(np.abs(stamps - t)))
        assert abs(stamps[i] - t) < 1e-3
        return poses[i]

    return out, config, dataset, pose_at


# Ghost shares measured on the gates' Bonn run (printed at the end of the test run); each gate is 15 %
# above its measurement, the regression margin of every accuracy gate. 2026-11-26: 0.0024 / 0.0025
# before the final trajectory smoother, 0.0028 / 0.0030 with it. The mesh is fused from the keyframes'
# adjusted poses while the check projects it with trajectory.txt's (smoothed) poses; a few mm between
# them shows on thin structures. The masks' effect is unchanged (among people 0.0030 vs 0.0063 without).
GHOSTS_WHOLE_RUN = 0.0028        # with masks, the whole run
GHOSTS_AMONG_PEOPLE = 0.0030     # with masks, keyframes from frame 230 on


@pytest.mark.real
@pytest.mark.slow
@pytest.mark.xdist_group(ACCURACY_GROUP)   # reads the accuracy runs' Bonn run
def test_bonn_dense_map_leaves_no_ghosts(bonn_run, tmp_path):
    """Over the whole run the TSDF carves most of the walking people away by itself (the room was seen
    empty first), so masks and no masks differ little here; what remains is thin structures (table
    legs, chair edges) a few pixels off."""
    out, config, dataset, pose_at = bonn_run
    frames = [dataset[i] for i in range(0, len(dataset), 20)]
    assert export(out, "--dense") == 0
    masked = ghost_share(mesh_vertices(out / MESH), frames, pose_at, config.camera)
    assert export(out, "--dense", "--no-masks", "--out", tmp_path) == 0
    unmasked = ghost_share(mesh_vertices(tmp_path / MESH), frames, pose_at, config.camera)
    report_figures("Bonn crowd dense map, ghost share (whole run)", f"{masked:.4f} with masks, {unmasked:.4f} without")
    assert masked <= GHOSTS_WHOLE_RUN * 1.15
    assert masked <= unmasked


@pytest.mark.real
@pytest.mark.slow
@pytest.mark.xdist_group(ACCURACY_GROUP)   # reads the accuracy runs' Bonn run
def test_bonn_map_built_among_people_needs_the_masks(bonn_run):
    """Keyframes from frame 230 on (people in view from the start: nothing carves them away). The
    masks must make a difference larger than the regression margins of both numbers together
    (unmasked > 1.15^2 x masked), so 'the masks keep people out' cannot flip by tolerated drift."""
    out, config, dataset, pose_at = bonn_run
    keyframes, config = load_keyframe_set(ExportRequest(results_dir=out))
    people_phase = keyframes.subset(np.flatnonzero(keyframes.frame_index >= PEOPLE_FROM_FRAME))
    frames = [dataset[i] for i in range(PEOPLE_FROM_FRAME, len(dataset), 20)]
    shares = {}
    for use_masks in (True, False):
        result = fuse_keyframes(people_phase, config.export, use_masks)
        shares[use_masks] = ghost_share(np.asarray(result.mesh.vertices), frames, pose_at, config.camera)
    report_figures(f"Bonn crowd dense map from frame {PEOPLE_FROM_FRAME}, ghost share",
                   f"{shares[True]:.4f} with masks, {shares[False]:.4f} without")
    assert shares[True] <= GHOSTS_AMONG_PEOPLE * 1.15
    assert shares[False] > 1.15 ** 2 * shares[True]


@pytest.mark.real
@pytest.mark.slow
@pytest.mark.xdist_group(ACCURACY_GROUP)   # reads the accuracy runs' Bonn run
def test_bonn_sparse_map_from_a_map_file_and_dataset(bonn_run, tmp_path):
    out, _config, dataset, _pose_at = bonn_run
    assert export("--map", out / "map.npz", "--dataset", dataset.root, "--sparse", "--out", tmp_path) == 0
    cloud = o3d().io.read_point_cloud(str(tmp_path / SPARSE))
    assert len(cloud.points) == int((~load_map(out / "map.npz")[0].landmarks.bad).sum()) > 500


def test_people_standing_still_are_read_as_dynamic_for_dense_maps(tmp_path):
    """``masks/<index>.png`` marks moving surfaces; ``<index>_still.png`` the people standing still, whom a
    dense map must leave out as well (docs/dynamic.md, standing people)."""
    import cv2

    from slam.run.tsdf import KeyframeSet

    moving = np.zeros((4, 6), np.uint8)
    moving[0, 0] = 255
    still = np.zeros((4, 6), np.uint8)
    still[2:, 3:] = 255
    cv2.imwrite(str(tmp_path / "000007.png"), moving)
    cv2.imwrite(str(tmp_path / "000007_still.png"), still)
    cv2.imwrite(str(tmp_path / "000009.png"), moving)
    keyframes = KeyframeSet(np.array([7, 9]), np.zeros(2), np.tile(np.eye(4), (2, 1, 1)), None, None, tmp_path)
    np.testing.assert_array_equal(keyframes.read_mask(0), np.maximum(moving, still))
    np.testing.assert_array_equal(keyframes.read_mask(1), moving)    # nobody stood still there
