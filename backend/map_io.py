"""Saving and loading a ``SlamMap``: the ``dynslam-map`` file format, version 1.

A map file is a compressed NumPy ``.npz`` archive (a zip of ``.npy`` arrays) that holds only plain
numeric and unicode arrays, so it is read with ``allow_pickle=False`` and never executes code.
Its members (K keyframes, F keyframe features in all, L pyramid levels, M landmarks, O observations):

==============================  ===============  ===========================================================
member                          shape, dtype     meaning
==============================  ===============  ===========================================================
``format``                      (), unicode      always ``"dynslam-map"``
``version``                     (), int64        format version, ``2`` (``1`` is still read)
``camera_json``                 (), unicode      camera intrinsics as JSON: fx, fy, cx, cy, width, height,
                                                 distortion, bf, depth_scale, name (``camera_info``)
``config_yaml``                 (), unicode      the resolved configuration of the run that built the map
``kf_id``                       (K,) int64       keyframe ids (0..K-1, their position in the map)
``kf_frame_index``              (K,) int64       index of the frame each keyframe was made from
``kf_timestamp``                (K,) float64     timestamps (s)
``kf_T_wc``                     (K,4,4) float64  keyframe poses, camera to world
``kf_feature_offsets``          (K+1,) int64     keyframe k's features are rows ``[off[k], off[k+1])`` of feat_*
``kf_scale_factors``            (K,L) float64    scale of each pyramid level, per keyframe
``feat_uv_raw``                 (F,2)            distorted pixel coordinates
``feat_uv``                     (F,2)            undistorted pixel coordinates
``feat_octaves``                (F,)             pyramid level
``feat_descriptors``            (F,32) uint8     ORB descriptors
``feat_depths``                 (F,)             depth (m), 0 = none
``feat_u_right``                (F,)             virtual stereo u, NaN = none
``feat_dynamic_prob``           (F,)             fused dynamic probability
``feat_landmark_of_keypoint``   (F,) int64       landmark id of each feature, -1 = none
``lm_<column>``                 (M,...)          landmark table columns: xyz, local_xyz, descriptors, octave,
                                                 anchor_kf, n_obs, visible, found, dynamic_sum,
                                                 dynamic_hits, bad, in_graph (dtypes as in map_store)
``obs_<column>``                (O,...)          observation table columns: kf, lm, kp, uv, depth,
                                                 level_scale, dynamic_prob, in_graph
``covisibility``                (K,K) int32      shared-landmark counts between keyframes
==============================  ===============  ===========================================================

Version 2 adds the landmark ``color`` (BGR uint8) and observation ``factor`` columns, and the
vocabulary, keyframe words and loop members documented in ``backend.map_io_places``. Version-1
files still load (without those).

Feature arrays keep the dtypes they had in memory. Landmark ids are row indices of the landmark
table; culled landmarks stay in the table with ``bad`` set, so ids remain valid. The iSAM2 graph is
not saved: a loaded map is meant for localisation against fixed landmarks (or as the starting point
of a new graph).

``save_map`` writes atomically (temporary file in the destination folder, flushed, fsynced, then
``os.replace``), so a reader sees the old file or the complete new one. ``load_map`` raises
``MapFormatError`` (a ``ValueError``) naming the path and the problem for a missing, truncated,
corrupt, foreign or wrong-version file, or one whose arrays disagree in size.
"""
from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from backend.map_io_places import PlaceData, place_arrays, read_place_arrays
from backend.map_store import KeyframeRecord, SlamMap, landmark_table, observation_table
from backend.place_recognition import KeyframeIndex
from slam.core.atomic_io import write_npz_atomic
from slam.core.frame import FeatureFrame
from slam.core.errors import DynslamError

FORMAT_NAME = "dynslam-map"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)   # version 1: no colour, factor handles, vocabulary, keyframe words or loops

PathLike = Union[str, os.PathLike]

_FEATURE_FIELDS = ("uv_raw", "uv", "octaves", "descriptors", "depths", "u_right", "dynamic_prob")
_CAMERA_CHECKED = ("fx", "fy", "cx", "cy", "width", "height")


class MapFormatError(DynslamError, ValueError):
    """A map file that cannot be read as a dynslam map (names the path and what is wrong)."""


class MapCameraError(DynslamError, ValueError):
    """A map built with a different camera than the one of the run that wants to use it."""


def camera_info_from_config(camera_config: Any) -> dict:
    """The intrinsics stored with a map, from a ``CameraConfig``."""
    return {
        "name": str(camera_config.name), "fx": float(camera_config.fx), "fy": float(camera_config.fy),
        "cx": float(camera_config.cx), "cy": float(camera_config.cy), "width": int(camera_config.width),
        "height": int(camera_config.height), "distortion": [float(d) for d in camera_config.distortion],
        "bf": float(camera_config.bf), "depth_scale": float(camera_config.depth_scale),
    }


def check_camera_compatible(camera_info: Mapping, camera_config: Any, path: PathLike = "map") -> None:
    """Raise ``MapCameraError`` when the map's fx/fy/cx/cy/width/height differ from the run's."""
    wrong = []
    for key in _CAMERA_CHECKED:
        saved, current = camera_info.get(key), getattr(camera_config, key)
        if saved is None or not np.isclose(float(saved), float(current), rtol=1e-9, atol=1e-9):
            wrong.append(f"{key} {saved} in the map vs {current} in the run")
    if wrong:
        raise MapCameraError(f"{path}: map was built with a different camera ({'; '.join(wrong)})")


# ------------------------------------------------------------------------------------------ saving
def _map_arrays(slam_map: SlamMap, camera_info: Mapping, config_yaml: str) -> dict[str, np.ndarray]:
    kfs = slam_map.keyframes
    counts = [len(k.features) for k in kfs]
    offsets = np.zeros(len(kfs) + 1, np.int64)
    offsets[1:] = np.cumsum(counts)
    levels = {len(k.features.scale_factors) for k in kfs}
    if len(levels) > 1:
        raise ValueError(f"keyframes have different pyramid depths {sorted(levels)}; cannot save")
    n_levels = levels.pop() if levels else 0
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT_NAME), "version": np.array(FORMAT_VERSION, np.int64),
        "camera_json": np.array(json.dumps(dict(camera_info), sort_keys=True)),
        "config_yaml": np.array(config_yaml),
        "kf_id": np.array([k.id for k in kfs], np.int64),
        "kf_frame_index": np.array([k.frame_index for k in kfs], np.int64),
        "kf_timestamp": np.array([k.timestamp for k in kfs], np.float64),
        "kf_T_wc": np.asarray(slam_map.kf_T_wc, np.float64).reshape(len(kfs), 4, 4),
        "kf_feature_offsets": offsets,
        "kf_scale_factors": np.array([k.features.scale_factors for k in kfs], np.float64).reshape(len(kfs), n_levels),
        "covisibility": np.asarray(slam_map.covisibility),
    }
    empty = FeatureFrame(0, 0.0, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64),
                         np.zeros((0, 32), np.uint8), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    for name in _FEATURE_FIELDS:
        parts = [np.asarray(getattr(k.features, name)) for k in kfs] or [getattr(empty, name)]
        arrays[f"feat_{name}"] = np.concatenate(parts)
    lok = [np.asarray(k.landmark_of_keypoint, np.int64) for k in kfs] or [np.zeros(0, np.int64)]
    arrays["feat_landmark_of_keypoint"] = np.concatenate(lok)
    for prefix, table in (("lm", slam_map.landmarks), ("obs", slam_map.observations)):
        for name in table._data:
            arrays[f"{prefix}_{name}"] = np.ascontiguousarray(getattr(table, name))
    return arrays


def save_map(path: PathLike, slam_map: SlamMap, camera_info: Mapping, config_yaml: str,
             index: Optional[KeyframeIndex] = None, loops: Sequence = ()) -> None:
    """Write ``slam_map`` (with the keyframe index and its vocabulary, and the loops, when given) to
    ``path`` in the dynslam-map format, atomically."""
    arrays = _map_arrays(slam_map, camera_info, config_yaml)
    arrays.update(place_arrays(slam_map.num_keyframes, index, loops))
    write_npz_atomic(path, **arrays)


# ----------------------------------------------------------------------------------------- loading
def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise MapFormatError(f"{path}: map file does not exist")
    try:
        archive = np.load(path, allow_pickle=False)
        if not isinstance(archive, np.lib.npyio.NpzFile):
            raise MapFormatError(f"{path}: not a dynslam map (a single .npy array, not an .npz archive)")
        with archive:
            return {name: archive[name] for name in archive.files}
    except MapFormatError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, KeyError,
            RuntimeError, UnicodeDecodeError) as exc:
        raise MapFormatError(f"{path}: not a readable dynslam map (truncated or corrupt .npz: {exc})") from exc


def _scalar_str(arrays: dict, key: str, path: Path) -> str:
    value = arrays[key]
    if value.shape != () or value.dtype.kind != "U":
        raise MapFormatError(f"{path}: member '{key}' should be a text scalar, got {value.dtype} {value.shape}")
    return str(value[()])


@dataclass
class LoadedMap:
    slam_map: SlamMap
    camera_info: dict
    config_yaml: str
    places: PlaceData       # vocabulary, keyframe words and loops (empty for version-1 files)

    def __iter__(self):     # ``slam_map, camera_info, config_yaml = load_map(path)`` keeps working
        return iter((self.slam_map, self.camera_info, self.config_yaml))

    def __getitem__(self, i: int):
        return (self.slam_map, self.camera_info, self.config_yaml)[i]


def load_map(path: PathLike) -> LoadedMap:
    """Read a map file. Raises ``MapFormatError`` naming the path and the problem."""
    path = Path(path)
    arrays = _read_arrays(path)
    if "format" not in arrays or arrays["format"].dtype.kind != "U" or str(arrays["format"][()]) != FORMAT_NAME:
        raise MapFormatError(f"{path}: not a dynslam map (no format='{FORMAT_NAME}' marker)")
    version = arrays.get("version")
    if version is None or version.shape != () or version.dtype.kind not in "iu":
        raise MapFormatError(f"{path}: dynslam map without a valid version number")
    if int(version) not in READABLE_VERSIONS:
        raise MapFormatError(f"{path}: dynslam map version {int(version)} is not supported "
                             f"(this dynslam reads versions {', '.join(map(str, READABLE_VERSIONS))})")
    required = ["camera_json", "config_yaml", "kf_id", "kf_frame_index", "kf_timestamp", "kf_T_wc",
                "kf_feature_offsets", "kf_scale_factors", "covisibility", "feat_landmark_of_keypoint"]
    required += [f"feat_{n}" for n in _FEATURE_FIELDS]
    lm_columns, obs_columns = landmark_table()._data, observation_table()._data
    optional = {"lm_color", "obs_factor"}  # added after version 1 went out: absent means unknown (black)
    required += [f"lm_{n}" for n in lm_columns if f"lm_{n}" not in optional] + [f"obs_{n}" for n in obs_columns]
    missing = [k for k in required if k not in arrays]
    if missing:
        raise MapFormatError(f"{path}: dynslam map is missing members {missing}")
    try:
        camera_info = json.loads(_scalar_str(arrays, "camera_json", path))
    except json.JSONDecodeError as exc:
        raise MapFormatError(f"{path}: camera_json is not valid JSON ({exc})") from exc
    if not isinstance(camera_info, dict):
        raise MapFormatError(f"{path}: camera_json should be a JSON object")
    config_yaml = _scalar_str(arrays, "config_yaml", path)
    slam_map = _build_map(arrays, path, lm_columns, obs_columns)
    places = read_place_arrays(arrays, path, slam_map.num_keyframes, MapFormatError)
    return LoadedMap(slam_map, camera_info, config_yaml, places)


def _expect(cond: bool, path: Path, what: str) -> None:
    if not cond:
        raise MapFormatError(f"{path}: inconsistent dynslam map: {what}")


def _build_map(a: dict, path: Path, lm_columns: dict, obs_columns: dict) -> SlamMap:
    K = len(a["kf_id"])
    offsets = a["kf_feature_offsets"]
    F = len(a["feat_uv"])
    _expect(a["kf_id"].ndim == 1 and np.array_equal(a["kf_id"], np.arange(K)), path, "keyframe ids are not 0..K-1")
    _expect(a["kf_frame_index"].shape == (K,) and a["kf_timestamp"].shape == (K,), path,
            "keyframe frame indices / timestamps do not match the keyframe count")
    _expect(a["kf_T_wc"].shape == (K, 4, 4), path, f"kf_T_wc has shape {a['kf_T_wc'].shape}, expected ({K}, 4, 4)")
    _expect(a["kf_scale_factors"].ndim == 2 and len(a["kf_scale_factors"]) == K, path, "kf_scale_factors shape")
    _expect(offsets.shape == (K + 1,) and offsets.dtype.kind in "iu" and offsets[0] == 0
            and np.all(np.diff(offsets) >= 0) and offsets[-1] == F, path, "keyframe feature offsets")
    for name in list(_FEATURE_FIELDS) + ["landmark_of_keypoint"]:
        _expect(len(a[f"feat_{name}"]) == F, path, f"feat_{name} has {len(a[f'feat_{name}'])} rows, expected {F}")
    _expect(a["covisibility"].shape == (K, K), path, f"covisibility shape {a['covisibility'].shape}, expected ({K}, {K})")

    slam_map = SlamMap()
    for k in range(K):
        s, e = int(offsets[k]), int(offsets[k + 1])
        features = FeatureFrame(int(a["kf_frame_index"][k]), float(a["kf_timestamp"][k]),
                                *(a[f"feat_{n}"][s:e].copy() for n in _FEATURE_FIELDS),
                                scale_factors=a["kf_scale_factors"][k].copy(), gray=None)
        slam_map.keyframes.append(KeyframeRecord(k, int(a["kf_frame_index"][k]), float(a["kf_timestamp"][k]),
                                                 features, a["feat_landmark_of_keypoint"][s:e].astype(np.int64)))
    slam_map.kf_T_wc = a["kf_T_wc"].astype(np.float64)
    slam_map.covisibility = a["covisibility"].astype(np.int32)
    for prefix, table, columns in (("lm", slam_map.landmarks, lm_columns), ("obs", slam_map.observations, obs_columns)):
        n = len(a[f"{prefix}_{next(iter(columns))}"])
        for name, arr in columns.items():
            a.setdefault(f"{prefix}_{name}", np.zeros((n,) + arr.shape[1:], arr.dtype))
            value = a[f"{prefix}_{name}"]
            _expect(value.shape == (n,) + arr.shape[1:], path,
                    f"{prefix}_{name} has shape {value.shape}, expected {(n,) + arr.shape[1:]}")
        if n:
            table.append(**{name: a[f"{prefix}_{name}"] for name in columns})
    M = len(slam_map.landmarks)
    lok = a["feat_landmark_of_keypoint"]
    _expect(bool(np.all((lok >= -1) & (lok < M))), path, "feature landmark ids out of range")
    obs = slam_map.observations
    _expect(bool(np.all((obs.kf >= 0) & (obs.kf < K) & (obs.lm >= 0) & (obs.lm < M))), path,
            "observation keyframe/landmark ids out of range")
    _expect(bool(np.all((slam_map.landmarks.anchor_kf >= 0) & (slam_map.landmarks.anchor_kf < max(K, 1)))), path,
            "landmark anchor keyframes out of range")
    return slam_map
