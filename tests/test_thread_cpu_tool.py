"""tools/thread_cpu.py: named functions charged the tracking thread's CPU over a run, calls on other threads
left out, and a wrong target named."""
from __future__ import annotations

import sys
import threading
import types
from collections import Counter, defaultdict

import pytest

from conftest import load_tool, real_sequence

tool = load_tool("thread_cpu")


def test_a_wrapped_function_is_charged_on_the_main_thread_only():
    class Work:
        @staticmethod
        def step(n):
            return sum(i * i for i in range(n))

    module = types.ModuleType("thread_cpu_probe")
    module.Work = Work
    sys.modules["thread_cpu_probe"] = module
    spent, calls = defaultdict(float), Counter()
    tool.wrap("thread_cpu_probe:Work.step", spent, calls, threading.get_ident())
    assert Work.step(20000) == sum(i * i for i in range(20000))      # still the function, as a staticmethod
    other = threading.Thread(target=Work.step, args=(20000,))
    other.start()
    other.join()
    assert calls["thread_cpu_probe:Work.step"] == 1
    assert spent["thread_cpu_probe:Work.step"] > 0
    with pytest.raises(SystemExit, match="module:qualified.name"):
        tool.wrap("thread_cpu_probe.Work.step", spent, calls, threading.get_ident())


@pytest.mark.slow
def test_a_run_prints_each_targets_cost_per_frame(tmp_path, capsys):
    sequence = real_sequence("rgbd_dataset_freiburg1_xyz_first37")
    assert tool.main([str(sequence), "frontend.tracker:Tracker.track", "frontend.dynamic.keyframe_masks:fused_pixel_mask",
                      "--output", str(tmp_path / "run")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("rgbd_dataset_freiburg1_xyz_first37: main thread CPU")
    rows = {line.split()[-1]: line.split() for line in lines[1:]}
    assert int(rows["frontend.tracker:Tracker.track"][4]) >= 30          # every tracked frame after the first
    assert float(rows["frontend.tracker:Tracker.track"][0]) > 0
    assert int(rows["frontend.dynamic.keyframe_masks:fused_pixel_mask"][4]) >= 2     # two per keyframe
