"""Shared test set-up: where the real data lives, how its absence is handled, and factories.

Tiers (markers registered in pyproject.toml):
- ``real``: needs ``../shared`` (real sequences or the ONNX detectors) beside the checkout;
- ``slow``: takes more than a few seconds; ``pytest -m "not slow" -n 2`` is the everyday tier (< 2 min),
  ``pytest -n 2 --dist loadgroup`` the whole suite (tests/_suite_hooks.py groups the slow tests).

Missing real data: a user's clone without ``../shared`` skips those tests with a reason. In CI (the
environment variable ``CI`` is set, as ``.ci/run`` runs) a missing data set or model is a *failure*
naming what is missing, so a green CI always means the real-data gates ran.
"""
from __future__ import annotations

import http.server
import json
import os
import subprocess
import sys
import threading
import warnings
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from backend.local_mapping import LocalMapper
from slam.core.config import load_config
from slam.datasets import SyntheticSequence, write_tum_layout
from slam.datasets.synthetic import look_rotation
from slam.core.geometry import invert, make_pose, so3_exp, transform_points

# The suite's hooks: measured figures printed at the end, slow tests grouped for xdist (tests/_suite_hooks.py;
# pytest registers them as this conftest's own)
from _suite_hooks import (ACCURACY_GROUP, pytest_collection_modifyitems, pytest_runtest_logreport,  # noqa: F401
                          pytest_runtest_makereport, pytest_terminal_summary, report_figures)
# ROS and RealSense bags of a generated sequence (the formats' encoding lives in tests/_bag_writers.py)
from _bag_writers import (DEPTH_DELAY_S, DEPTH_TOPIC, INFO_TOPIC, RGB_TOPIC, RS_COLOUR, RS_DEPTH,  # noqa: F401
                          RS_DEPTH_DELAY_S, RS_UNITS_TOPIC, START_S, render_depth_camera, rs_extrinsic,
                          write_bag, write_realsense_bag)

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data"
MODELS = SHARED / "models"

RPY = "rgbd_dataset_freiburg1_rpy_first400"
XYZ = "rgbd_dataset_freiburg1_xyz_first37"
DESK = "rgbd_dataset_freiburg1_desk_9frames"
BONN = "rgbd_bonn_crowd_first480"
MODEL_FILES = {"yolox": "yolox_nano_416.onnx", "nanodet": "nanodet_m_320.onnx"}


def in_ci() -> bool:
    return bool(os.environ.get("CI"))


def require_shared(path: Path, what: str) -> Path:
    """``path`` if it exists; otherwise skip (a user's clone) or fail (CI) saying what is missing."""
    if path.exists():
        return path
    message = f"{what} is missing: {path} does not exist (it comes with ../shared beside the checkout)"
    if in_ci():
        pytest.fail(f"CI needs the real data: {message}", pytrace=False)
    pytest.skip(message)


def real_sequence(name: str) -> Path:
    """The folder of a real sequence in ../shared/data (skip or CI failure when absent)."""
    return require_shared(DATA / name, f"real sequence {name}")


def model_file(kind: str) -> Path:
    """The development copy of a detector model in ../shared/models (skip or CI failure when absent)."""
    return require_shared(MODELS / MODEL_FILES[kind], f"detector model {kind}")


# ----------------------------------------------------------------------------------- factories
def synthetic_sequence(n_frames: int = 40, seed: int = 0, **kwargs):
    """A generated RGB-D room (``slam.datasets.SyntheticSequence``), e.g. ``movers="people"``."""
    return SyntheticSequence(n_frames=n_frames, seed=seed, **kwargs)


def synthetic_config(sequence, preset: Optional[str] = "static", **overrides):
    """The default config with ``sequence``'s camera, then ``preset``, then dotted overrides. The preset
    is ``static`` (dynamic handling off) unless a test asks for another (or None, the product's
    default): most tests are about other parts, and the dynamic front end would only slow them down."""
    from slam.run.dynamic_eval import synthetic_config as make

    return make(sequence, preset=preset, **overrides)


def grow_random_map(seed: int, n_keyframes: int, window: int = 6, per_keyframe: int = 40, fuse_every: int = 5):
    """Yield ``(slam_map, touched)`` while a seeded random ``SlamMap`` grows one keyframe at a time.

    Keyframe k observes new landmarks and ones seen in the last ``window`` keyframes (sometimes the
    same landmark twice, as after a fusion). Every ``fuse_every`` keyframes a few landmarks are
    fused into others the way ``landmark_fusion`` does it (observations re-pointed, duplicate bad).
    ``touched``: keyframes whose covisibility was updated (ascending). Built through the map's own
    API only, so a brute-force reference can replay the same map."""
    from types import SimpleNamespace

    from backend.map_store import SlamMap

    rng = np.random.default_rng(seed)
    slam_map = SlamMap()
    first_of = [0]                       # first landmark id of each keyframe
    for k in range(n_keyframes):
        n_new = int(rng.integers(per_keyframe // 2, per_keyframe))
        new = slam_map.landmarks.append(xyz=rng.normal(size=(n_new, 3)), anchor_kf=np.full(n_new, k))
        old_pool = np.arange(first_of[max(0, k - window)], new[0])
        old = rng.choice(old_pool, size=min(len(old_pool), per_keyframe // 2), replace=False)
        lms = np.concatenate([old, new, rng.choice(new, size=2)])     # two repeated observations
        slam_map.add_keyframe(SimpleNamespace(index=k, timestamp=float(k), gray=None), np.eye(4), lms)
        slam_map.observations.append(kf=np.full(len(lms), k), lm=lms, kp=np.arange(len(lms)))
        first_of.append(len(slam_map.landmarks))
        slam_map.update_covisibility(k)
        touched = np.array([k])
        if k and k % fuse_every == 0:
            ids = np.arange(len(slam_map.landmarks))
            dup = rng.choice(ids, size=6, replace=False)
            target = rng.choice(np.setdiff1d(ids, dup), size=6)
            order = np.argsort(dup)
            rows = slam_map.observation_rows(dup)
            obs = slam_map.observations
            slam_map.relink_observations(rows, target[order][np.searchsorted(dup[order], obs.lm[rows])])
            slam_map.landmarks.bad[dup] = True
            touched = np.union1d(np.unique(obs.kf[rows]), [k])
            for t in touched:
                slam_map.update_covisibility(int(t))
        yield slam_map, touched


def run_dynslam(args: Sequence[str], timeout: float = 600, env: Optional[dict] = None,
                cwd: Optional[Path] = None) -> subprocess.CompletedProcess:
    """``dynslam ARGS`` in a fresh Python process (what a user runs), capturing its output."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "slam.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=full_env, cwd=cwd or REPO)


def read_summary(results: Path) -> dict:
    return json.loads((Path(results) / "summary.json").read_text())


def tum_pose_lines(path: Path) -> list[str]:
    """The pose lines of a TUM file (comments, e.g. ``# t LOST``, left out)."""
    return [line for line in Path(path).read_text().splitlines() if line and not line.startswith("#")]


def frame_errors(results: Path, groundtruth: Path) -> np.ndarray:
    """Per-frame translation error (m) of a run's trajectory after the ATE alignment."""
    from slam.run.evaluation import evaluate_files

    report = evaluate_files(groundtruth, Path(results) / "trajectory.txt", 0.02)
    return np.asarray(report.ate.errors)


def load_tool(name: str):
    """A script of ``tools/`` imported as a module (the tools are scripts, not a package)."""
    import importlib.util

    tools = REPO / "tools"
    spec = importlib.util.spec_from_file_location(f"{name}_tool", tools / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    sys.path.insert(0, str(tools))   # a tool may import its siblings (ablation.py imports sweep.py)
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(tools))
    return module


class AccuracyRuns:
    """The cases of ``tools/accuracy.py``, each run once per test session as ``dynslam`` processes
    (2 at a time: this machine's cores) and shared by every test that needs them (the gates, the
    Bonn map export, ...)."""

    def __init__(self, root: Path):
        self.tool = load_tool("accuracy")
        self.root = root
        self.results: dict = {}
        self.identical: dict[str, bool] = {}

    def get(self, *names: str, twins: bool = False) -> dict:
        """Results of the named cases, running those not run yet; ``twins``: also the second process
        of the suite's determinism cases among them (``SUITE_DETERMINISM_CASES``)."""
        for name in names:
            case = self.tool.CASES[name]
            if case.sequence:
                real_sequence(case.sequence)
            if "static" not in case.args and case.sequence:
                model_file("yolox")   # the default runs the real detector, no cache
        todo = [n for n in names if n not in self.results]
        suite_twins = self.tool.SUITE_DETERMINISM_CASES if twins else ()
        late_twins = [n for n in names if n in self.results and n in suite_twins and n not in self.identical]
        if todo:
            results, identical = self.tool.run_cases(todo, self.root, jobs=2, twins=suite_twins)
            self.results.update(results)
            self.identical.update(identical)
        for name in late_twins:   # run first without its twin: the second process now
            again = self.tool.run_case(self.tool.CASES[name], self.root / f"{name}_again")
            self.identical[name] = self.tool.same_trajectory(self.root / name, again.results)
        return {n: self.results[n] for n in names}


@pytest.fixture(scope="session")
def accuracy_runs(tmp_path_factory) -> AccuracyRuns:
    return AccuracyRuns(tmp_path_factory.mktemp("accuracy"))


# ------------------------------------------------------------------ a room walked twice, with drift
# The camera walks an ellipse (1.0 x 0.8 m) in the generated room looking outwards, PERIOD frames per
# lap. The renderer is exact, so on its own the system hardly drifts; ``inject_drift`` makes drift the
# way it arises in practice: from frame DRIFT_FROM on, every keyframe's *new* landmarks are measured
# DRIFT_DEG rotated about the camera (used by test_loop_closing.py and the fault table).
PERIOD = 150
LAPS = 2
DRIFT_DEG = 0.3
DRIFT_FROM, DRIFT_UNTIL = 30, LAPS * PERIOD


def lap_pose(i: int) -> np.ndarray:
    a = 2 * np.pi * i / PERIOD
    T = np.eye(4)
    T[:3, :3] = look_rotation(a, -0.05, 0.0)
    T[:3, 3] = [1.0 * np.cos(a), 0.8 * np.sin(a), 1.4]
    return T


def walk_laps(system, seq, n_frames: int, renders: Optional[dict] = None) -> np.ndarray:
    """Feed ``system`` the first ``n_frames`` of the lap path (``lap_pose``) rendered from ``seq`` at
    30 Hz; returns the true poses. Ends with the worker's last update landed: the tests edit and compare
    the settled graph. ``renders`` (frame -> read-only rgb, depth) keeps the images for the next walk of
    the same ``seq``: rendering is about a third of a walk's time."""
    gt = []
    for i in range(n_frames):
        T = lap_pose(i)
        images = None if renders is None else renders.get(i)
        if images is None:
            images = seq.render(T, 0.0)
            if renders is not None:
                for image in images:
                    image.setflags(write=False)   # shared with the next walk
                renders[i] = images
        system.process(*images, i / 30.0, i)
        gt.append(T)
    system.mapper.sync()
    return np.array(gt)


def inject_drift(monkeypatch) -> None:
    R = Rotation.from_euler("y", DRIFT_DEG, degrees=True).as_matrix()   # camera y = vertical: a heading error
    create = LocalMapper._create_landmarks

    def drifting(self, kf_id, frame, T_wc, lm_of_kp, colors=None):
        first = len(self.map.landmarks)
        n = create(self, kf_id, frame, T_wc, lm_of_kp, colors)
        if not DRIFT_FROM <= frame.index < DRIFT_UNTIL:
            return n
        lm, obs, cam = self.map.landmarks, self.map.observations, self.camera
        new = np.arange(first, len(lm))
        lm.local_xyz[new] = lm.local_xyz[new] @ R.T
        self.map.refresh_anchored()
        rows = np.flatnonzero((obs.kf == kf_id) & (obs.lm >= first))
        p = lm.local_xyz[obs.lm[rows]]
        obs.uv[rows] = np.c_[cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy]
        obs.depth[rows] = p[:, 2]
        return n

    monkeypatch.setattr(LocalMapper, "_create_landmarks", drifting)


def drift_room_config(loop: bool):
    seq = SyntheticSequence(n_frames=2)
    fx, fy, cx, cy = seq.intrinsics
    return load_config("static", overrides={"camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy,
                                  "camera.width": seq.width, "camera.height": seq.height,
                                  "camera.distortion": [0.0] * 5, "loop.enabled": loop})




# ----------------------------------------------------------------------------------- local HTTP server
class RangeHandler(http.server.BaseHTTPRequestHandler):
    """Serves ``server.files`` (URL path -> bytes) with Range support; records every Range header.

    ``server.ignore_range`` answers 200 with the whole file anyway; ``server.cut_after`` announces the
    full length but closes the connection after that many body bytes; ``server.fail_status`` answers
    every request with that HTTP error.
    """

    def do_GET(self):  # noqa: N802 (http.server's naming)
        server = self.server
        server.ranges.append(self.headers.get("Range"))
        if server.fail_status:
            self.send_error(server.fail_status)
            return
        body = server.files.get(self.path)
        if body is None:
            self.send_error(404, "Not Found")
            return
        start = 0
        wanted = self.headers.get("Range")
        if wanted and not server.ignore_range:
            start = int(wanted.split("=")[1].split("-")[0])
            if start >= len(body):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(body)}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
        else:
            self.send_response(200)
        self.send_header("Content-Length", str(len(body) - start))
        self.end_headers()
        payload = body[start:]
        if server.cut_after is not None:
            payload = payload[:server.cut_after]
        self.wfile.write(payload)
        if server.cut_after is not None:
            self.wfile.flush()
            self.close_connection = True

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    """A local HTTP server on 127.0.0.1 (a thread) serving ``server.files``; ``server.base_url``."""
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), RangeHandler)
    httpd.files, httpd.ranges, httpd.ignore_range, httpd.cut_after, httpd.fail_status = {}, [], False, None, 0
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    httpd.base_url = f"http://127.0.0.1:{httpd.server_address[1]}"
    yield httpd
    httpd.shutdown()
    httpd.server_close()




# --- a ring of keyframes for the graph back ends (tests/test_window_graph.py, test_graph_process.py) ----

RING_FX, RING_CX, RING_CY = 525.0, 319.5, 239.5


def _ring_calibration():
    from backend.factors import StereoCalibration

    return StereoCalibration(RING_FX, RING_FX, RING_CX, RING_CY, 0.08)


RING_CALIBRATION = _ring_calibration()


def ring_poses(n: int, radius: float = 2.0) -> np.ndarray:
    """Cameras on a circle looking outwards, one every 360/n degrees: the last one meets the first."""
    poses = []
    for k in range(n):
        yaw = 2 * np.pi * k / n
        R = so3_exp([0.0, yaw, 0.0])
        poses.append(make_pose(R, R @ np.array([0.0, 0.0, -radius])))
    return np.array(poses)


def wall_points(poses: np.ndarray, rng: np.random.Generator, per_keyframe: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Points 2-3 m in front of each camera; returns (points, index of the keyframe that made each)."""
    pts, owner = [], []
    for k, T in enumerate(poses):
        local = np.column_stack([rng.uniform(-1.0, 1.0, per_keyframe), rng.uniform(-0.7, 0.7, per_keyframe),
                                 rng.uniform(2.0, 3.0, per_keyframe)])
        pts.append(transform_points(T, local))
        owner += [k] * per_keyframe
    return np.vstack(pts), np.array(owner)


def observe(graph, kf: int, T: np.ndarray, ids: np.ndarray, points: np.ndarray) -> None:
    Xc = transform_points(invert(T), points[ids])
    ok = Xc[:, 2] > 0.3
    uv = np.column_stack([RING_FX * Xc[:, 0] / Xc[:, 2] + RING_CX, RING_FX * Xc[:, 1] / Xc[:, 2] + RING_CY])
    inside = ok & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
    for j, p, z in zip(ids[inside], uv[inside], Xc[inside, 2]):
        graph.add_observation(kf, int(j), p, depth=float(z))


def drifted(poses: np.ndarray, yaw_per_step_deg: float) -> np.ndarray:
    """Odometry-like guesses: every step's motion turned a little more than the truth."""
    out = [poses[0]]
    extra = make_pose(so3_exp([0.0, np.radians(yaw_per_step_deg), 0.0]), [0.0, 0.0, 0.0])
    for k in range(1, len(poses)):
        out.append(out[-1] @ extra @ invert(poses[k - 1]) @ poses[k])
    return np.array(out)


def run_ring(graph, n: int, seed: int = 0, drift_deg: float = 0.0):
    """Keyframes round the ring as a SLAM run adds them: each sees its own points and its two
    predecessors', one update per keyframe. With ``drift_deg`` the measurements are those of a drifted
    ring (every step turned a little more): consistent among themselves, so only a loop reveals it.
    Returns (true poses, true points, keyframe that made each point)."""
    poses = ring_poses(n)
    seen = drifted(poses, drift_deg)              # the world as the measurements describe it
    local, owner = wall_points(np.tile(np.eye(4), (n, 1, 1)), np.random.default_rng(seed))
    points = np.vstack([transform_points(poses[k], local[owner == k]) for k in range(n)])
    seen_points = np.vstack([transform_points(seen[k], local[owner == k]) for k in range(n)])
    for k in range(n):
        graph.add_keyframe(k, seen[k])
        if k:
            graph.add_relative_pose(k - 1, k, invert(seen[k - 1]) @ seen[k], 0.05, 2.0)
        for j in np.flatnonzero(owner == k):
            graph.add_landmark(int(j), seen_points[j])
        observe(graph, k, seen[k], np.flatnonzero((owner >= k - 2) & (owner <= k)), seen_points)
        graph.update()
    return poses, points, owner


# --- fixtures shared by test modules split by topic (test_faults_*, test_cli_*, test_frontend_*) ------------

@pytest.fixture
def restore_warning_format(monkeypatch):
    """main() installs its own warnings.formatwarning; keep it from leaking into other tests (modules that
    call main() use it with ``pytestmark = pytest.mark.usefixtures("restore_warning_format")``)."""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)


FAULT_TUM_FRAMES = 24


@pytest.fixture(scope="module")
def tum_folder(tmp_path_factory) -> Path:
    """A generated room written as a TUM folder (lists, PNGs, camera.yaml, groundtruth.txt): what the
    fault tests hurt; built once per module."""
    return write_tum_layout(synthetic_sequence(FAULT_TUM_FRAMES), tmp_path_factory.mktemp("tum") / "synthetic_room")


ORBIT_FRAMES = 30


@pytest.fixture(scope="module")
def orbit_sequence():
    """The first frames of the seeded orbit sequence, rendered once per module: (frames, T_wc ground truth)."""
    seq = SyntheticSequence(n_frames=ORBIT_FRAMES, path="orbit", seed=0)
    _, gt = seq.groundtruth()
    return list(seq), gt


@pytest.fixture(scope="module")
def default_config():
    return load_config()


@pytest.fixture(scope="module")
def default_camera(default_config):
    from slam.core.camera import PinholeCamera
    return PinholeCamera.from_config(default_config.camera)


@pytest.fixture(scope="module")
def orbit_features(orbit_sequence, default_config, default_camera):
    """ORB features of the orbit sequence's first three frames (default config)."""
    from frontend.orb_extractor import OrbExtractor
    frames, _ = orbit_sequence
    extractor = OrbExtractor(default_config.orb, default_camera)
    return [extractor.extract(cv2.cvtColor(f.rgb, cv2.COLOR_BGR2GRAY), f.depth, f.index, f.timestamp)
            for f in frames[:3]]
