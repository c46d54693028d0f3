"""The README's Python example runs as written, on a small scene made here for its placeholders."""
from __future__ import annotations

import json
import re

import numpy as np

from conftest import REPO


def readme_python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), flags=re.S)


def test_backend_example_runs_and_recovers_the_pose():
    block = next(b for b in readme_python_blocks() if "FactorGraphBackend" in b)
    fx, fy, cx, cy = 517.3, 516.5, 318.6, 255.3
    T_true = np.eye(4)
    T_true[:3, 3] = [0.10, 0.0, 0.0]              # keyframe 1 is 10 cm right of keyframe 0
    rng = np.random.default_rng(0)
    world = np.c_[rng.uniform(-0.8, 0.8, 12), rng.uniform(-0.6, 0.6, 12), rng.uniform(1.5, 3.0, 12)]
    cam1 = (np.linalg.inv(T_true) @ np.c_[world, np.ones(12)].T).T[:, :3]

    def uv(p):
        return (fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy)

    T_guess = T_true.copy()
    T_guess[:3, 3] += [0.02, -0.01, 0.01]         # a rough guess, as a tracker would give
    points = [(w + 0.03, uv(w), w[2], uv(c)) for w, c in zip(world, cam1)]
    names = {"T_wc_guess": T_guess, "T_01": T_true, "points": points}
    exec(compile(block, "README.md", "exec"), names)   # noqa: S102  (our own README)
    assert np.allclose(names["T_wc1"][:3, 3], T_true[:3, 3], atol=0.005)
    ids, xyz_est = names["ids"], names["xyz"]
    assert list(ids) == list(range(12)) and np.allclose(xyz_est, world, atol=0.01)
    after = names["graph"].keyframe_pose(1)       # without the relative pose, the landmarks hold it
    assert np.allclose(after[:3, 3], T_true[:3, 3], atol=0.005)


def test_system_example_of_the_package_docstring_runs():
    import slam
    from slam.datasets import SyntheticSequence

    doc = slam.__doc__
    code = "\n".join(line.strip() for line in doc.splitlines() if line.startswith("    "))
    seq = SyntheticSequence(n_frames=2)
    frame = seq.frame(0)
    fx, fy, cx, cy = seq.intrinsics
    names = {"bgr_uint8": frame.rgb, "depth_metres_float32": frame.depth, "timestamp": frame.timestamp}
    code = code.replace('load_config("tum_fr1")', 'load_config("tum_fr1", overrides=CAMERA)')
    names["CAMERA"] = {"camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy,
                       "camera.distortion": [0.0] * 5}
    exec(compile(code, "slam/__init__.py", "exec"), names)   # noqa: S102
    assert names["out"].T_wc is not None and np.allclose(names["out"].T_wc, np.eye(4))


def test_system_example_runs_on_a_generated_frame():
    block = next(b for b in readme_python_blocks() if "System(load_config" in b)
    from slam.datasets import SyntheticSequence

    seq = SyntheticSequence(n_frames=2)
    fx, fy, cx, cy = seq.intrinsics
    frame = seq.frame(0)
    camera = {"camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy, "camera.distortion": [0.0] * 5}
    block = block.replace('load_config("tum_fr1")', 'load_config("tum_fr1", overrides=CAMERA)')
    names = {"CAMERA": camera, "bgr": frame.rgb, "depth_m": frame.depth, "t": frame.timestamp}
    exec(compile(block, "README.md", "exec"), names)   # noqa: S102
    assert names["out"].T_wc is not None and names["tracked"].all() and len(names["stamps"]) == 1


def test_lookahead_example_runs_on_generated_frames():
    """The README's lookahead call: frame 1 announces frame 2, whose begun work the next call takes."""
    first = next(b for b in readme_python_blocks() if "System(load_config" in b)
    block = next(b for b in readme_python_blocks() if "UpcomingFrame(" in b)
    from slam.datasets import SyntheticSequence

    seq = SyntheticSequence(n_frames=3)
    fx, fy, cx, cy = seq.intrinsics
    f0, f1, f2 = (seq.frame(i) for i in range(3))
    camera = {"camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy, "camera.distortion": [0.0] * 5}
    first = first.replace('load_config("tum_fr1")', 'load_config("tum_fr1", overrides=CAMERA)')
    names = {"CAMERA": camera, "bgr": f0.rgb, "depth_m": f0.depth, "t": f0.timestamp}
    exec(compile(first, "README.md", "exec"), names)   # noqa: S102
    names.update(bgr=f1.rgb, depth_m=f1.depth, t=f1.timestamp, index=1, next_bgr=f2.rgb, next_depth_m=f2.depth,
                 next_t=f2.timestamp)
    exec(compile(block, "README.md", "exec"), names)   # noqa: S102
    system = names["system"]
    assert system._lookahead._begun.index == 2       # begun, waiting for its call
    out = system.process(f2.rgb, f2.depth, f2.timestamp, 2)
    assert system._lookahead._begun is None          # taken by it
    system.close()
    assert names["out"].T_wc is not None and out.T_wc is not None


def test_own_source_example_runs_through_the_pipeline(tmp_path):
    """The README's source of one's own (``DatasetDefaults``) runs through ``Pipeline`` as written: every
    frame tracked, the results folder written (and the bookkeeping the run reports is the defaults')."""
    block = next(b for b in readme_python_blocks() if "DatasetDefaults" in b)
    from slam.datasets import SyntheticSequence

    seq = SyntheticSequence(n_frames=8)
    fx, fy, cx, cy = seq.intrinsics
    camera = {"camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy, "camera.distortion": [0.0] * 5,
              "output.report": False}
    block = block.replace('load_config("tum_fr1")', 'load_config("tum_fr1", overrides=CAMERA)')
    block = block.replace('"results/mine"', "OUT")
    names = {"CAMERA": camera, "OUT": tmp_path / "mine", "frames": [(f.rgb, f.depth, f.timestamp) for f in seq]}
    exec(compile(block, "README.md", "exec"), names)   # noqa: S102
    summary = json.loads((tmp_path / "mine" / "summary.json").read_text())
    assert summary["frames"] == summary["tracked"] == 8
    assert summary["dataset"] == "my_frames" and summary["dataset_path"] is None and summary["missing_files"] == []
    poses = [line for line in (tmp_path / "mine" / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(poses) == 8
