"""tools/sweep.py (and sweep_tables.py): a tiny sweep on a generated sequence (runs in parallel child processes, a failing
configuration recorded as failed), the tables' statistics, the sweep file and the ablation alias."""
from __future__ import annotations

import contextlib
import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import REPO, XYZ, load_tool, real_sequence

TOOLS = REPO / "tools"

sweep = load_tool("sweep")
tables = load_tool("sweep_tables")
FRAMES = 20


def tiny_sweep_argv(root: Path) -> list[str]:
    return ["--sequences", "synthetic:people", "--configs", "none", "dynamic_box_depth", str(root / "broken.yaml"),
            "--repeats", "2", "--max-frames", str(FRAMES), "--jobs", "2", "--output", str(root / "out"),
            "--detection-cache", str(root / "cache"), "--quiet"]


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory):
    """2 configurations × 2 repeats × 20 frames of walking people, plus a configuration whose file has an
    unknown key, 2 runs at a time. Returns (exit status, output folder, printed table)."""
    root = tmp_path_factory.mktemp("sweep")
    (root / "broken.yaml").write_text("dynamic:\n  no_such_key: 1\n")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = sweep.main(tiny_sweep_argv(root))
    return status, root / "out", printed.getvalue()


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.mark.slow
def test_csv_has_one_row_per_run_with_the_run_folders_numbers(tiny_sweep):
    status, output, _ = tiny_sweep
    assert status == 1  # some runs failed; the sweep itself finished
    rows = read_csv(output / "sweep.csv")
    assert [(r["config"], r["repeat"], r["seed"]) for r in rows] == [
        (c, str(k), str(k)) for c in ("none", "dynamic_box_depth", "broken") for k in (0, 1)]
    assert {r["sequence"] for r in rows} == {"synthetic_people"}
    for row in rows[:4]:
        assert row["status"] == "ok" and row["error"] == ""
        run_dir = Path(row["run_dir"])
        summary = json.loads((run_dir / "summary.json").read_text())
        evaluation = json.loads((run_dir / "evaluation.json").read_text())
        assert float(row["ate_rmse_m"]) == pytest.approx(evaluation["ate"]["rmse"])
        assert float(row["rpe_trans_m"]) == pytest.approx(evaluation["rpe_frame"]["translation"]["rmse"])
        assert float(row["rpe_rot_deg"]) == pytest.approx(evaluation["rpe_frame"]["rotation"]["rmse"])
        assert (int(row["tracked"]), int(row["frames"])) == (summary["tracked"], FRAMES)
        assert float(row["median_ms"]) == pytest.approx(summary["timing_ms"]["total"]["median_ms"])
        assert float(row["ms_extract"]) == pytest.approx(summary["timing_ms"]["extract"]["median_ms"])
    assert rows[2]["ms_dynamic.box_depth"] and not rows[0]["ms_dynamic.box_depth"]  # per-module columns


@pytest.mark.slow
def test_runs_get_their_seed_and_the_detection_cache(tiny_sweep):
    _, output, _ = tiny_sweep
    config = yaml.safe_load((output / "runs" / "synthetic_people__dynamic_box_depth__r1" / "config.yaml").read_text())
    assert config["seed"] == 1 and config["dynamic"]["cpr"]["seed"] == 1
    assert config["dynamic"]["methods"] == ["box_depth"]
    assert Path(config["dynamic"]["detector"]["cache_dir"]) == output.parent / "cache"


@pytest.mark.slow
def test_a_failing_configuration_is_recorded_with_its_message(tiny_sweep):
    _, output, printed = tiny_sweep
    failed = [r for r in read_csv(output / "sweep.csv") if r["config"] == "broken"]
    assert [r["status"] for r in failed] == ["failed", "failed"]
    assert all(r["error"].startswith("ConfigError:") and "no_such_key" in r["error"] for r in failed)
    assert all(r["ate_rmse_m"] == "" for r in failed)
    line = next(line for line in printed.splitlines() if "`broken`" in line)
    assert "2 (2 failed: ConfigError:" in line and "| – | – |" in line


@pytest.mark.slow
def test_markdown_table_has_the_columns_and_the_medians_of_the_runs(tiny_sweep):
    _, output, printed = tiny_sweep
    assert (output / "sweep.md").read_text() == printed
    lines = printed.splitlines()
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    assert header == ["configuration", "ATE RMSE median (m)", "min – max", "RPE median (m, ° per frame)",
                      "frames tracked (worst)", "ms/frame (median)", "vs. none", "runs"]
    assert len(lines) == 2 + 3
    rows = read_csv(output / "sweep.csv")
    for config, line in zip(("none", "dynamic_box_depth"), lines[2:4]):
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        runs = [r for r in rows if r["config"] == config]
        ates = [float(r["ate_rmse_m"]) for r in runs]
        assert cells[0] == f"`{config}`"
        assert cells[1] == f"{np.median(ates):.4f}" and cells[2] == f"{min(ates):.4f} – {max(ates):.4f}"
        assert cells[3].startswith(f"{np.median([float(r['rpe_trans_m']) for r in runs]):.4f}, ")
        assert cells[4] == f"{min(int(r['tracked']) for r in runs)}/{FRAMES}"
        assert cells[5] == f"{np.median([float(r['median_ms']) for r in runs]):.1f}"
        assert cells[7] == "2"
    assert lines[2].split("|")[7].strip() == "1.0×"
    json_rows = json.loads((output / "sweep.json").read_text())["runs"]
    assert len(json_rows) == 6


def fake_row(config: str, repeat: int, ate=None, **extra) -> dict:
    row = {"sequence": "seq", "config": config, "repeat": repeat, "seed": repeat, "status": "ok", "error": "",
           "ate_rmse_m": ate, "rpe_trans_m": 0.01 * (repeat + 1), "rpe_rot_deg": 0.5 * (repeat + 1),
           "tracked": 100 - repeat, "frames": 100, "median_ms": 20.0 + repeat}
    row.update(extra)
    return row


def test_medians_spread_and_ratio_from_per_run_numbers():
    spec = sweep.SweepSpec(sequences=["seq"], configs=[sweep.ConfigSpec("off"), sweep.ConfigSpec("fused", ("x",))],
                           baseline="off")
    rows = [fake_row("off", 0, 0.8), fake_row("off", 1, 0.6), fake_row("off", 2, 1.0),
            fake_row("fused", 0, 0.03), fake_row("fused", 1, 0.01), fake_row("fused", 2, 0.02),
            fake_row("fused", 3, status="failed", error="RuntimeError: boom | bang", ate_rmse_m=None)]
    groups = {g["config"].label: g for g in tables.group_stats(rows, spec)}
    assert groups["off"]["ate_median"] == pytest.approx(0.8)
    assert (groups["off"]["ate_min"], groups["off"]["ate_max"]) == (0.6, 1.0)
    assert groups["fused"]["ate_median"] == pytest.approx(0.02) and groups["fused"]["failed"] == 1
    assert groups["fused"]["rpe_trans"] == pytest.approx(0.02) and groups["fused"]["median_ms"] == pytest.approx(21.0)
    assert groups["fused"]["tracked"] == (98, 100)  # the worst of the successful repeats
    table = sweep.markdown_table(rows, spec).splitlines()
    assert table[2] == "| `off` | 0.8000 | 0.6000 – 1.0000 | 0.0200, 1.000 | 98/100 | 21.0 | 1.0× | 3 |"
    assert table[3] == ("| `fused` | 0.0200 | 0.0100 – 0.0300 | 0.0200, 1.000 | 98/100 | 21.0 | 40× | "
                        "4 (1 failed: RuntimeError: boom \\| bang) |")


def test_several_sequences_get_a_sequence_column():
    spec = sweep.SweepSpec(sequences=["synthetic:a", "synthetic:b"], configs=[sweep.ConfigSpec("off")])
    sweep.check_spec(spec)  # defaults the baseline to the first configuration
    rows = [fake_row("off", 0, 0.5), {**fake_row("off", 0, 0.25), "sequence": "other"}]
    table = sweep.markdown_table(rows, spec).splitlines()
    assert table[0].startswith("| sequence | configuration |")
    assert table[2].startswith("| seq | `off` | 0.5000") and table[3].startswith("| other | `off` | 0.2500")


def test_collect_row_reports_a_crash_and_a_timeout(tmp_path):
    job = {"sequence_label": "s", "config": "c", "repeat": 0, "seed": 0, "run_dir": str(tmp_path)}
    (tmp_path / "run.log").write_text("Fatal Python error: Segmentation fault\n")
    assert sweep.collect_row(job, -11, 1.0)["error"] == "killed by signal 11"
    assert sweep.collect_row(job, 3, 1.0)["error"] == "exit status 3: Fatal Python error: Segmentation fault"
    assert sweep.collect_row(job, None, 5.0, timeout=5)["error"] == "timed out after 5 s"
    assert sweep.collect_row(job, 0, 1.0)["error"] == "the run wrote no summary.json"
    assert sweep.collect_row(job, None, 0.0, error="OSError: disk full")["error"] == "OSError: disk full"


def test_bonn_ablation_sweep_file_defines_the_readme_ablation():
    spec = sweep.load_sweep_file(TOOLS / "sweeps" / "bonn_ablation.yaml")
    repo = TOOLS.parent
    assert spec.sequences == [str((repo.parent / "shared" / "data" / "rgbd_bonn_crowd_first480").resolve())]
    assert spec.presets == ["bonn"] and spec.repeats == 3 and spec.baseline == "off"
    assert {c.label: c.presets for c in spec.configs} == {
        "off": ("static",), "dynamic_box_prior": ("dynamic_box_prior",), "dynamic_cpr": ("dynamic_cpr",),
        "dynamic_box_depth": ("dynamic_box_depth",), "dynamic_flow_epipolar": ("dynamic_flow_epipolar",),
        "dynamic_depth_sdf": ("dynamic_depth_sdf",), "dynamic_all": ("dynamic_all",)}
    from slam.core.config import SlamConfig, apply_yaml

    for config in spec.configs:  # every preset exists and loads
        for preset in spec.presets + list(config.presets):
            apply_yaml(SlamConfig(), preset)


def test_sweep_file_paths_and_command_line_overrides(tmp_path):
    (tmp_path / "s.yaml").write_text(
        "sequences: [data/seq, synthetic:people:seed=2]\npresets: [bonn, configs/x.yaml]\n"
        "configs:\n  plain: null\n  both: {presets: dynamic_all, set: {tracking.match_ratio: 0.8}, description: d}\n"
        "repeats: 2\n")
    spec = sweep.load_sweep_file(tmp_path / "s.yaml")
    assert spec.sequences == [str(sweep.REPO / "data" / "seq"), "synthetic:people:seed=2"]
    assert spec.presets == ["bonn", str(sweep.REPO / "configs" / "x.yaml")]
    assert spec.configs[1] == sweep.ConfigSpec("both", ("dynamic_all",), (("tracking.match_ratio", 0.8),), "d")
    args = sweep.build_parser().parse_args([str(tmp_path / "s.yaml"), "--repeats", "5", "--max-frames", "7",
                                            "--set", "seed=3", "--baseline", "both"])
    spec = sweep.spec_from_args(args)
    assert (spec.repeats, spec.max_frames, spec.baseline, spec.overrides) == (5, 7, "both", {"seed": 3})
    jobs = sweep.make_jobs(spec, tmp_path)
    assert len(jobs) == 2 * 2 * 5 and jobs[-1]["presets"] == ["bonn", str(sweep.REPO / "configs" / "x.yaml"),
                                                               "dynamic_all"]
    assert jobs[-1]["overrides"] == {"seed": 3, "tracking.match_ratio": 0.8}
    assert jobs[-1]["run_dir"] == str(tmp_path / "runs" / "synthetic_people_seed=2__both__r4")


def test_bad_sweeps_are_refused_with_a_clear_error(tmp_path, capsys):
    assert sweep.main(["--sequences", str(tmp_path / "missing"), "--configs", "none"]) == 2
    assert "sequence folder not found" in capsys.readouterr().err
    assert sweep.main(["--configs", "none"]) == 2
    assert "nothing to run" in capsys.readouterr().err
    (tmp_path / "s.yaml").write_text("sequence: [x]\n")
    assert sweep.main([str(tmp_path / "s.yaml")]) == 2
    assert "expected a mapping with keys" in capsys.readouterr().err
    assert sweep.main(["--sequences", "synthetic", "--configs", "none", "--baseline", "other"]) == 2
    assert "baseline 'other'" in capsys.readouterr().err


def test_ablation_alias_translates_to_sweep_arguments():
    ablation = load_tool("ablation")
    assert ablation.sweep_arguments(["--repeats", "3"])[:3] == [str(TOOLS / "sweeps" / "bonn_ablation.yaml"),
                                                                "--repeats", "3"]
    args = ablation.sweep_arguments(["SEQ", "--configs", "none", "dynamic_all", "--set", "a=1", "--jobs", "1"])
    assert args[:6] == ["--sequences", "SEQ", "--configs", "none", "dynamic_all", "--set"]
    assert args[6:10] == ["a=1", "--jobs", "1", "--output"]


@pytest.mark.slow
def test_same_seed_gives_the_same_row(tiny_sweep, tmp_path):
    """The same sequence, configuration and seed, run again alone (one job instead of two in
    parallel): every accuracy column of its row is identical; only the timings may differ."""
    _, output, _ = tiny_sweep
    argv = ["--sequences", "synthetic:people", "--configs", "dynamic_box_depth", "--repeats", "1",
            "--max-frames", str(FRAMES), "--jobs", "1", "--output", str(tmp_path / "again"),
            "--detection-cache", str(output.parent / "cache"), "--quiet"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert sweep.main(argv) == 0
    again = read_csv(tmp_path / "again" / "sweep.csv")
    first = [r for r in read_csv(output / "sweep.csv") if r["config"] == "dynamic_box_depth" and r["seed"] == "0"]
    assert len(again) == len(first) == 1
    columns = [k for k in first[0] if not k.startswith("ms") and k not in ("median_ms", "mean_ms", "run_dir",
                                                                            "wall_s", "fps")]
    assert {"ate_rmse_m", "rpe_trans_m", "tracked", "seed"} <= set(columns)
    assert {k: again[0][k] for k in columns} == {k: first[0][k] for k in columns}
    first_run, again_run = Path(first[0]["run_dir"]), Path(again[0]["run_dir"])
    assert (first_run / "trajectory.txt").read_bytes() == (again_run / "trajectory.txt").read_bytes()


@pytest.mark.slow
def test_resume_keeps_finished_runs_and_reruns_the_failed_ones(tiny_sweep):
    """Last: it reruns the module's sweep in place."""
    _, output, _ = tiny_sweep
    marker = output / "runs" / "synthetic_people__none__r0" / "kept"
    marker.write_text("")
    failed_marker = output / "runs" / "synthetic_people__broken__r0" / "kept"
    failed_marker.write_text("")
    before = read_csv(output / "sweep.csv")
    with contextlib.redirect_stdout(io.StringIO()):
        assert sweep.main(tiny_sweep_argv(output.parent) + ["--resume"]) == 1
    after = read_csv(output / "sweep.csv")
    assert marker.exists()  # not run again
    assert [r["ate_rmse_m"] for r in after] == [r["ate_rmse_m"] for r in before]
    assert [r["status"] for r in after] == [r["status"] for r in before]
    assert not failed_marker.exists()  # failed runs are run again


def test_hard_scene_sequences_parse_label_and_are_checked(tmp_path):
    sequences = load_tool("sweep_sequences")
    assert sequences.hard_scene_options("hard:close_pass") == {"scene": "close_pass", "seed": 0}
    assert sequences.hard_scene_options("hard:border:seed=3") == {"scene": "border", "seed": 3}
    for bad in ("hard:nope", "hard:", "hard:border:frames=3"):
        with pytest.raises(sequences.SequenceSpecError):
            sequences.hard_scene_options(bad)
    assert sweep.sequence_label("hard:stand_walk:seed=2") == "hard_stand_walk_seed=2"
    args = sweep.build_parser().parse_args(["--sequences", "hard:three_close", "--configs", "none"])
    spec = sweep.spec_from_args(args)
    assert spec.sequences == ["hard:three_close"]   # a spec, not a folder to resolve
    sweep.check_spec(spec)
    assert sweep.make_jobs(spec, tmp_path)[0]["run_dir"] == str(tmp_path / "runs" / "hard_three_close__none__r0")
    assert sweep.main(["--sequences", "hard:no_such_scene", "--configs", "none"]) == 2


def test_composite_sequences_parse_label_and_are_checked(tmp_path):
    sequences = load_tool("sweep_sequences")
    folder = real_sequence(XYZ)
    spec = f"composite:two_walk:path={folder}"
    assert sequences.composite_options(spec) == {"scene": "two_walk", "path": folder, "seed": 0}
    relative = sequences.composite_options("composite:none:path=../shared/data/" + XYZ + ":seed=2")
    assert relative["path"] == (REPO.parent / "shared" / "data" / XYZ).resolve() and relative["seed"] == 2
    for bad in ("composite:two_walk", f"composite:nope:path={folder}", f"composite:two_walk:path={tmp_path}",
                f"composite:two_walk:path={folder}:frames=3"):
        with pytest.raises(sequences.SequenceSpecError):
            sequences.composite_options(bad)
    assert sweep.main(["--sequences", f"composite:two_walk:path={tmp_path}", "--configs", "none"]) == 2
    args = sweep.build_parser().parse_args(["--sequences", spec, "--configs", "none"])
    assert sweep.spec_from_args(args).sequences == [spec]   # a spec, not a folder to resolve


@pytest.mark.slow
def test_a_composite_sequence_runs_against_its_ground_truth(tmp_path):
    """20 frames of fr1/xyz with three people composited: the run finishes with an ATE on the real frames'
    ground truth, its detector the people's true boxes."""
    spec = f"composite:three_close:path={real_sequence(XYZ)}"
    argv = ["--sequences", spec, "--configs", "dynamic_all", "--max-frames", "20", "--jobs", "1",
            "--output", str(tmp_path), "--quiet"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert sweep.main(argv) == 0
    (row,) = read_csv(tmp_path / "sweep.csv")
    assert row["status"] == "ok" and row["frames"] == "20"
    # fr1/xyz's first 20 frames track to a few millimetres; composited people must not make that centimetres
    assert 0 < float(row["ate_rmse_m"]) < 0.02


def test_configs_first_orders_the_runs_configuration_by_configuration(tmp_path):
    spec = sweep.SweepSpec(sequences=["synthetic:a", "synthetic:b"], configs=[sweep.ConfigSpec("x"),
                                                                               sweep.ConfigSpec("y")])
    order = [(j["config"], j["sequence"]) for j in sweep.make_jobs(spec, tmp_path, configs_first=True)]
    assert order == [("x", "synthetic:a"), ("x", "synthetic:b"), ("y", "synthetic:a"), ("y", "synthetic:b")]
    assert [j["sequence"] for j in sweep.make_jobs(spec, tmp_path)][:2] == ["synthetic:a", "synthetic:a"]


def test_rows_carry_the_worst_frame_error(tmp_path):
    (tmp_path / "summary.json").write_text(json.dumps({"tracked": 9, "frames": 10, "timing_ms": {}}))
    ate = {"rmse": 0.02, "max": 0.06}
    rpe = {"translation": {"rmse": 0.01}, "rotation": {"rmse": 0.3}}
    (tmp_path / "evaluation.json").write_text(json.dumps({"ate": ate, "rpe_frame": rpe}))
    job = {"sequence_label": "s", "config": "c", "repeat": 0, "seed": 0, "run_dir": str(tmp_path)}
    row = sweep.collect_row(job, 0, 1.0)
    assert (row["status"], row["ate_rmse_m"], row["max_error_m"], row["tracked"]) == ("ok", 0.02, 0.06, 9)
    assert tables.csv_text([row]).splitlines()[0].split(",")[6:8] == ["ate_rmse_m", "max_error_m"]


@pytest.mark.slow
def test_a_hard_scene_runs_with_its_detector_misses(tmp_path):
    """20 frames of border (the person cut by the image border; its detector misses frames 2-9 of 20): the
    run finishes and its row has a worst-frame error no smaller than the RMSE."""
    argv = ["--sequences", "hard:border", "--configs", "dynamic_all", "--max-frames", "20", "--jobs", "1",
            "--output", str(tmp_path), "--quiet"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert sweep.main(argv) == 0
    (row,) = read_csv(tmp_path / "sweep.csv")
    assert row["sequence"] == "hard_border" and row["frames"] == "20"
    assert float(row["max_error_m"]) >= float(row["ate_rmse_m"]) > 0
    job = json.loads((Path(row["run_dir"]) / "job.json").read_text())
    assert job["sequence"] == "hard:border"
