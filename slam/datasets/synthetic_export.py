"""A generated sequence written out as a TUM RGB-D folder, so the CLI and ``TumDataset`` read it like a
real recording (tests of the command line, users who want files)."""
from __future__ import annotations

from pathlib import Path
from typing import Union

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from .synthetic import SyntheticSequence
from .tum import CAMERA_FILE


def write_tum_layout(seq: SyntheticSequence, folder: Union[str, Path], depth_scale: float = 5000.0) -> Path:
    """Write ``seq`` as a TUM RGB-D folder (rgb/, depth/, lists, groundtruth.txt, camera.yaml) so the CLI
    and TumDataset can run it like a real recording. Depth is 16-bit PNG, ``depth_scale`` units per metre."""
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines, assoc_lines = [], [], []
    for frame in seq:
        stamp = f"{frame.timestamp:.6f}"
        raw = np.clip(np.round(frame.depth.astype(np.float64) * depth_scale), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(folder / "rgb" / f"{stamp}.png"), frame.rgb)
        cv2.imwrite(str(folder / "depth" / f"{stamp}.png"), raw)
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
        depth_lines.append(f"{stamp} depth/{stamp}.png")
        assoc_lines.append(f"{stamp} rgb/{stamp}.png {stamp} depth/{stamp}.png")
    header = f"# {seq.name} (synthetic, dynslam)\n"
    (folder / "rgb.txt").write_text(header + "# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text(header + "# timestamp filename\n" + "\n".join(depth_lines) + "\n")
    (folder / "associations.txt").write_text("\n".join(assoc_lines) + "\n")
    ts, poses = seq.groundtruth()
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w, TUM's order
    gt = [f"{t:.6f} " + " ".join(f"{x:.9f}" for x in (*p[:3, 3], *q)) for t, p, q in zip(ts, poses, quats)]
    (folder / "groundtruth.txt").write_text(header + "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt) + "\n")
    fx, fy, cx, cy = seq.intrinsics
    camera = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": seq.width, "height": seq.height,
              "depth_scale": float(depth_scale)}
    (folder / CAMERA_FILE).write_text(yaml.safe_dump(camera, sort_keys=False))
    return folder
