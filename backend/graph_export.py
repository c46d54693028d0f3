"""Export the keyframe pose graph to g2o text and to a JSON document.

Two writers share one edge type, :class:`GraphEdge`::

    from backend.graph_export import graph_edges_from_mapper, export_g2o, export_json, mapper_keyframes
    edges = graph_edges_from_mapper(system.mapper)                # odometry + covisibility edges
    ids, stamps, poses = mapper_keyframes(system.mapper)
    export_g2o("graph.g2o", ids, poses, edges)                    # gtsam.readG2o(path, True) reads it
    export_json("graph.json", ids, stamps, poses, edges)

Conventions
-----------
* Poses are 4x4 camera-to-world matrices (``T_wc``), as everywhere in dynslam. The rotation is
  re-orthonormalised before it is written.
* ``GraphEdge.T_ab`` is pose b seen from pose a, ``T_wa^-1 @ T_wb`` (GTSAM's ``BetweenFactorPose3``
  measurement and g2o's ``EDGE_SE3:QUAT`` measurement).
* ``GraphEdge.information`` is a symmetric 6x6 matrix in **GTSAM's tangent order, rotation first**
  ``(rx, ry, rz, tx, ty, tz)``, the order ``FactorGraphBackend.add_relative_pose`` uses for its sigmas.
  g2o stores the information translation first ``(tx, ty, tz, rx, ry, rz)``; :func:`export_g2o`
  permutes it, and ``gtsam.readG2o`` permutes it back, so the noise model GTSAM builds from the file
  has exactly ``GraphEdge.information`` as its information matrix. (Only the order is converted: like
  GTSAM's own reader/writer, no rescaling between g2o's quaternion-vector rotation parametrisation and
  GTSAM's rotation vector is applied.)

g2o format (3-D), one line per vertex / edge::

    VERTEX_SE3:QUAT id x y z qx qy qz qw
    EDGE_SE3:QUAT a b x y z qx qy qz qw  I11 I12 I13 I14 I15 I16 I22 ... I66   (upper triangle, row-major,
                                                                             translation first)

JSON schema (``format`` "dynslam-graph", ``version`` 1)::

    {
      "format": "dynslam-graph",
      "version": 1,
      "pose_convention": "T_wc camera-to-world; edge t/q is T_ab = T_wa^-1 T_wb",
      "information_order": ["rx", "ry", "rz", "tx", "ty", "tz"],
      "keyframes": [{"id": int, "timestamp": float, "t": [x, y, z], "q": [qx, qy, qz, qw]}, ...],
      "edges": [{"a": int, "b": int, "kind": "odometry" | "covisibility" | "loop",
                 "t": [x, y, z], "q": [qx, qy, qz, qw], "information": 6x6 nested list}, ...]
    }

Quaternions are unit, Hamilton, (x, y, z, w) with ``w >= 0``. :func:`load_json` reads the document back.

Both writers are atomic: the text goes to a temporary file in the target's folder, is flushed and
fsynced, then ``os.replace``-d over the target, so a reader never sees a partial file and a failed
export leaves any previous file untouched (and no temporary file behind).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Protocol, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from slam.core.atomic_io import write_text_atomic
from slam.core.config import BackendConfig
from slam.core.geometry import invert, nearest_rotations

if TYPE_CHECKING:
    from backend.map_store import SlamMap

EDGE_KINDS = ("odometry", "covisibility", "loop")
JSON_FORMAT = "dynslam-graph"
JSON_VERSION = 1
INFORMATION_ORDER = ("rx", "ry", "rz", "tx", "ty", "tz")
# g2o index i holds GTSAM index _G2O_FROM_GTSAM[i]: g2o is (t, r), GTSAM is (r, t).
_G2O_FROM_GTSAM = np.array([3, 4, 5, 0, 1, 2])


@dataclass(frozen=True)
class GraphEdge:
    """A relative-pose constraint ``T_ab = T_wa^-1 T_wb`` between keyframes ``a`` and ``b``.

    ``information`` is 6x6, symmetric, rotation block first (see the module docstring).
    """

    a: int
    b: int
    T_ab: np.ndarray
    information: np.ndarray
    kind: str = "odometry"


# --- helpers ------------------------------------------------------------------------------------------
def pose_to_tq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t (3,), q (4,) as x, y, z, w with w >= 0) of a 4x4 pose."""
    t, q = poses_to_tq(np.asarray(T, dtype=float)[None])
    return t[0], q[0]


def poses_to_tq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t (n,3), q (n,4) as x, y, z, w with w >= 0) of n 4x4 poses, in one call: a graph has thousands of
    edges and the per-pose SVD and Rotation calls cost ~0.2 ms each."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    if len(T) == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    q = Rotation.from_matrix(nearest_rotations(T[:, :3, :3])).as_quat()
    q[q[:, 3] < 0] *= -1.0
    return T[:, :3, 3].copy(), q / np.linalg.norm(q, axis=1, keepdims=True)


def tq_to_pose(t, q) -> np.ndarray:
    """4x4 pose from a translation and an (x, y, z, w) quaternion."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def information_from_sigmas(sigma_t: float, sigma_r_deg: float, scale: float = 1.0) -> np.ndarray:
    """Diagonal information (rotation first) of independent sigmas, multiplied by ``scale``."""
    sr = np.radians(sigma_r_deg)
    return scale * np.diag(np.r_[np.full(3, 1.0 / sr ** 2), np.full(3, 1.0 / sigma_t ** 2)])


def information_to_g2o(information: np.ndarray) -> np.ndarray:
    """Rotation-first information -> g2o's translation-first order; one 6x6 matrix or a stack (..., 6, 6)."""
    info = np.asarray(information, dtype=float)
    return info[..., _G2O_FROM_GTSAM, :][..., _G2O_FROM_GTSAM]


def information_from_g2o(information_g2o: np.ndarray) -> np.ndarray:
    """g2o's translation-first information -> rotation-first order (the permutation is its own inverse)."""
    return information_to_g2o(information_g2o)


def _check_graph(kf_ids, poses, edges) -> tuple[list[int], np.ndarray]:
    ids = [int(k) for k in np.asarray(kf_ids).reshape(-1)]
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (K,4,4), got {poses.shape}")
    if len(ids) != len(poses):
        raise ValueError(f"{len(ids)} keyframe ids for {len(poses)} poses")
    if len(set(ids)) != len(ids):
        raise ValueError("keyframe ids must be unique")
    if not np.all(np.isfinite(poses)):
        raise ValueError("poses must be finite")
    known = set(ids)
    if _edges_valid(edges, known):
        return ids, poses
    for e in edges:                   # find the first bad edge and say what is wrong with it
        if e.kind not in EDGE_KINDS:
            raise ValueError(f"edge kind {e.kind!r} is not one of {EDGE_KINDS}")
        if int(e.a) not in known or int(e.b) not in known:
            raise ValueError(f"edge ({e.a}, {e.b}) refers to an unknown keyframe")
        T = np.asarray(e.T_ab, dtype=float)
        info = np.asarray(e.information, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"edge ({e.a}, {e.b}): T_ab must be a finite 4x4 matrix")
        if info.shape != (6, 6) or not np.all(np.isfinite(info)):
            raise ValueError(f"edge ({e.a}, {e.b}): information must be a finite 6x6 matrix")
        if not np.allclose(info, info.T, rtol=1e-9, atol=1e-12 * max(1.0, np.abs(info).max())):
            raise ValueError(f"edge ({e.a}, {e.b}): information must be symmetric")
    return ids, poses


def _edges_valid(edges: Sequence[GraphEdge], known: set[int]) -> bool:
    """Every edge passes ``_check_graph``'s tests, checked on stacked arrays (a run's ~2,000 edges one by one
    took 0.6 s); False sends the caller to the per-edge loop that names the first bad one."""
    if not edges:
        return True
    if any(e.kind not in EDGE_KINDS or int(e.a) not in known or int(e.b) not in known for e in edges):
        return False
    try:
        T = np.array([np.asarray(e.T_ab, dtype=float) for e in edges])
        info = np.array([np.asarray(e.information, dtype=float) for e in edges])
    except ValueError:                # ragged shapes
        return False
    if T.shape[1:] != (4, 4) or info.shape[1:] != (6, 6) or not (np.isfinite(T).all() and np.isfinite(info).all()):
        return False
    # np.allclose(info, info.T, rtol=1e-9, atol=1e-12 * max(1, |info|.max())) for every edge at once
    transposed = np.swapaxes(info, 1, 2)
    atol = 1e-12 * np.maximum(1.0, np.abs(info).max(axis=(1, 2)))
    return bool(np.all(np.abs(info - transposed) <= atol[:, None, None] + 1e-9 * np.abs(transposed)))


# --- writers ------------------------------------------------------------------------------------------
def format_g2o(kf_ids, poses, edges: Sequence[GraphEdge]) -> str:
    """The g2o 3-D text of the graph (what :func:`export_g2o` writes). The edges' information matrices are
    permuted and symmetrised as one stacked array, and every number is written as ``repr`` of a Python float
    (``tolist``), the shortest decimal that reads back to the same bits: with numpy calls per edge, Bonn
    crowd-480's 3,875 edges took 0.10 s at the end of the run, now 0.05."""
    ids, poses = _check_graph(kf_ids, poses, edges)
    lines = []
    t, q = poses_to_tq(poses)
    for k, values in zip(ids, np.hstack([t, q]).tolist()):
        lines.append(" ".join(["VERTEX_SE3:QUAT", str(k), *map(repr, values)]))
    if edges:
        info = information_to_g2o([np.asarray(e.information, dtype=float) for e in edges])
        info = 0.5 * (info + np.swapaxes(info, 1, 2))
        iu = np.triu_indices(6)
        t, q = poses_to_tq([e.T_ab for e in edges])
        for e, values in zip(edges, np.hstack([t, q, info[:, iu[0], iu[1]]]).tolist()):
            lines.append(" ".join(["EDGE_SE3:QUAT", str(int(e.a)), str(int(e.b)), *map(repr, values)]))
    return "\n".join(lines) + "\n"


def export_g2o(path, kf_ids, poses, edges: Sequence[GraphEdge]) -> None:
    """Write the graph as g2o 3-D text (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``), atomically.

    Readable by ``gtsam.readG2o(path, True)``: vertex ``k`` becomes key ``k`` with pose ``poses[i]``,
    each edge a ``BetweenFactorPose3(a, b, T_ab)`` whose Gaussian noise model has information
    ``edge.information``. Edge kinds are not representable in g2o; use :func:`export_json` for them.
    """
    write_text_atomic(path, format_g2o(kf_ids, poses, edges))


def graph_to_json(kf_ids, timestamps, poses, edges: Sequence[GraphEdge]) -> dict:
    """The JSON document (a dict) described in the module docstring."""
    ids, poses = _check_graph(kf_ids, poses, edges)
    stamps = np.asarray(timestamps, dtype=float).reshape(-1)
    if len(stamps) != len(ids):
        raise ValueError(f"{len(stamps)} timestamps for {len(ids)} keyframes")
    keyframes = []
    for k, s, t, q in zip(ids, stamps, *poses_to_tq(poses)):
        keyframes.append({"id": k, "timestamp": float(s), "t": t.tolist(), "q": q.tolist()})
    out_edges = []
    for e, t, q in zip(edges, *poses_to_tq([e.T_ab for e in edges])):
        info = np.asarray(e.information, dtype=float)
        out_edges.append({"a": int(e.a), "b": int(e.b), "kind": e.kind, "t": t.tolist(), "q": q.tolist(),
                          "information": (0.5 * (info + info.T)).tolist()})
    return {"format": JSON_FORMAT, "version": JSON_VERSION,
            "pose_convention": "T_wc camera-to-world; edge t/q is T_ab = T_wa^-1 T_wb",
            "information_order": list(INFORMATION_ORDER), "keyframes": keyframes, "edges": out_edges}


def export_json(path, kf_ids, timestamps, poses, edges: Sequence[GraphEdge]) -> None:
    """Write the graph as a ``dynslam-graph`` v1 JSON document, atomically: one keyframe or edge per line.

    Each line is its own ``json.dumps`` without ``indent``, which Python's C encoder writes; ``indent``
    switches to the pure-Python encoder, 4.5 s for the ~2,000 edges of a 480-frame Bonn run (~0.3 s now)."""
    doc = graph_to_json(kf_ids, timestamps, poses, edges)
    lists = {key: doc.pop(key) for key in ("keyframes", "edges")}
    lines = ["{" + json.dumps(doc)[1:-1] + ","]
    for i, (key, items) in enumerate(lists.items()):
        lines.append(f" {json.dumps(key)}: [")
        lines.append(",\n".join("  " + json.dumps(item) for item in items))
        lines.append(" ]" + ("," if i + 1 < len(lists) else ""))
    lines.append("}")
    write_text_atomic(path, "\n".join(line for line in lines if line) + "\n")


def load_json(path) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[GraphEdge]]:
    """(kf_ids (K,), timestamps (K,), poses (K,4,4), edges) from a :func:`export_json` file."""
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    if doc.get("format") != JSON_FORMAT or doc.get("version") != JSON_VERSION:
        raise ValueError(f"{path}: not a {JSON_FORMAT} v{JSON_VERSION} document")
    kfs = doc["keyframes"]
    ids = np.array([k["id"] for k in kfs], dtype=np.int64)
    stamps = np.array([k["timestamp"] for k in kfs], dtype=float)
    poses = np.array([tq_to_pose(k["t"], k["q"]) for k in kfs]).reshape(-1, 4, 4)
    edges = [GraphEdge(int(e["a"]), int(e["b"]), tq_to_pose(e["t"], e["q"]), np.array(e["information"], float),
                       e["kind"]) for e in doc["edges"]]
    return ids, stamps, poses, edges


# --- from a LocalMapper --------------------------------------------------------------------------------
class MapperView(Protocol):
    """What the export reads of a ``LocalMapper``: its map and the back end's settings (the odometry
    sigmas its factors use)."""

    map: "SlamMap"
    cfg: BackendConfig


def mapper_keyframes(mapper: MapperView) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kf_ids, timestamps, kf_T_wc copy) of a LocalMapper's map."""
    kfs = mapper.map.keyframes
    return (np.array([k.id for k in kfs], dtype=np.int64), np.array([k.timestamp for k in kfs], dtype=float),
            mapper.map.kf_T_wc.copy())


def graph_edges_from_mapper(mapper: MapperView, min_shared: int = 15, odometry_sigma_t: Optional[float] = None,
                            odometry_sigma_r_deg: Optional[float] = None,
                            covisibility_sigma_t: Optional[float] = None,
                            covisibility_sigma_r_deg: Optional[float] = None) -> list[GraphEdge]:
    """Pose-graph edges of a LocalMapper's current estimate.

    * odometry: ``(k-1, k)`` for every keyframe k > 0, information
      :func:`information_from_sigmas` of the odometry sigmas (default: the mapper's
      ``cfg.odometry_sigma_t`` / ``cfg.odometry_sigma_r_deg``, the values its odometry factors use);
    * covisibility: every non-consecutive pair ``(i, j)``, ``i < j``, whose ``map.covisibility`` count
      ``n`` is ``>= min_shared``. Its information is the covisibility sigmas' information (default: the
      odometry sigmas) multiplied by ``n / min_shared``: each shared landmark is treated as an
      independent, equally informative constraint, so information grows linearly with the count and a
      pair right at the threshold weighs as much as an odometry edge. Consecutive pairs are left out:
      their relative pose is the odometry edge's, so a second edge would only double-count it.

    Relative poses are ``T_ab = kf_T_wc[a]^-1 kf_T_wc[b]`` from the map's (optimised) poses.
    """
    sig_t = odometry_sigma_t if odometry_sigma_t is not None else float(mapper.cfg.odometry_sigma_t)
    sig_r = odometry_sigma_r_deg if odometry_sigma_r_deg is not None else float(mapper.cfg.odometry_sigma_r_deg)
    cov_t = covisibility_sigma_t if covisibility_sigma_t is not None else sig_t
    cov_r = covisibility_sigma_r_deg if covisibility_sigma_r_deg is not None else sig_r
    if min(sig_t, sig_r, cov_t, cov_r) <= 0:
        raise ValueError("sigmas must be positive")
    if min_shared < 1:
        raise ValueError("min_shared must be >= 1")
    T_wc = np.asarray(mapper.map.kf_T_wc, dtype=float)
    K = len(T_wc)
    T_cw = invert(T_wc)

    edges: list[GraphEdge] = []
    odo_info = information_from_sigmas(sig_t, sig_r)
    for k in range(1, K):
        edges.append(GraphEdge(k - 1, k, T_cw[k - 1] @ T_wc[k], odo_info.copy(), "odometry"))
    covis = np.asarray(mapper.map.covisibility)[:K, :K]
    ii, jj = np.nonzero(np.triu(covis, k=2) >= min_shared)
    # information_from_sigmas(cov_t, cov_r, n / min_shared) for every pair at once, the same products (a call
    # per pair was 0.05 s of the ~4,000 edges a 480-frame run has)
    scale = covis[ii, jj].astype(np.int64) / min_shared
    cov_info = information_from_sigmas(cov_t, cov_r)[None] * scale[:, None, None]
    T_ij = T_cw[ii] @ T_wc[jj]
    for e, (i, j) in enumerate(zip(ii.tolist(), jj.tolist())):
        edges.append(GraphEdge(i, j, T_ij[e], cov_info[e], "covisibility"))
    return edges


def loop_edges(loops, sigma_t: float, sigma_r_deg: float) -> list[GraphEdge]:
    """Live loop factors as edges (kind "loop"): the measured ``T_match_query``, not the estimate, with
    the loop factor's information. Loops removed as inconsistent are left out."""
    info = information_from_sigmas(sigma_t, sigma_r_deg)
    return [GraphEdge(int(e.match_kf), int(e.query_kf), np.asarray(e.T_match_query, float), info.copy(), "loop")
            for e in loops if e.active]
