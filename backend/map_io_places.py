"""Map-file members for place recognition and loops (dynslam-map version 2; see ``backend.map_io``).

==============================  ===============  ===========================================================
member                          shape, dtype     meaning
==============================  ===============  ===========================================================
``voc_k``, ``voc_levels``,      (), int64        the vocabulary the keyframe index was built with, in the
``voc_n_training_docs``                          members of the vocabulary file format
``voc_node_descriptors``        (V,32) uint8     (``backend.place_recognition``): tree nodes, parents, idf
``voc_node_parents``            (V,) int32
``voc_idf``                     (W,) float64
``bow_offsets``                 (K+1,) int64     keyframe k's bag of words is rows ``[off[k], off[k+1])``
``bow_words``, ``bow_weights``  (B,) int32/f64   word ids (sorted) and L1-normalised tf-idf weights
``loop_query``, ``loop_match``  (N,) int64       keyframes joined by each loop factor
``loop_T_match_query``          (N,4,4) float64  the query pose seen from the match (the factor's measurement)
``loop_n_inliers``              (N,) int64       PnP inliers of the verification (0 if injected)
``loop_score``                  (N,) float64     BoW score of the match
``loop_active``                 (N,) bool        False: removed again as inconsistent
``loop_source``                 (N,) unicode     "detected" or "injected"
==============================  ===============  ===========================================================

All members are optional as a group: a version-1 file, or a map saved without place recognition,
has none of them and loads with no vocabulary, no index and no loops.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from backend.place_recognition import BowVector, KeyframeIndex, Vocabulary, VocabularyError

VOCABULARY_KEYS = ("k", "levels", "n_training_docs", "node_descriptors", "node_parents", "idf")


@dataclass
class StoredLoop:
    query_kf: int
    match_kf: int
    T_match_query: np.ndarray
    n_inliers: int
    score: float
    active: bool
    source: str


@dataclass
class PlaceData:
    vocabulary: Optional[Vocabulary] = None
    bows: dict[int, BowVector] = field(default_factory=dict)
    loops: list[StoredLoop] = field(default_factory=list)


def place_arrays(n_keyframes: int, index: Optional[KeyframeIndex], loops: Sequence) -> dict[str, np.ndarray]:
    """Members for the index's vocabulary and keyframe words, and the loops (objects with the
    ``StoredLoop`` attributes, e.g. ``backend.loop_closing.LoopEdge``)."""
    arrays: dict[str, np.ndarray] = {}
    if index is not None:
        arrays.update({f"voc_{k}": v for k, v in index.vocabulary.to_arrays().items()})
        bows = [index.bow(k) if k in index else BowVector(np.zeros(0, np.int32), np.zeros(0))
                for k in range(n_keyframes)]
        offsets = np.zeros(n_keyframes + 1, np.int64)
        offsets[1:] = np.cumsum([len(b) for b in bows])
        arrays["bow_offsets"] = offsets
        arrays["bow_words"] = np.concatenate([b.words for b in bows] + [np.zeros(0, np.int32)]).astype(np.int32)
        arrays["bow_weights"] = np.concatenate([b.weights for b in bows] + [np.zeros(0)]).astype(np.float64)
    arrays["loop_query"] = np.array([e.query_kf for e in loops], np.int64)
    arrays["loop_match"] = np.array([e.match_kf for e in loops], np.int64)
    arrays["loop_T_match_query"] = np.array([e.T_match_query for e in loops], np.float64).reshape(-1, 4, 4)
    arrays["loop_n_inliers"] = np.array([e.n_inliers for e in loops], np.int64)
    arrays["loop_score"] = np.array([e.score for e in loops], np.float64)
    arrays["loop_active"] = np.array([e.active for e in loops], bool)
    arrays["loop_source"] = np.array([e.source for e in loops], dtype="U16")
    return arrays


def read_place_arrays(a: dict, path: Path, n_keyframes: int, error: type) -> PlaceData:
    """The place-recognition and loop members of a loaded map; ``error`` names what is wrong."""
    data = PlaceData()
    if "voc_idf" in a:
        try:
            data.vocabulary = Vocabulary.from_arrays({k: a[f"voc_{k}"] for k in VOCABULARY_KEYS}, str(path))
        except (KeyError, VocabularyError) as exc:
            raise error(f"{path}: the map's vocabulary is unusable ({exc})") from exc
        data.bows = _read_bows(a, path, n_keyframes, data.vocabulary.n_words, error)
    if "loop_query" in a:
        data.loops = _read_loops(a, path, n_keyframes, error)
    return data


def _read_bows(a: dict, path: Path, n_keyframes: int, n_words: int, error: type) -> dict[int, BowVector]:
    off, words, weights = a.get("bow_offsets"), a.get("bow_words"), a.get("bow_weights")
    if off is None or words is None or weights is None:
        raise error(f"{path}: map has a vocabulary but no keyframe words (bow_offsets/bow_words/bow_weights)")
    ok = (off.shape == (n_keyframes + 1,) and off[0] == 0 and np.all(np.diff(off) >= 0) and off[-1] == len(words)
          and words.shape == weights.shape and np.all((words >= 0) & (words < n_words)))
    if not ok:
        raise error(f"{path}: inconsistent keyframe words (bow_offsets/bow_words/bow_weights)")
    return {k: BowVector(words[off[k]:off[k + 1]].astype(np.int32), weights[off[k]:off[k + 1]].astype(np.float64))
            for k in range(n_keyframes)}


def _read_loops(a: dict, path: Path, n_keyframes: int, error: type) -> list[StoredLoop]:
    names = ("loop_query", "loop_match", "loop_T_match_query", "loop_n_inliers", "loop_score", "loop_active",
             "loop_source")
    missing = [n for n in names if n not in a]
    if missing:
        raise error(f"{path}: map is missing loop members {missing}")
    n = len(a["loop_query"])
    if any(len(a[name]) != n for name in names) or a["loop_T_match_query"].shape != (n, 4, 4):
        raise error(f"{path}: loop members disagree in length")
    ends = np.r_[a["loop_query"], a["loop_match"]]
    if np.any((ends < 0) | (ends >= n_keyframes)):
        raise error(f"{path}: loop keyframe ids out of range")
    return [StoredLoop(int(a["loop_query"][i]), int(a["loop_match"][i]), a["loop_T_match_query"][i].copy(),
                       int(a["loop_n_inliers"][i]), float(a["loop_score"][i]), bool(a["loop_active"][i]),
                       str(a["loop_source"][i])) for i in range(n)]
