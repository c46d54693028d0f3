"""tools/speed_ab.py: this tree against another commit, run alternately, with the ratio and a same-bits check."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from conftest import load_tool

speed_ab = load_tool("speed_ab")
REPO = Path(__file__).resolve().parents[1]


def test_sides_alternate_abba_so_a_drift_of_the_machine_hits_both():
    assert speed_ab.round_order(1) == [0, 1]
    assert speed_ab.round_order(3) == [0, 1, 1, 0, 0, 1]


def _runs(whole, cpu, ate, trajectory):
    return speed_ab.SideRuns(list(whole), list(cpu), [ate] * len(whole), [trajectory] * len(whole))


def test_summary_gives_every_round_the_ratio_of_the_means_the_spread_and_whether_the_bits_agree():
    same = {"seq": (_runs([90.0, 110.0], [150.0, 170.0], 0.0233, b"t"),
                    _runs([100.0, 120.0], [180.0, 180.0], 0.0233, b"t"))}
    text = speed_ab.summary_table(same)
    assert "| seq | this tree | 90.0, 110.0 | 100.0 | 160.0 | 0.0233 |" in text
    assert "| seq | base | 100.0, 120.0 | 110.0 | 180.0 | 0.0233 |" in text
    assert "seq: this tree / base = 0.909 (whole run), 0.889 (CPU); spread of one side 20.0% / 18.2%; " \
           "trajectories the same bits" in text
    differ = {"seq": (_runs([90.0], [150.0], 0.0240, b"a"), _runs([100.0], [180.0], 0.0233, b"b"))}
    text = speed_ab.summary_table(differ)
    assert "spread of one side – / –; trajectories differ" in text and "| 0.0240 |" in text


def test_a_revision_that_is_not_a_commit_is_refused_before_anything_runs(tmp_path):
    with pytest.raises(SystemExit, match="'no-such-rev' is not a commit"):
        speed_ab.main(["no-such-rev", str(tmp_path), "-o", str(tmp_path / "out")])


def test_a_missing_sequence_folder_is_exit_2(tmp_path, capsys):
    assert speed_ab.main(["HEAD", str(tmp_path / "nowhere"), "-o", str(tmp_path / "out")]) == 2
    assert "sequence folder not found" in capsys.readouterr().err


@pytest.mark.slow
def test_this_tree_against_head_runs_both_sides_and_leaves_no_worktree(tum_folder, tmp_path, capsys):
    out = tmp_path / "ab"
    assert speed_ab.main(["HEAD", str(tum_folder), "--rounds", "1", "-c", "static", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| synthetic_room | this tree |" in text and "| synthetic_room | base |" in text
    assert "synthetic_room: this tree / base = " in text
    # Without uncommitted changes to the product, this tree is HEAD: the same trajectory to the bit.
    clean = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "slam", "frontend", "backend", "configs"],
                           cwd=REPO).returncode == 0
    if clean:
        assert "trajectories the same bits" in text
    assert (out / "speed_ab.md").read_text().startswith("this tree vs HEAD")
    assert {p.name for p in out.iterdir()} >= {"synthetic_room_this_0", "synthetic_room_base_0"}
    worktrees = subprocess.run(["git", "worktree", "list"], cwd=REPO, capture_output=True, text=True).stdout
    assert ".speed_ab_" not in worktrees and not list(REPO.parent.glob(".speed_ab_*"))
