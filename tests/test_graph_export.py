"""Pose-graph export: g2o read back by gtsam.readG2o, JSON round trip, atomic writes, System end to end."""
from __future__ import annotations

import json
import os

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from backend.graph_export import (GraphEdge, export_g2o, export_json, graph_edges_from_mapper, load_json,
                                  mapper_keyframes)
from slam.core.config import BackendConfig
from slam.core.geometry import invert


def random_pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(scale=1.0, size=3)).as_matrix()
    T[:3, 3] = rng.normal(scale=3.0, size=3)
    return T


def random_information(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return A @ A.T + 6.0 * np.eye(6)   # dense, symmetric positive definite


@pytest.fixture
def graph():
    """Seeded random keyframes (non-contiguous ids) and odometry / covisibility / loop edges."""
    rng = np.random.default_rng(42)
    ids = np.array([0, 1, 2, 3, 5, 8, 13])
    poses = np.array([random_pose(rng) for _ in ids])
    stamps = np.linspace(0.0, 3.0, len(ids))
    pairs = [(0, 1, "odometry"), (1, 2, "odometry"), (2, 3, "odometry"), (3, 5, "odometry"),
             (5, 8, "odometry"), (8, 13, "odometry"), (0, 3, "covisibility"), (2, 8, "covisibility"),
             (13, 0, "loop")]
    index = {k: i for i, k in enumerate(ids)}
    edges = []
    for a, b, kind in pairs:
        T_ab = invert(poses[index[a]]) @ poses[index[b]]
        if kind == "loop":                                   # a measurement that is not the estimate
            T_ab = T_ab @ random_pose(np.random.default_rng(7))
        edges.append(GraphEdge(a, b, T_ab, random_information(rng), kind))
    return ids, stamps, poses, edges


def pose_matrix(p: gtsam.Pose3) -> np.ndarray:
    return np.asarray(p.matrix())


# --- g2o -------------------------------------------------------------------------------------------
def test_g2o_reads_back_in_gtsam(graph, tmp_path):
    ids, _, poses, edges = graph
    path = tmp_path / "graph.g2o"
    export_g2o(path, ids, poses, edges)
    factors, values = gtsam.readG2o(str(path), True)

    assert values.size() == len(ids)
    for k, T in zip(ids, poses):
        np.testing.assert_allclose(pose_matrix(values.atPose3(int(k))), T, atol=1e-9)

    between = [factors.at(i) for i in range(factors.size())]
    assert len(between) == len(edges)
    for f, e in zip(between, edges):
        assert isinstance(f, gtsam.BetweenFactorPose3)
        assert list(f.keys()) == [e.a, e.b]
        np.testing.assert_allclose(pose_matrix(f.measured()), e.T_ab, atol=1e-9)
        info = np.asarray(f.noiseModel().information())
        np.testing.assert_allclose(info, e.information, rtol=1e-6, atol=1e-6)


def test_g2o_information_order_is_translation_first(tmp_path):
    """A rotation-only information entry lands in g2o's rotation block (columns 4-6 of the triangle)."""
    info = np.diag([10.0, 20.0, 30.0, 1.0, 2.0, 3.0])          # rotation first (GTSAM order)
    export_g2o(tmp_path / "g.g2o", [0, 1], np.array([np.eye(4), np.eye(4)]),
               [GraphEdge(0, 1, np.eye(4), info)])
    edge = (tmp_path / "g.g2o").read_text().splitlines()[2].split()
    assert edge[0] == "EDGE_SE3:QUAT"
    tri = np.array(edge[10:], float)
    assert len(tri) == 21
    assert tri[[0, 6, 11, 15, 18, 20]].tolist() == [1.0, 2.0, 3.0, 10.0, 20.0, 30.0]


def test_g2o_rejects_bad_input(graph, tmp_path):
    ids, _, poses, edges = graph
    with pytest.raises(ValueError):
        export_g2o(tmp_path / "g.g2o", ids, poses, edges + [GraphEdge(0, 99, np.eye(4), np.eye(6))])
    with pytest.raises(ValueError):
        export_g2o(tmp_path / "g.g2o", ids, poses, [GraphEdge(0, 1, np.eye(4), np.triu(np.ones((6, 6))))])
    with pytest.raises(ValueError):
        export_g2o(tmp_path / "g.g2o", ids, poses, [GraphEdge(0, 1, np.eye(4), np.eye(6), "imu")])
    assert not (tmp_path / "g.g2o").exists()


# --- JSON ------------------------------------------------------------------------------------------
def test_json_round_trip(graph, tmp_path):
    ids, stamps, poses, edges = graph
    path = tmp_path / "graph.json"
    export_json(path, ids, stamps, poses, edges)

    doc = json.loads(path.read_text())
    assert doc["format"] == "dynslam-graph" and doc["version"] == 1
    assert set(doc["keyframes"][0]) == {"id", "timestamp", "t", "q"}
    assert set(doc["edges"][0]) == {"a", "b", "kind", "t", "q", "information"}
    assert [e["kind"] for e in doc["edges"]] == [e.kind for e in edges]
    # one keyframe or edge per line: a person (or grep) reads it, and each line is JSON of its own
    lines = path.read_text().splitlines()
    item_lines = [json.loads(line.strip().rstrip(",")) for line in lines if line.startswith("  {")]
    assert item_lines == doc["keyframes"] + doc["edges"]

    ids2, stamps2, poses2, edges2 = load_json(path)
    np.testing.assert_array_equal(ids2, ids)
    np.testing.assert_allclose(stamps2, stamps)
    np.testing.assert_allclose(poses2, poses, atol=1e-12)
    assert len(edges2) == len(edges)
    for e2, e in zip(edges2, edges):
        assert (e2.a, e2.b, e2.kind) == (e.a, e.b, e.kind)
        np.testing.assert_allclose(e2.T_ab, e.T_ab, atol=1e-12)
        np.testing.assert_allclose(e2.information, e.information, rtol=1e-12)


# --- atomic writes ---------------------------------------------------------------------------------
def test_atomic_write_leaves_no_temp_files(graph, tmp_path):
    ids, stamps, poses, edges = graph
    for _ in range(2):                                        # second round overwrites in place
        export_g2o(tmp_path / "graph.g2o", ids, poses, edges)
        export_json(tmp_path / "graph.json", ids, stamps, poses, edges)
    assert sorted(os.listdir(tmp_path)) == ["graph.g2o", "graph.json"]


def test_failed_write_keeps_previous_file(graph, tmp_path, monkeypatch):
    ids, stamps, poses, edges = graph
    path = tmp_path / "graph.g2o"
    export_g2o(path, ids, poses, edges)
    before = path.read_bytes()

    def failing_replace(src, dst):
        raise OSError("disk gone")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError):
        export_g2o(path, ids[:2], poses[:2], edges[:1])
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["graph.g2o"]


# --- from a mapper ---------------------------------------------------------------------------------
class _FakeMap:
    def __init__(self, poses, covis):
        self.kf_T_wc = poses
        self.covisibility = covis


class _FakeMapper:
    def __init__(self, poses, covis):
        self.map = _FakeMap(poses, covis)
        self.cfg = BackendConfig()


def test_graph_edges_from_mapper_weights():
    rng = np.random.default_rng(3)
    poses = np.array([random_pose(rng) for _ in range(5)])
    covis = np.zeros((5, 5), np.int32)
    covis[0, 1] = covis[1, 0] = 100   # consecutive: odometry only
    covis[0, 2] = covis[2, 0] = 30
    covis[1, 4] = covis[4, 1] = 14    # below the threshold
    covis[2, 4] = covis[4, 2] = 15
    edges = graph_edges_from_mapper(_FakeMapper(poses, covis), min_shared=15, odometry_sigma_t=0.1,
                                    odometry_sigma_r_deg=1.0)
    odo = [e for e in edges if e.kind == "odometry"]
    cov = [e for e in edges if e.kind == "covisibility"]
    assert [(e.a, e.b) for e in odo] == [(0, 1), (1, 2), (2, 3), (3, 4)]
    assert [(e.a, e.b) for e in cov] == [(0, 2), (2, 4)]
    base = np.diag([1 / np.radians(1.0) ** 2] * 3 + [100.0] * 3)
    np.testing.assert_allclose(odo[0].information, base)
    np.testing.assert_allclose(cov[0].information, 2.0 * base)
    np.testing.assert_allclose(cov[1].information, base)
    for e in edges:
        np.testing.assert_allclose(e.T_ab, invert(poses[e.a]) @ poses[e.b], atol=1e-12)


@pytest.mark.slow   # a whole run: kept out of the fast tier (< 2 min)
def test_system_graph_exports_to_gtsam(tmp_path):
    from slam.core.config import load_config
    from slam.datasets import SyntheticSequence
    from slam.runtime.system import System

    config = load_config()
    system = System(config)
    for frame in SyntheticSequence(n_frames=30):
        system.process(frame.rgb, frame.depth, frame.timestamp)
    mapper = system.mapper
    K = mapper.map.num_keyframes
    assert K >= 2

    edges = graph_edges_from_mapper(mapper, min_shared=config.backend.covisibility_min_shared)
    assert sum(e.kind == "odometry" for e in edges) == K - 1
    assert any(e.kind == "covisibility" for e in edges)
    ids, stamps, poses = mapper_keyframes(mapper)
    path = tmp_path / "system.g2o"
    export_g2o(path, ids, poses, edges)
    export_json(tmp_path / "system.json", ids, stamps, poses, edges)

    factors, values = gtsam.readG2o(str(path), True)
    assert values.size() == K
    assert sorted(int(k) for k in values.keys()) == list(range(K))
    for k in range(K):
        np.testing.assert_allclose(pose_matrix(values.atPose3(k)), mapper.map.kf_T_wc[k], atol=1e-9)
    assert factors.size() == len(edges)
    assert len(load_json(tmp_path / "system.json")[3]) == len(edges)
