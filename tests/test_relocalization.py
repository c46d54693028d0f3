"""Global relocalization through the keyframe index, and the place-recognition part of map files."""
from __future__ import annotations

import numpy as np
import pytest

from backend.map_io import MapFormatError, load_map
from backend.place_recognition import DEFAULT_VOCABULARY, Vocabulary
from slam.core.config import load_config
from slam.datasets import SyntheticSequence
from slam.runtime.system import System

MAPPED = 80          # frames mapped before the camera is "kidnapped"
BLANK = 3            # frames with nothing in them (tracking is lost)
REVISIT = range(10, 30)   # then the camera is back where it was at these frames


def _error_vs_truth(T_est: np.ndarray, T_gt: np.ndarray, T_gt0: np.ndarray) -> float:
    """Position error of an estimate in the map frame (the first camera) against ground truth."""
    return float(np.linalg.norm(T_est[:3, 3] - (np.linalg.inv(T_gt0) @ T_gt)[:3, 3]))


@pytest.fixture(scope="module")
def kidnapped():
    seq = SyntheticSequence(n_frames=MAPPED)
    frames = list(seq)
    _, gt = seq.groundtruth()
    system = System(load_config("static"))
    outputs = [system.process(f.rgb, f.depth, f.timestamp, f.index) for f in frames]
    keyframes_before = system.num_keyframes
    blank_rgb, blank_depth = np.zeros_like(frames[0].rgb), np.zeros_like(frames[0].depth)
    t = frames[-1].timestamp
    for k in range(BLANK):
        t += 1 / 30
        outputs.append(system.process(blank_rgb, blank_depth, t, MAPPED + k))
    revisit = []
    for i in REVISIT:
        t += 1 / 30
        revisit.append((i, system.process(frames[i].rgb, frames[i].depth, t, len(outputs))))
        outputs.append(revisit[-1][1])
    return system, gt, outputs, revisit, keyframes_before


@pytest.mark.slow
def test_kidnapped_camera_is_relocalized_in_the_same_map(kidnapped):
    system, gt, outputs, revisit, keyframes_before = kidnapped
    assert all(o.T_wc is not None for o in outputs[:MAPPED])
    assert all(o.T_wc is None for o in outputs[MAPPED:MAPPED + BLANK])
    tracked = [o.T_wc is not None for _, o in revisit]
    assert tracked[0], "the first frame at the old place should relocalize"
    assert all(tracked)
    assert system.relocalizer.successes >= 1
    # Same map, not a restart: poses are in the first camera's frame and agree with ground truth.
    for i, out in revisit:
        assert _error_vs_truth(out.T_wc, gt[i], gt[0]) < 0.02, i
    assert system.num_keyframes >= keyframes_before
    stamps, poses, ok = system.trajectory()
    assert not ok[MAPPED:MAPPED + BLANK].any() and np.isnan(poses[MAPPED:MAPPED + BLANK]).all()


@pytest.mark.slow
def test_relocalization_is_timed(kidnapped):
    system = kidnapped[0]
    _, report = system.place_recognition_report()
    reloc = report["relocalization_per_attempt"]
    assert report["relocalization_attempts"] == reloc["count"] >= BLANK
    assert reloc["max_ms"] > 0


@pytest.mark.slow
def test_map_file_keeps_vocabulary_words_and_loops(kidnapped, tmp_path):
    system = kidnapped[0]
    edge = system.loop_closer.add_constraint(0, system.num_keyframes - 1,
                                             np.linalg.solve(system.mapper.map.kf_T_wc[0],
                                                             system.mapper.map.kf_T_wc[-1]))
    path = tmp_path / "map.npz"
    system.save_map(path)
    loaded = load_map(path)
    places = loaded.places
    shipped = Vocabulary.load(DEFAULT_VOCABULARY)
    assert places.vocabulary.n_words == shipped.n_words
    np.testing.assert_array_equal(places.vocabulary.node_descriptors, shipped.node_descriptors)
    index = system.loop_closer.index
    assert len(places.bows) == system.num_keyframes
    for k, bow in places.bows.items():
        np.testing.assert_array_equal(bow.words, index.bow(k).words)
        np.testing.assert_allclose(bow.weights, index.bow(k).weights)
    assert len(places.loops) == len(system.loop_closer.loops)
    stored = places.loops[-1]
    assert (stored.query_kf, stored.match_kf, stored.source, stored.active) == (edge.query_kf, edge.match_kf,
                                                                                  "injected", edge.active)
    np.testing.assert_allclose(stored.T_match_query, edge.T_match_query)


@pytest.mark.slow
def test_localization_run_relocalizes_through_the_saved_index(kidnapped, tmp_path):
    system = kidnapped[0]
    path = tmp_path / "map.npz"
    system.save_map(path)
    loaded = load_map(path)
    seq = SyntheticSequence(n_frames=40)
    localizer = System(load_config("static"), prior_map=loaded.slam_map, localization_only=True,
                       vocabulary=loaded.places.vocabulary, prior_words=loaded.places.bows)
    assert len(localizer.loop_closer.index) == loaded.slam_map.num_keyframes
    _, gt = seq.groundtruth()
    frame = seq.frame(20, cache=False)
    out = localizer.process(frame.rgb, frame.depth, frame.timestamp, 0)
    assert out.T_wc is not None and localizer.relocalizer.successes == 1
    assert _error_vs_truth(out.T_wc, gt[20], gt[0]) < 0.02


@pytest.mark.slow
def test_inconsistent_words_are_a_clear_error(kidnapped, tmp_path):
    system = kidnapped[0]
    path = tmp_path / "map.npz"
    system.save_map(path)
    with np.load(path) as z:
        arrays = dict(z)
    arrays["bow_words"] = arrays["bow_words"] + 10**6
    bad = tmp_path / "bad.npz"
    np.savez_compressed(bad, **arrays)
    with pytest.raises(MapFormatError, match="keyframe words"):
        load_map(bad)
