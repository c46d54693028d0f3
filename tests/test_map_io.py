"""Map save/load (backend.map_io) and localisation-only runs against a saved map."""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from backend.map_io import (MapCameraError, MapFormatError, camera_info_from_config, check_camera_compatible,
                            load_map, save_map)
from slam.cli import main, resolve_run_config
from slam.core.config import load_config
from slam.datasets import SyntheticSequence, TumDataset
from slam.run.evaluation import ate
from slam.runtime.system import System

N_FRAMES = 40
from conftest import XYZ, real_sequence


def map_arrays(slam_map) -> dict[str, np.ndarray]:
    """Every array of a SlamMap, keyed by name, for exact comparisons."""
    out = {"kf_T_wc": slam_map.kf_T_wc, "covisibility": slam_map.covisibility}
    for k in slam_map.keyframes:
        out[f"kf{k.id}_meta"] = np.array([k.id, k.frame_index, k.timestamp])
        out[f"kf{k.id}_lok"] = k.landmark_of_keypoint
        for name in ("uv_raw", "uv", "octaves", "descriptors", "depths", "u_right", "dynamic_prob", "scale_factors"):
            out[f"kf{k.id}_{name}"] = getattr(k.features, name)
    for prefix, table in (("lm", slam_map.landmarks), ("obs", slam_map.observations)):
        for name in table._data:
            out[f"{prefix}_{name}"] = getattr(table, name).copy()
    return {k: np.array(v, copy=True) for k, v in out.items()}


def assert_same_arrays(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].dtype == b[key].dtype, key
        assert a[key].shape == b[key].shape, key
        assert np.array_equal(a[key], b[key], equal_nan=a[key].dtype.kind == "f"), key


def run_system(system: System, frames) -> np.ndarray:
    tracked = []
    for frame in frames:
        out = system.process(frame.rgb, frame.depth, frame.timestamp, frame.index)
        tracked.append(out.T_wc is not None)
    return np.array(tracked)


def trajectory_ate(system: System, gt) -> float:
    stamps, poses, tracked = system.trajectory()
    return ate(gt[0], gt[1], stamps[tracked], poses[tracked]).rmse


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory):
    seq = SyntheticSequence(n_frames=N_FRAMES)
    frames = list(seq)
    config = load_config("static")   # about map files: the dynamic front end only adds time
    system = System(config)
    tracked = run_system(system, frames)
    assert tracked.all()
    path = tmp_path_factory.mktemp("map") / "map.npz"
    save_map(path, system.mapper.map, camera_info_from_config(config.camera), config.to_yaml())
    return dict(seq=seq, frames=frames, config=config, system=system, path=path,
                ate=trajectory_ate(system, seq.groundtruth()))


def test_round_trip_gives_identical_arrays(synthetic_run):
    original = synthetic_run["system"].mapper.map
    loaded, camera_info, config_yaml = load_map(synthetic_run["path"])
    assert loaded.num_keyframes == original.num_keyframes > 1
    assert len(loaded.landmarks) == len(original.landmarks) > 0
    assert_same_arrays(map_arrays(original), map_arrays(loaded))
    assert camera_info == camera_info_from_config(synthetic_run["config"].camera)
    assert config_yaml == synthetic_run["config"].to_yaml()
    with np.load(synthetic_run["path"], allow_pickle=False) as archive:  # no pickled members
        assert str(archive["format"]) == "dynslam-map" and int(archive["version"]) == 2


def test_atomic_save_leaves_no_temp_file(synthetic_run, tmp_path):
    target = tmp_path / "m.npz"
    target.write_bytes(b"old")
    save_map(target, synthetic_run["system"].mapper.map, {"fx": 1.0}, "")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz"]
    load_map(target)


def test_truncated_file_is_a_format_error(synthetic_run, tmp_path):
    data = synthetic_run["path"].read_bytes()
    bad = tmp_path / "truncated.npz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFormatError, match="truncated.npz"):
        load_map(bad)


def test_garbage_file_is_a_format_error(tmp_path):
    bad = tmp_path / "garbage.npz"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(MapFormatError, match="garbage.npz"):
        load_map(bad)
    missing = tmp_path / "absent.npz"
    with pytest.raises(MapFormatError, match="absent.npz"):
        load_map(missing)


def test_foreign_npz_and_wrong_version_are_format_errors(synthetic_run, tmp_path):
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, a=np.arange(3))
    with pytest.raises(MapFormatError, match="foreign.npz.*not a dynslam map"):
        load_map(foreign)
    with np.load(synthetic_run["path"], allow_pickle=False) as archive:
        arrays = {k: archive[k] for k in archive.files}
    arrays["version"] = np.array(99, np.int64)
    wrong = tmp_path / "v99.npz"
    np.savez_compressed(wrong, **arrays)
    with pytest.raises(MapFormatError, match=r"v99.npz.*version 99"):
        load_map(wrong)
    del arrays["lm_xyz"]
    arrays["version"] = np.array(1, np.int64)
    np.savez_compressed(wrong, **arrays)
    with pytest.raises(MapFormatError, match="lm_xyz"):
        load_map(wrong)


def test_camera_mismatch_is_reported(synthetic_run):
    config = load_config(overrides={"camera.fx": 500.0})
    info = camera_info_from_config(synthetic_run["config"].camera)
    check_camera_compatible(info, synthetic_run["config"].camera)
    with pytest.raises(MapCameraError, match="fx 525.0 in the map vs 500.0"):
        check_camera_compatible(info, config.camera, "m.npz")


def test_localization_only_on_synthetic(synthetic_run):
    prior, _, _ = load_map(synthetic_run["path"])
    before = map_arrays(prior)
    system = System(synthetic_run["config"], prior_map=prior, localization_only=True)
    tracked = run_system(system, synthetic_run["frames"])
    assert tracked.all(), np.flatnonzero(~tracked)
    loc_ate = trajectory_ate(system, synthetic_run["seq"].groundtruth())
    assert abs(loc_ate - synthetic_run["ate"]) < 0.01, (loc_ate, synthetic_run["ate"])
    assert system.num_keyframes == len(prior.keyframes)
    assert_same_arrays(before, map_arrays(system.mapper.map))


def test_localization_only_recovers_after_lost(synthetic_run):
    """A blank frame makes the tracker lose; the next frame relocalises against the whole map."""
    prior, _, _ = load_map(synthetic_run["path"])
    system = System(synthetic_run["config"], prior_map=prior, localization_only=True)
    frames = synthetic_run["frames"][:12]
    tracked = []
    for i, frame in enumerate(frames):
        rgb = np.zeros_like(frame.rgb) if i == 6 else frame.rgb
        depth = np.zeros_like(frame.depth) if i == 6 else frame.depth
        tracked.append(system.process(rgb, depth, frame.timestamp, frame.index).T_wc is not None)
    assert not tracked[6] and all(tracked[:6]) and all(tracked[7:])


def test_cli_save_and_load_map(tmp_path, monkeypatch):
    from slam.datasets import write_tum_layout

    import warnings

    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # main() replaces it
    seq = SyntheticSequence(n_frames=20)
    root = tmp_path / "synthetic_seq"
    write_tum_layout(seq, root)
    map_path = tmp_path / "map.npz"
    assert main(["run", str(root), "-o", str(tmp_path / "a"), "-q", "-c", "static", "--save-map", str(map_path)]) == 0
    assert map_path.is_file() and sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []
    before = map_arrays(load_map(map_path)[0])
    assert main(["run", str(root), "-o", str(tmp_path / "b"), "-q", "-c", "static", "--load-map", str(map_path)]) == 0
    assert_same_arrays(before, map_arrays(load_map(map_path)[0]))
    assert main(["run", str(root), "-o", str(tmp_path / "c"), "-q", "-c", "static", "--load-map", str(map_path),
                 "--set", "camera.fx=500"]) == 2
    (tmp_path / "bad.npz").write_bytes(b"nonsense")
    assert main(["run", str(root), "-o", str(tmp_path / "d"), "-q", "--load-map", str(tmp_path / "bad.npz")]) == 2


@pytest.mark.slow   # a whole run: kept out of the fast tier (< 2 min)
@pytest.mark.real
def test_localization_only_on_fr1_xyz(tmp_path):
    root = real_sequence(XYZ)
    config = resolve_run_config(root, ["static"], {})   # about localization: no detector needed
    dataset = TumDataset(root, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt)
    frames = list(dataset)
    gt = dataset.groundtruth()
    mapping = System(config, sequence_name=dataset.name)
    assert run_system(mapping, frames).all()
    map_ate = trajectory_ate(mapping, gt)
    path = tmp_path / "xyz.npz"
    save_map(path, mapping.mapper.map, camera_info_from_config(config.camera), config.to_yaml())
    prior, camera_info, _ = load_map(path)
    check_camera_compatible(camera_info, config.camera, path)
    before = map_arrays(prior)
    system = System(config, sequence_name=dataset.name, prior_map=prior, localization_only=True)
    tracked = run_system(system, frames)
    assert tracked.all(), np.flatnonzero(~tracked)
    loc_ate = trajectory_ate(system, gt)
    assert abs(loc_ate - map_ate) < 0.01, (loc_ate, map_ate)
    assert_same_arrays(before, map_arrays(system.mapper.map))
