"""tools/benchmark.py's speed report: back-end cost as the map grows, and the table beside the peer."""
from __future__ import annotations

import numpy as np

from conftest import load_tool

benchmark = load_tool("benchmark")


def test_backend_cost_is_the_median_of_the_keyframes_up_to_each_mark():
    keyframe_ms = np.arange(1.0, 121.0)   # the k-th keyframe costs k ms
    at = benchmark.backend_cost_at_marks(keyframe_ms)
    assert at == {50: 45.5, 100: 95.5}    # keyframes 41-50 and 91-100; 200 and 500 not reached


def test_speed_table_has_the_ratio_to_the_peer_and_dashes_for_what_is_missing():
    rows = [{"system": "dynslam", "sequence": "seq", "whole_run_ms_per_frame": 30.0,
             "latency_ms": {"median": 20.0, "p95": 50.0}, "backend_ms_at_keyframes": {50: 40.0}},
            {"system": "ORB-SLAM3 (stock)", "sequence": "seq", "median_ms": {"total": 12.0}},
            {"system": "dynslam", "sequence": "alone", "whole_run_ms_per_frame": 10.0,
             "latency_ms": {"median": 5.0, "p95": 9.0}, "backend_ms_at_keyframes": {}}]
    lines = benchmark.speed_table(rows).splitlines()
    assert lines[0].startswith("| sequence | whole-run ms/frame | latency median | latency p95 |")
    assert lines[2] == "| seq | 30.0 | 20.0 | 50.0 | 40.0 | – | – | – | 12.0 | 2.5x |"
    assert lines[3] == "| alone | 10.0 | 5.0 | 9.0 | – | – | – | – | – | – |"
    assert len(lines) == 4, "the peer is a column, not a row"
