"""What a run leaves in its results folder so ``dynslam export`` can rebuild maps without re-running SLAM.

- ``masks/<frame index:06d>.png``  per keyframe, the front end's dynamic probability (8-bit, 255 = 1.0),
                                   written only with dynamic handling on: moving surfaces (people
                                   standing still are left out, frontend/dynamic/region_motion.py, and
                                   so are flagged pixels that earlier frames show did not move,
                                   frontend/dynamic/free_space.py);
- ``masks/<frame index:06d>_still.png``  per keyframe: the pixels flagged but not moving (people standing
                                   still, surfaces the free-space test found unmoved; 255), which dense
                                   maps leave out like the moving ones;
- ``keyframes/``                   when the frames cannot be re-read later (generated sequences, bags,
                                   readers without random access): per keyframe ``color/<index>.png``
                                   (BGR), ``depth/<index>.png`` (16-bit, millimetres) and ``frames.txt``
                                   (frame index and timestamp per line);
- ``map.npz``                      the final map (``backend.map_io``), unless ``export.save_map`` is off;
- ``map_sparse.ply``               the landmarks as a coloured point cloud, unless ``export.sparse_ply`` is off.

Every file is written atomically (temporary file in the same folder, then ``os.replace``). The per-keyframe
files go through one background thread (``dynslam-writer``): each atomic write fsyncs the file and its folder
(~15 ms a mask on this machine, 1.3 s of a 400-frame run), which the tracking thread no longer waits for. One
thread keeps their order (a revision rewrites a mask written before); ``drain`` waits for them and raises a
failed write's error, ``close`` drains. The maps at the end of a run go the same way (``finish``).
"""
from __future__ import annotations

import logging
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Optional

import cv2
import numba
import numpy as np

from slam.core.atomic_io import write_atomic, write_text_atomic
from slam.datasets.base import RGBDDataset
from slam.run.sparse_map import write_sparse_ply

log = logging.getLogger("dynslam")

MASK_DIR = "masks"
STILL_SUFFIX = "_still"      # masks/<index>_still.png: flagged, not moving (255), never fused into maps
KEYFRAME_DIR = "keyframes"
KEYFRAME_LIST = "frames.txt"
KEYFRAME_DEPTH_SCALE = 1000.0   # keyframes/depth PNGs hold millimetres
MAP_FILE = "map.npz"
SPARSE_PLY = "map_sparse.ply"


def write_png_atomic(path: Path, image: np.ndarray) -> None:
    """Encode ``image`` as PNG in memory and write it atomically; raises naming the path on failure."""
    ok, buffer = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"{path}: could not encode a {image.dtype} {image.shape} image as PNG")
    write_atomic(path, lambda handle: handle.write(buffer.tobytes()))


def mask_to_png(mask: np.ndarray) -> np.ndarray:
    """Dynamic probability in [0, 1] (HxW float) to 8-bit, 255 = certainly dynamic: NaN 0, clipped to [0, 1],
    times 255 and rounded half to even in the mask's own precision (what ``np.round(np.clip(np.nan_to_num(mask),
    0, 1) * 255.0)`` gives, NEP 50), in one compiled pass (~0.6 ms a frame of whole-array steps on Bonn crowd,
    where keyframe masks are written again as later frames revise them)."""
    mask = np.asarray(mask)
    if mask.dtype not in (np.float32, np.float64):
        mask = mask.astype(np.float64)
    return _to_png(mask.reshape(-1), mask.dtype.type(255.0)).reshape(mask.shape)


@numba.njit(nogil=True, cache=True)
def _to_png(mask, scale):
    out = np.empty(mask.shape[0], np.uint8)
    for i in range(mask.shape[0]):
        v = mask[i]
        if v > 1:                  # +inf too
            v = scale
        elif v > 0:
            v = v * scale
        else:                      # NaN, -inf and below 0
            v = scale * 0
        out[i] = np.uint8(np.rint(v))
    return out


def depth_to_millimetres(depth: np.ndarray) -> np.ndarray:
    """Depth in metres (0 = invalid) to 16-bit millimetres, clipped to 65.535 m."""
    mm = np.round(np.nan_to_num(depth.astype(np.float64), nan=0.0) * KEYFRAME_DEPTH_SCALE)
    return np.clip(mm, 0, 65535).astype(np.uint16)


def needs_keyframe_copies(dataset: RGBDDataset) -> bool:
    """Whether export could not read the keyframes back from the dataset (no folder it can reopen)."""
    return dataset.root is None or not dataset.reopenable


class RunArtifacts:
    """Writes the export inputs during a run (keyframe masks and images) and the maps at its end."""

    def __init__(self, output_dir: Path, config, copy_keyframes: bool):
        self.output_dir = Path(output_dir)
        self.config = config
        self.copy_keyframes = copy_keyframes     # keep keyframe images: the dataset cannot give them back
        self._keyframe_rows: list[str] = []
        self._writer: Optional[ThreadPoolExecutor] = None    # started at the first file
        self._pending: deque[Future] = deque()

    def on_frame(self, out, frame, system) -> None:
        """Pipeline hook, once per processed frame: keyframes leave their mask (and images); earlier
        keyframes whose masks the front end revised (a person there turned out to stand still) are
        written again."""
        for revised in system.revised_keyframe_masks:
            self._write_masks(revised.frame_index, revised.mask, revised.still_people)
        if not out.is_keyframe:
            return
        # Every keyframe has a mask (all zeros with dynamic handling off), so export never guesses.
        mask = system.last_dynamic_mask
        mask = np.zeros(frame.depth.shape, np.float32) if mask is None else mask
        self._write_masks(frame.index, mask, system.last_still_people_mask)
        if self.copy_keyframes:
            self._write_keyframe_images(frame)

    def _write_masks(self, index: int, mask: np.ndarray, still: Optional[np.ndarray]) -> None:
        # The images are converted here, on the caller's thread: the writer gets arrays nobody changes later.
        self._submit(_write_mask_files, self.output_dir / MASK_DIR, index, mask_to_png(mask),
                     None if still is None or not still.any() else still.astype(np.uint8) * 255)

    def _write_keyframe_images(self, frame) -> None:
        folder = self.output_dir / KEYFRAME_DIR
        self._keyframe_rows.append(f"{frame.index} {frame.timestamp:.6f}")
        header = "# frame_index timestamp (color/<index:06d>.png BGR, depth/<index:06d>.png uint16 mm)\n"
        self._submit(_write_keyframe_files, folder, frame.index, frame.rgb.copy(), depth_to_millimetres(frame.depth),
                     header + "\n".join(self._keyframe_rows) + "\n")

    def _submit(self, write: Callable[..., None], *args) -> None:
        """Hand a write to the writer thread; first raise the error of a write that already failed."""
        while self._pending and self._pending[0].done():
            self._pending.popleft().result()
        if self._writer is None:
            self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dynslam-writer")
        self._pending.append(self._writer.submit(write, *args))

    def drain(self) -> None:
        """Wait until every file handed to the writer is written; raise the first failed write's error
        (an OSError naming the file) after waiting for the rest."""
        error: Optional[BaseException] = None
        while self._pending:
            try:
                self._pending.popleft().result()
            except Exception as exc:   # noqa: BLE001 - kept and raised once the others are written
                error = error or exc
        if error is not None:
            raise error

    def close(self, raise_errors: bool = True) -> None:
        """Drain and stop the writer thread (every exit path of a run; a second call does nothing)."""
        try:
            if raise_errors:
                self.drain()
            else:
                try:
                    self.drain()
                except Exception as exc:   # noqa: BLE001 - the run is failing already: say it, keep its error
                    log.error("%s", exc)
        finally:
            if self._writer is not None:
                self._writer.shutdown(wait=True)
                self._writer = None

    def finish(self, system) -> None:
        """At the end of a run (``system`` closed): the keyframe masks the run's end revises, map.npz and
        map_sparse.ply (per ``config.export``), all on the writer thread; ``close`` waits for them. Nothing
        changes the map any more, and what the pipeline does meanwhile (the graph files, the evaluation, the
        report) only reads it, so the map's compression (~0.4 s of zlib, which releases the GIL) overlaps
        with them instead of preceding them."""
        for revised in system.finish_keyframe_masks():
            self._write_masks(revised.frame_index, revised.mask, revised.still_people)
        if system.localization_only or system.mapper.map.num_keyframes == 0:
            return   # a localisation run builds no map of its own
        export = self.config.export
        if export.save_map:
            self._submit(system.save_map, self.output_dir / MAP_FILE)
        if export.sparse_ply:
            self._submit(write_sparse_ply, self.output_dir / SPARSE_PLY, system.mapper.map)


def _write_mask_files(folder: Path, index: int, mask_png: np.ndarray, still_png: Optional[np.ndarray]) -> None:
    write_png_atomic(folder / f"{index:06d}.png", mask_png)
    still_path = folder / f"{index:06d}{STILL_SUFFIX}.png"
    if still_png is not None:
        write_png_atomic(still_path, still_png)
    elif still_path.exists():          # a revision found the pixels moving after all
        still_path.unlink()


def _write_keyframe_files(folder: Path, index: int, rgb: np.ndarray, depth_mm: np.ndarray, frame_list: str) -> None:
    write_png_atomic(folder / "color" / f"{index:06d}.png", rgb)
    write_png_atomic(folder / "depth" / f"{index:06d}.png", depth_mm)
    write_text_atomic(folder / KEYFRAME_LIST, frame_list)


def read_keyframe_list(folder: Path) -> Optional[dict[float, int]]:
    """{timestamp: frame index} from ``keyframes/frames.txt``, or None when the folder has none."""
    path = Path(folder) / KEYFRAME_LIST
    if not path.is_file():
        return None
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    try:
        return {float(t): int(i) for i, t in rows}
    except ValueError as exc:
        raise ValueError(f"{path}: expected 'frame_index timestamp' per line ({exc})") from None
