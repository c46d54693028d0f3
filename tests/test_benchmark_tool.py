"""tools/benchmark.py's speed report: back-end cost as the map grows, and the table beside the peer."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import load_tool

benchmark = load_tool("benchmark")


def test_backend_cost_is_the_median_of_the_keyframes_up_to_each_mark():
    keyframe_ms = np.arange(1.0, 121.0)   # the k-th keyframe costs k ms
    at = benchmark.backend_cost_at_marks(keyframe_ms)
    assert at == {50: 45.5, 100: 95.5}    # keyframes 41-50 and 91-100; 200 and 500 not reached


def test_mapping_line_gives_the_median_update_and_the_marks_reached():
    line = benchmark.mapping_line(np.arange(1.0, 61.0))     # the k-th update costs k ms
    assert "median 30.5 over 60" in line and "@50 45.5" in line and "@100" not in line
    assert benchmark.mapping_line(np.zeros(0)) == "mapping back end: no keyframe update"


def test_speed_table_has_the_ratio_to_the_peer_and_dashes_for_what_is_missing():
    rows = [{"system": "dynslam", "sequence": "seq", "whole_run_ms_per_frame": 30.0,
             "latency_ms": {"median": 20.0, "p95": 50.0}, "backend_ms_at_keyframes": {50: 40.0},
             "cost_trend": {"first_ms": 18.0, "last_ms": 22.5, "ratio": 1.25}},
            {"system": "ORB-SLAM3 (stock)", "sequence": "seq", "median_ms": {"total": 12.0}},
            {"system": "dynslam", "sequence": "alone", "whole_run_ms_per_frame": 10.0,
             "latency_ms": {"median": 5.0, "p95": 9.0}, "backend_ms_at_keyframes": {}}]
    lines = benchmark.speed_table(rows).splitlines()
    assert lines[0].startswith("| sequence | whole-run ms/frame | latency median | latency p95 |")
    assert lines[2] == "| seq | 30.0 | 20.0 | 50.0 | 18.0 / 22.5 (1.25) | 40.0 | – | – | – | 12.0 | 2.5x |"
    assert lines[3] == "| alone | 10.0 | 5.0 | 9.0 | – | – | – | – | – | – | – |"
    assert len(lines) == 4, "the peer is a column, not a row"


def test_cost_trend_compares_the_first_and_last_quarter_after_the_first_second():
    ms = np.concatenate([np.full(benchmark.TREND_WARMUP_FRAMES, 500.0), np.full(100, 20.0), np.full(100, 30.0)])
    trend = benchmark.cost_trend(ms)          # quarters of the 200 frames after the warm-up: 50 frames each
    assert trend == {"first_ms": 20.0, "last_ms": 30.0, "ratio": 1.5}
    assert benchmark.cost_trend(np.ones(benchmark.TREND_WARMUP_FRAMES + 3)) == {}


def test_module_trend_line_names_the_modules_that_changed_most():
    trends = {"tracking": {"first_ms": 20.0, "last_ms": 21.0, "ratio": 1.05},
              "backend": {"first_ms": 2.8, "last_ms": 36.7, "ratio": 13.1},
              "dynamic.box_depth": {"first_ms": 4.5, "last_ms": 44.9, "ratio": 10.0},
              "dynamic.prepare_wait": {"first_ms": 25.0, "last_ms": 6.0, "ratio": 0.24}, "loop": {}}
    line = benchmark.module_trend_line(trends)
    assert line.endswith("dynamic.box_depth 4.5 -> 44.9, backend 2.8 -> 36.7, dynamic.prepare_wait 25.0 -> 6.0, "
                         "tracking 20.0 -> 21.0")
    assert benchmark.module_trend_line({"loop": {}}).endswith("run too short")
    assert benchmark.module_trend_line(trends, "CPU").startswith("step by module, mean CPU ms per frame")


def _dynslam_row(sequence: str, whole_run_ms: float, ate_m: float, trend_ratio: float = 1.0) -> dict:
    return {"system": "dynslam", "sequence": sequence, "whole_run_ms_per_frame": whole_run_ms, "ate_rmse_m": ate_m,
            "cost_trend": {"first_ms": 20.0, "last_ms": 20.0 * trend_ratio, "ratio": trend_ratio}}


def test_check_holds_each_sequence_to_the_issues_targets(capsys):
    peer = {"system": "ORB-SLAM3 (stock)", "sequence": "rgbd_dataset_freiburg1_rpy_first400", "median_ms": {"total": 12.0}}
    rpy = "rgbd_dataset_freiburg1_rpy_first400"
    assert benchmark._check_targets([_dynslam_row(rpy, 24.0, 0.0240), peer]) == 0
    assert benchmark._check_targets([_dynslam_row("rgbd_bonn_crowd_first480", 44.0, 0.0120)]) == 0
    capsys.readouterr()
    assert benchmark._check_targets([_dynslam_row(rpy, 129.7, 0.0233), peer]) == 1
    err = capsys.readouterr().err
    assert "whole run 129.7 ms/frame > 25.0 ms" in err and "10.8x the ORB-SLAM3 peer's tracking > 2.0x" in err
    assert benchmark._check_targets([_dynslam_row(rpy, 20.0, 0.0260, trend_ratio=1.3), peer]) == 1
    err = capsys.readouterr().err
    assert "ATE 0.0260 m > 0.0253 m" in err and "last quarter's step 26.0 ms > 1.25 x the first quarter's 20.0" in err
    assert "whole run" not in err          # 20 ms/frame, 1.7x the peer: both within


def _long_report(first_ms: float, last_ms: float) -> dict:
    blocks = [{"first": 1, "last": 1000, "mean_ms": first_ms, "keyframes": 200, "keyframes_added": 200,
               "rss_end_mib": 350.0},
              {"first": 4001, "last": 5000, "mean_ms": last_ms, "keyframes": 399, "keyframes_added": 1,
               "rss_end_mib": 448.0}]
    return {"sequence": "synthetic_orbit_seed0", "frames": 5000, "tracked": 5000, "ate_rmse_m": 0.0042,
            "blocks": blocks, "wall_ms_per_frame": 83.5, "peak_rss_mib": 630.0, "rss_peak_frames_mib": 455.0,
            "growth_mib_per_1000": 1.2}


def test_long_run_table_compares_the_first_and_last_block(capsys):
    text = benchmark.long_run_table(_long_report(66.2, 45.4), benchmark.TARGETS["long_run_ratio"])
    assert "| 1–1000 | 66.2 | 200 (200) | 350 |" in text and "| 4001–5000 | 45.4 | 399 (1) | 448 |" in text
    assert "last / first: **0.69** (target ≤ 1.25)" in text and "peak RSS 630 MiB" in text
    assert benchmark._check_targets([], _long_report(66.2, 45.4)) == 0
    assert benchmark._check_targets([], _long_report(56.9, 107.0)) == 1     # the 1.88 of before
    assert "long run: last 1,000 frames 107.0 ms > 1.25 x the first 56.9 ms" in capsys.readouterr().err


def test_long_run_needs_two_blocks(capsys):
    with pytest.raises(SystemExit):
        benchmark.main(["--long-run", "1500"])
    assert "--long-run needs at least 2000 frames" in capsys.readouterr().err


@pytest.mark.slow
def test_long_run_runs_the_memory_tool_in_its_own_process(tmp_path):
    report = benchmark.run_long(40, tmp_path, block=15)
    assert report["frames"] == 40 and [(b["first"], b["last"]) for b in report["blocks"]] == [(1, 15), (16, 30), (31, 40)]
    assert (tmp_path / "long_run.json").is_file()
    assert "last / first" in benchmark.long_run_table(report, benchmark.TARGETS["long_run_ratio"])


def test_method_line_lists_every_dynamic_method_slowest_first():
    line = benchmark.method_line({"box_depth": 4.25, "cpr": 21.0, "detector": 0.1})
    assert line == ("dynamic front end (methods, detector wait, steps), median wall ms per frame: cpr 21.0, "
                    "box_depth 4.2, detector 0.1")
    assert benchmark.method_line({}) == "dynamic front end: none (dynamic handling off)"


def test_module_cpu_line_lists_modules_by_cpu_without_the_total():
    line = benchmark.module_cpu_line({"tracking": 24.1, "dynamic.flow_epipolar": 19.25, "total": 70.0})
    assert line == ("module CPU, mean ms per frame (the thread that ran it): tracking 24.1, "
                    "dynamic.flow_epipolar 19.2")
    assert benchmark.module_cpu_line({}) == "module CPU: not measured"


def test_module_timer_counts_a_waiting_block_as_wall_time_but_not_as_cpu():
    import time

    from slam.core.timing import ModuleTimer

    timer = ModuleTimer()
    with timer.measure("waits"):
        time.sleep(0.05)             # a thread waiting for a core, a lock or a result: wall, no CPU
    with timer.measure("works"):
        end = time.thread_time() + 0.03
        while time.thread_time() < end:
            pass
    timer.end_frame()
    summary = timer.summary()
    assert summary["waits"]["median_ms"] >= 50 and summary["waits"]["cpu_mean_ms"] < 10
    assert summary["works"]["cpu_mean_ms"] >= 30
    assert summary["total"]["cpu_mean_ms"] == pytest.approx(summary["waits"]["cpu_mean_ms"]
                                                            + summary["works"]["cpu_mean_ms"])


def test_compile_line_shows_numba_compiling_inside_the_timed_run_only():
    row = {"sequence": "seq", "frames": 400, "kernel_compile_s": 80.0}
    assert benchmark.compile_line(row) == ("\nseq: numba compiled kernels for 80.0 s inside the timed run (once per "
                                          "install; 200.0 ms of the whole run's ms per frame)")
    assert benchmark.compile_line({**row, "kernel_compile_s": 0.1}) == ""
    assert benchmark.compile_line({"sequence": "seq", "frames": 3}) == ""      # a row from before the field


def test_a_failing_warm_up_names_its_command(tmp_path):
    with pytest.raises(RuntimeError, match=r"warm-up run failed .*slam\.cli run .*missing_sequence"):
        benchmark.warm_up(tmp_path / "missing_sequence", tmp_path / "out", [], [])
