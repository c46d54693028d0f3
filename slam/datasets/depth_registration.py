"""Depth from its own camera re-projected into the colour camera's pixel grid ("registration").

A RealSense depth image is measured by the stereo module, a few centimetres beside the colour camera and
with other intrinsics; SLAM needs the depth of the surface each *colour* pixel sees. Each depth pixel is
back-projected with the depth intrinsics, moved into the colour frame by the extrinsic, and projected with
the colour intrinsics (their distortion included: the colour image stays as recorded, the tracker
undistorts keypoints itself).

Like librealsense's ``rs2::align``, a depth pixel is splatted over its whole footprint rather than one
point: its two corners (u-0.5, v-0.5) and (u+0.5, v+0.5), projected at the pixel's depth, bound the colour
pixel centres it covers. Neighbouring footprints tile the colour image, so a colour camera of higher
resolution than the depth camera gets no pinholes. Where footprints overlap (a near edge occluding a far
surface after the shift of viewpoint) the nearest depth wins (a z-buffer); colour pixels that nothing
covers, e.g. the strip of background the depth camera cannot see behind a near edge, stay 0 (no depth).
Unlike ``rs2::align`` the stored depth is the point's z in the *colour* frame, not the depth camera's.
Everything is vectorised: a per-pixel ray table is built once, each frame is a few array operations.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

MAX_FOOTPRINT_PX = 8
"""Largest footprint of one depth pixel in colour pixels per axis; beyond it the depth camera is far
coarser than the colour one and the splat would cost more than it is worth (an error says so)."""


@dataclass(frozen=True)
class StreamIntrinsics:
    """Pinhole intrinsics of one image stream; ``distortion`` in OpenCV's order k1 k2 p1 p2 k3."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = field(default=(0.0,) * 5)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        return any(abs(d) > 0.0 for d in self.distortion)

    def same_as(self, other: "StreamIntrinsics", tol_px: float = 1e-3) -> bool:
        """Whether both streams share one pixel grid (sizes, intrinsics and distortion agree)."""
        a = np.r_[self.fx, self.fy, self.cx, self.cy, self.distortion]
        b = np.r_[other.fx, other.fy, other.cx, other.cy, other.distortion]
        return (self.width, self.height) == (other.width, other.height) and bool(np.allclose(a, b, atol=tol_px))


def is_identity(T: np.ndarray, tol_m: float = 1e-6, tol_rad: float = 1e-6) -> bool:
    """Whether a 4x4 rigid transform moves nothing (within ``tol_m`` metres and ``tol_rad`` radians)."""
    return bool(np.abs(T[:3, 3]).max() <= tol_m and np.abs(T[:3, :3] - np.eye(3)).max() <= tol_rad)


class DepthRegistration:
    """Registers depth images of ``depth`` intrinsics to the ``colour`` pixel grid.

    ``T_colour_depth`` (4x4) maps a point in depth-camera coordinates to colour-camera coordinates.
    """

    def __init__(self, depth: StreamIntrinsics, colour: StreamIntrinsics, T_colour_depth: np.ndarray) -> None:
        self.depth, self.colour = depth, colour
        T = np.asarray(T_colour_depth, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_colour_depth must be a finite 4x4 matrix, got shape {T.shape}")
        self.R, self.t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
        u, v = np.meshgrid(np.arange(depth.width, dtype=np.float64), np.arange(depth.height, dtype=np.float64))
        # Normalised rays (x/z, y/z) through each depth pixel's top-left corner, centre and bottom-right corner.
        self._rays = [self._normalised(np.stack([u.ravel() + d, v.ravel() + d], axis=1)) for d in (-0.5, 0.0, 0.5)]

    def _normalised(self, uv: np.ndarray) -> np.ndarray:
        """(2, N) float32 ideal normalised coordinates of depth pixel positions (undistorted if need be)."""
        d = self.depth
        if d.distorted:
            uv = cv2.undistortPoints(uv.reshape(-1, 1, 2), d.K, np.asarray(d.distortion, np.float64)).reshape(-1, 2)
            return uv.T.astype(np.float32)
        return np.stack([(uv[:, 0] - d.cx) / d.fx, (uv[:, 1] - d.cy) / d.fy]).astype(np.float32)

    def _to_colour(self, rays: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Colour-frame (x, y, z) of depth pixels at depth ``z`` along ``rays``; elementwise, no BLAS."""
        R, t = self.R, self.t
        x, y = rays[0] * z, rays[1] * z
        return tuple(R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i] for i in range(3))

    def _project(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour pixel coordinates of colour-frame points (z > 0), with the colour camera's distortion
        (OpenCV's k1 k2 p1 p2 k3 model written out: cv2.projectPoints is ten times slower here)."""
        c = self.colour
        xn, yn = x / z, y / z
        if c.distorted:
            k1, k2, p1, p2, k3 = (np.float32(v) for v in (tuple(c.distortion) + (0.0,) * 5)[:5])
            r2 = xn * xn + yn * yn
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xy = xn * yn
            xn, yn = (xn * radial + 2 * p1 * xy + p2 * (r2 + 2 * xn * xn),
                      yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xy)
        return np.float32(c.fx) * xn + np.float32(c.cx), np.float32(c.fy) * yn + np.float32(c.cy)

    def __call__(self, depth_m: np.ndarray) -> np.ndarray:
        """Depth in metres (HxW of the depth camera, 0 = none) -> float32 depth on the colour grid (0 = none)."""
        d, c = self.depth, self.colour
        if depth_m.shape != (d.height, d.width):
            raise ValueError(f"depth image is {depth_m.shape[1]}x{depth_m.shape[0]}, the depth camera is "
                             f"{d.width}x{d.height}")
        z = depth_m.ravel().astype(np.float32, copy=False)
        keep = np.flatnonzero((z > 0) & np.isfinite(z))
        z = z[keep]
        corners = []
        for rays in (self._rays[0], self._rays[2]):
            x, y, zc = self._to_colour(rays[:, keep], z)
            corners.append((x, y, zc))
        z_colour = self._to_colour(self._rays[1][:, keep], z)[2]   # stored depth: the pixel centre's z
        ahead = (corners[0][2] > 0) & (corners[1][2] > 0) & (z_colour > 0)
        (u0, v0), (u1, v1) = (self._project(*(a[ahead] for a in corner)) for corner in corners)
        z_colour = z_colour[ahead]
        # Colour pixel centres (integers) inside the footprint [min, max) of the two projected corners.
        c0 = np.ceil(np.minimum(u0, u1)).astype(np.int32)
        r0 = np.ceil(np.minimum(v0, v1)).astype(np.int32)
        nc = np.ceil(np.maximum(u0, u1)).astype(np.int32) - c0
        nr = np.ceil(np.maximum(v0, v1)).astype(np.int32) - r0
        out = np.full(c.height * c.width, np.inf, np.float32)
        span_c, span_r = (int(n.max()) if n.size else 0 for n in (nc, nr))
        if max(span_c, span_r) > MAX_FOOTPRINT_PX:
            raise ValueError(f"a depth pixel covers up to {max(span_c, span_r)} colour pixels per axis (more than "
                             f"{MAX_FOOTPRINT_PX}): the depth and colour intrinsics do not fit together")
        for dr in range(span_r):
            for dc in range(span_c):
                col, row = c0 + dc, r0 + dr
                hit = (dc < nc) & (dr < nr) & (col >= 0) & (col < c.width) & (row >= 0) & (row < c.height)
                flat = row[hit].astype(np.int64) * c.width + col[hit]
                np.minimum.at(out, flat, z_colour[hit])   # the z-buffer: the nearest surface wins
        out[np.isinf(out)] = 0.0
        return out.reshape(c.height, c.width)
