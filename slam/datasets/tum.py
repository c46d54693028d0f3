"""TUM RGB-D folder reader (also used for Bonn RGB-D Dynamic, which copies the TUM layout).

A TUM folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines, ``#`` comments), the images
they list, optionally ``associations.txt`` (``t_rgb rgb_path t_depth depth_path``) and ``groundtruth.txt``
(``timestamp tx ty tz qx qy qz qw``, camera-to-world). Colour and depth are recorded by separate sensors, so
pairs are formed by nearest timestamp, exactly like TUM's ``associate.py``.

Real folders are often incomplete (trimmed copies that keep the full lists, a dropped frame), so listed but
absent files are skipped with one summary warning instead of failing; unreadable files are skipped while
iterating, each with its own warning, and recorded in ``dataset.skipped``. Lists out of time order are
sorted and a repeated timestamp is kept once, each with a warning naming the file and the lines.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Iterator, Optional, Union

import cv2
import numpy as np
import yaml

from slam.core.errors import DynslamError

from .base import DatasetDefaults, RGBDFrame, read_ahead

PathLike = Union[str, Path]

CAMERA_FILE = "camera.yaml"
"""Optional intrinsics file beside the lists (written by ``write_tum_layout``); keys fx fy cx cy width
height depth_scale."""

_MAX_NAMES = 10


class DatasetError(DynslamError, ValueError):
    """A folder that cannot be read as a dataset at all (missing root, missing lists, malformed lines)."""


class DatasetWarning(UserWarning):
    """Something in a dataset was skipped; the run goes on with what is there."""


def read_list(path: Path, columns: int) -> list[list[str]]:
    """Rows of a whitespace/comma separated TUM list with ``#`` comments, each cut to ``columns`` fields.

    Raises DatasetError naming the file and line when a row is too short or a timestamp is not a number,
    because a silently dropped line would shift every association after it.
    """
    return [fields for _, fields in read_numbered_list(path, columns)]


def read_numbered_list(path: Path, columns: int) -> list[tuple[int, list[str]]]:
    """``read_list`` with each row's line number (1-based), for messages that point at a line."""
    rows = []
    for lineno, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").replace("\t", " ").split()
        if len(fields) < columns:
            raise DatasetError(f"{path}:{lineno}: expected {columns} fields, got {line!r}")
        try:
            float(fields[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: timestamp is not a number: {line!r}") from None
        rows.append((lineno, fields[:columns]))
    return rows


def time_ordered(path: Path, rows: list[tuple[int, list[str]]]) -> list[list[str]]:
    """The rows sorted by timestamp, a repeated timestamp kept once (its first line); each fix is warned
    about naming the file and the lines.

    Association pairs streams by time and ``frame.index`` is a frame's position in time, so a line out
    of order must not silently become another frame's neighbour, and two frames at one instant would
    give two poses at one timestamp (a trajectory no evaluation can associate unambiguously).
    """
    if not rows:
        return []
    lines = np.array([n for n, _ in rows])
    t = np.array([float(fields[0]) for _, fields in rows])
    latest = np.maximum.accumulate(t)
    back = np.flatnonzero(t[1:] < latest[:-1]) + 1     # earlier than a line above it
    if len(back):
        where = [f"line {lines[i]} ({t[i]:.6f} < {latest[i - 1]:.6f} above it)" for i in back]
        warnings.warn(f"{path}: {len(back)} line(s) out of time order, sorted by timestamp: {_name_list(where)}",
                      DatasetWarning, stacklevel=3)
    order = np.argsort(t, kind="stable")    # stable: among equal stamps the first line comes first
    ts = t[order]
    repeat = np.r_[False, ts[1:] == ts[:-1]]
    if repeat.any():
        first = order[np.maximum.accumulate(np.where(repeat, 0, np.arange(len(ts))))]
        where = [f"line {lines[order[k]]} repeats {ts[k]:.6f} of line {lines[first[k]]}"
                 for k in np.flatnonzero(repeat)]
        warnings.warn(f"{path}: {int(repeat.sum())} repeated timestamp(s) dropped (the first line is kept): "
                      f"{_name_list(where)}", DatasetWarning, stacklevel=3)
    return [rows[i][1] for i in order[~repeat]]


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt: float = 0.02,
              greedy: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one timestamp matching of two streams; returns index arrays (ia, ib) sorted by t_a.

    Candidates are all pairs with |t_a - t_b| <= max_dt (found with searchsorted, as TUM's associate.py
    considers them). ``greedy=True`` then accepts them from the smallest |dt| up exactly like
    associate.py. The default instead keeps the largest number of pairs (ties: smallest total |dt|),
    because greedy loses a frame wherever the streams are offset by about half a frame period: on TUM
    fr1/xyz's first 37 frames (depth ~15 ms before colour, 32 ms period) greedy keeps only 32 pairs.
    Where greedy loses nothing (fr1/rpy, Bonn crowd) both give the same pairs.
    """
    t_a = np.asarray(t_a, dtype=np.float64)
    t_b = np.asarray(t_b, dtype=np.float64)
    order_b = np.argsort(t_b, kind="stable")
    tb = t_b[order_b]
    lo = np.searchsorted(tb, t_a - max_dt, side="left")
    hi = np.searchsorted(tb, t_a + max_dt, side="right")
    counts = np.maximum(hi - lo, 0)
    ia = np.repeat(np.arange(len(t_a)), counts)
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    ib = np.repeat(lo, counts) + (np.arange(len(ia)) - starts)
    dt = np.abs(t_a[ia] - tb[ib])
    keep = dt <= max_dt  # guards against rounding in t_a +- max_dt
    ia, ib, dt = ia[keep], ib[keep], dt[keep]
    chosen = _greedy_pairs(ia, ib, dt) if greedy else _max_pairs(ia, ib, dt, len(tb))
    out_a, out_b = ia[chosen], order_b[ib[chosen]]
    by_time = np.argsort(t_a[out_a], kind="stable")
    return out_a[by_time], out_b[by_time]


def _greedy_pairs(ia: np.ndarray, ib: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """associate.py's rule: accept candidates by increasing |dt| unless either side is taken."""
    used_a, used_b, chosen = set(), set(), []
    for k in np.lexsort((ib, ia, dt)):  # a loop over candidate pairs (about one per frame)
        if ia[k] not in used_a and ib[k] not in used_b:
            used_a.add(ia[k])
            used_b.add(ib[k])
            chosen.append(k)
    return np.asarray(chosen, dtype=np.int64)


def _max_pairs(ia: np.ndarray, ib: np.ndarray, dt: np.ndarray, n_b: int) -> np.ndarray:
    """Most pairs, then least total |dt|, as the longest chain of candidates increasing in both indices.

    Order-preserving matchings suffice: crossing pairs can always be swapped without leaving the window
    or raising the cost. Candidates come sorted by (ia, ib); a Fenwick tree over ib keeps, for every
    prefix of the b stream, the best chain (count, -cost, last candidate) so each step costs O(log n_b).
    """
    tree: list[tuple[int, float, int]] = [(0, 0.0, -1)] * (n_b + 1)
    prev = np.full(len(ia), -1, dtype=np.int64)
    k = 0
    while k < len(ia):
        row_end = k
        while row_end < len(ia) and ia[row_end] == ia[k]:
            row_end += 1
        updates = []
        for c in range(k, row_end):  # query the whole row first: one a-sample is used at most once
            count, neg_cost, last = _prefix_max(tree, int(ib[c]))
            prev[c] = last
            updates.append((int(ib[c]) + 1, (count + 1, neg_cost - float(dt[c]), c)))
        for pos, value in updates:
            while pos <= n_b:
                tree[pos] = max(tree[pos], value)
                pos += pos & -pos
        k = row_end
    chosen, c = [], _prefix_max(tree, n_b)[2]
    while c >= 0:
        chosen.append(c)
        c = int(prev[c])
    return np.asarray(chosen[::-1], dtype=np.int64)


def _prefix_max(tree: list[tuple[int, float, int]], pos: int) -> tuple[int, float, int]:
    """Best value stored at Fenwick positions 1..pos (i.e. b indices < pos)."""
    best = (0, 0.0, -1)
    while pos > 0:
        best = max(best, tree[pos])
        pos -= pos & -pos
    return best


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N,4) quaternions in TUM order (qx, qy, qz, qw) to (N,3,3) rotations; normalises first because
    motion-capture files are printed with 4 digits and are not exactly unit."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


def load_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Parse a TUM trajectory file into (timestamps (N,), camera-to-world poses (N,4,4))."""
    rows = read_list(path, 8)
    if not rows:
        raise DatasetError(f"{path}: no poses (expected 'timestamp tx ty tz qx qy qz qw' lines)")
    data = np.asarray(rows, dtype=np.float64)
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = quat_to_matrix(data[:, 4:8])
    poses[:, :3, 3] = data[:, 1:4]
    return data[:, 0], poses


def guess_camera(root: PathLike) -> Optional[str]:
    """Camera model name from the folder name ("tum_fr1/2/3", "bonn") or None, so the CLI can pick
    intrinsics without asking; TUM and Bonn keep the sensor in their folder names."""
    name = Path(root).name.lower() or Path(root).resolve().name.lower()
    match = re.search(r"freiburg([123])", name)
    if match:
        return f"tum_fr{match.group(1)}"
    if "bonn" in name:
        return "bonn"
    return None


def read_intrinsics(folder: PathLike) -> Optional[dict]:
    """Contents of ``camera.yaml`` in ``folder`` (fx fy cx cy width height depth_scale) or None if absent.

    Real TUM/Bonn folders have no such file (use ``guess_camera``); synthetic folders carry their own.
    """
    path = Path(folder) / CAMERA_FILE
    if not path.is_file():
        return None
    data = yaml.safe_load(path.read_text())
    missing = {"fx", "fy", "cx", "cy"} - set(data or {})
    if missing:
        raise DatasetError(f"{path}: missing keys {sorted(missing)}")
    return data


def _name_list(names: list[str]) -> str:
    shown = ", ".join(names[:_MAX_NAMES])
    more = len(names) - _MAX_NAMES
    return shown + (f" and {more} more" if more > 0 else "")


class TumDataset(DatasetDefaults):
    """Lazily read RGB-D frames of a TUM-layout folder; see the module docstring for the layout.

    ``frame.index`` is the frame's position in ``timestamps`` (kept when a corrupt frame is skipped), so
    ``dataset.timestamps[frame.index] == frame.timestamp``.
    """

    reopenable = True    # map export reads keyframe images back from the folder

    def __init__(self, root: PathLike, depth_scale: float = 5000.0, max_dt: float = 0.02) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"dataset folder {self.root} does not exist (expected a TUM RGB-D folder "
                               "with rgb.txt, depth.txt, rgb/ and depth/)")
        if not (self.root / "rgb.txt").is_file() and not (self.root / "associations.txt").is_file():
            raise DatasetError(f"{self.root} has no rgb.txt (expected a TUM RGB-D folder with rgb.txt, "
                               "depth.txt or associations.txt, rgb/ and depth/)")
        self.name = self.root.resolve().name
        self.depth_scale = float(depth_scale)
        self.max_dt = float(max_dt)
        self.intrinsics = read_intrinsics(self.root)
        self.skipped: list[tuple[Path, str]] = []
        self.missing: list[Path] = []
        t_rgb, rgb, t_depth, depth = self._pairs()
        self._drop_missing(t_rgb, rgb, t_depth, depth)

    def _pairs(self) -> tuple[np.ndarray, list[str], np.ndarray, list[str]]:
        """All (rgb, depth) pairs: from associations.txt when present, else by timestamp association.

        Also records every listed file in ``self._listed`` so the missing-file warning can count them.
        """
        assoc = self.root / "associations.txt"
        if assoc.is_file():
            rows = time_ordered(assoc, read_numbered_list(assoc, 4))
            self.association_source = "associations.txt"
            self.unmatched_rgb = 0
            self._listed = ([r[1] for r in rows], [r[3] for r in rows])
            return (np.array([float(r[0]) for r in rows]), [r[1] for r in rows],
                    np.array([float(r[2]) for r in rows]), [r[3] for r in rows])
        depth_txt = self.root / "depth.txt"
        if not depth_txt.is_file():
            raise DatasetError(f"{self.root} has rgb.txt but no depth.txt (expected both, or associations.txt)")
        rgb_txt = self.root / "rgb.txt"
        rgb_rows = time_ordered(rgb_txt, read_numbered_list(rgb_txt, 2))
        depth_rows = time_ordered(depth_txt, read_numbered_list(depth_txt, 2))
        self._listed = ([r[1] for r in rgb_rows], [r[1] for r in depth_rows])
        t_rgb = np.array([float(r[0]) for r in rgb_rows])
        t_depth = np.array([float(r[0]) for r in depth_rows])
        ia, ib = associate(t_rgb, t_depth, self.max_dt)
        self.association_source = f"nearest timestamp within {self.max_dt * 1000:g} ms"
        self.unmatched_rgb = len(t_rgb) - len(ia)
        return (t_rgb[ia], [rgb_rows[i][1] for i in ia], t_depth[ib], [depth_rows[i][1] for i in ib])

    def _drop_missing(self, t_rgb: np.ndarray, rgb: list[str], t_depth: np.ndarray, depth: list[str]) -> None:
        """Keep only pairs whose files both exist; warn once, counting and naming the absent files."""
        listed_rgb, listed_depth = self._listed
        exists = {p: (self.root / p).is_file() for p in set(listed_rgb) | set(listed_depth)}
        keep = np.array([exists[a] and exists[b] for a, b in zip(rgb, depth)], dtype=bool)
        self._t_rgb, self._t_depth = t_rgb[keep], t_depth[keep]
        self._t_rgb.flags.writeable = False
        self._rgb = [self.root / p for p, k in zip(rgb, keep) if k]
        self._depth = [self.root / p for p, k in zip(depth, keep) if k]
        missing_rgb = [p for p in listed_rgb if not exists[p]]
        missing_depth = [p for p in listed_depth if not exists[p]]
        self.missing = [self.root / p for p in missing_rgb + missing_depth]
        if self.missing:
            warnings.warn(
                f"{self.name}: {len(missing_rgb)} of {len(listed_rgb)} listed rgb files and "
                f"{len(missing_depth)} of {len(listed_depth)} listed depth files are missing, "
                f"skipping {int((~keep).sum())} of {len(keep)} frames: "
                f"{_name_list(missing_rgb + missing_depth)}", DatasetWarning, stacklevel=3)
        if not keep.any():
            raise DatasetError(f"{self.root}: none of the {len(keep)} associated rgb/depth pairs has both "
                               f"files present (association: {self.association_source})")

    @property
    def timestamps(self) -> np.ndarray:
        """Colour timestamps of the frames this dataset yields (read-only), in seconds."""
        return self._t_rgb

    def __len__(self) -> int:
        return len(self._rgb)

    def __iter__(self) -> Iterator[RGBDFrame]:
        # Decoding two PNGs costs ~6 ms a frame; OpenCV releases the GIL while it decodes, so a reader
        # thread loads the next frames while this one is tracked (base.read_ahead).
        for i, (frame, reason) in enumerate(read_ahead(self._load, len(self))):
            if frame is not None:
                yield frame
            else:
                self._skip(i, reason)

    def _skip(self, i: int, reason: str) -> None:
        path = self._rgb[i] if reason.startswith("colour") else self._depth[i]
        if (path, reason) not in self.skipped:
            self.skipped.append((path, reason))
        warnings.warn(f"{self.name}: skipping frame {i} ({path}): {reason}", DatasetWarning, stacklevel=3)

    def __getitem__(self, i: int) -> RGBDFrame:
        """Random access for re-reading a frame; raises DatasetError if its files are unreadable."""
        frame, reason = self._load(range(len(self))[i])
        if frame is None:
            raise DatasetError(f"{self.name}: frame {i}: {reason}")
        return frame

    def _load(self, i: int) -> tuple[Optional[RGBDFrame], str]:
        """Read one pair; returns (None, reason) instead of raising so iteration can skip it."""
        rgb = _imread(self._rgb[i], cv2.IMREAD_COLOR)
        if rgb is None or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            return None, "colour image unreadable or not 8-bit 3-channel"
        raw = _imread(self._depth[i], cv2.IMREAD_UNCHANGED)
        if raw is None or raw.ndim != 2 or raw.dtype != np.uint16:
            desc = "unreadable" if raw is None else f"{raw.dtype} with shape {raw.shape}"
            return None, f"depth image is not a 16-bit single-channel PNG ({desc})"
        if raw.shape != rgb.shape[:2]:
            return None, (f"depth image is {raw.shape[1]}x{raw.shape[0]} but its colour image {self._rgb[i].name} is "
                          f"{rgb.shape[1]}x{rgb.shape[0]} (they must be registered pixel to pixel)")
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        frame = RGBDFrame(index=i, timestamp=float(self._t_rgb[i]), rgb=rgb, depth=depth,
                          rgb_path=self._rgb[i], depth_path=self._depth[i])
        return frame, ""

    def groundtruth(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(timestamps, (N,4,4) camera-to-world) from groundtruth.txt, or None if the folder has none.

        Not associated to frames here: the mocap runs at a higher rate and evaluation matches it itself.
        """
        path = self.root / "groundtruth.txt"
        return load_groundtruth(path) if path.is_file() else None

    def __repr__(self) -> str:
        return f"TumDataset({str(self.root)!r}, frames={len(self)}, association={self.association_source!r})"


def _imread(path: Path, flags: int) -> Optional[np.ndarray]:
    """cv2.imread that reports a corrupt file as None rather than raising (some codecs raise)."""
    try:
        return cv2.imread(str(path), flags)
    except cv2.error:
        return None
