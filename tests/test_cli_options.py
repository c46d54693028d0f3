"""CLI smoke tests of the command line itself: ``--help`` (in-process and one real ``dynslam --help``
subprocess), ``dynslam config``, ``--version`` and the options every command shares."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from _cli_helpers import run_cli
from slam.cli import main
from slam.core.config import SlamConfig, load_config

pytestmark = pytest.mark.usefixtures("restore_warning_format")


# --- help / config -----------------------------------------------------------------------------------

def test_dynslam_help_in_a_subprocess():
    exe = shutil.which("dynslam") or str(Path(sys.executable).with_name("dynslam"))
    if not Path(exe).exists():
        pytest.skip("the dynslam console script is not installed (pip install -e .)")
    proc = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    for command in ("run", "demo", "eval", "config"):
        assert command in proc.stdout


def test_help_imports_no_heavy_modules():
    """``dynslam --help`` must stay instant: the heavy libraries load inside the commands only."""
    code = ("import sys\nfrom slam.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('gtsam', 'cv2', 'numpy', 'scipy', 'open3d', 'onnxruntime') if m in sys.modules]\n"
            "assert not heavy, heavy")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def test_config_prints_yaml_that_loads_back(capsys, tmp_path):
    code, out, _ = run_cli(capsys, "config")
    assert code == 0
    path = tmp_path / "printed.yaml"
    path.write_text(out)
    assert load_config(path).to_dict() == SlamConfig().to_dict()


def test_config_with_preset_shows_its_intrinsics(capsys):
    code, out, _ = run_cli(capsys, "config", "-c", "tum_fr1")
    assert code == 0
    data = yaml.safe_load(out)
    assert data["camera"]["fx"] == pytest.approx(517.306408)
    assert data["camera"]["name"] == "tum_fr1"
    assert "517.306408" in out


def test_config_set_override_is_applied(capsys):
    code, out, _ = run_cli(capsys, "config", "--set", "tracking.match_ratio=0.7", "--set", "orb.n_features=1500")
    assert code == 0
    data = yaml.safe_load(out)
    assert data["tracking"]["match_ratio"] == 0.7 and data["orb"]["n_features"] == 1500


def test_config_unknown_preset_exits_2(capsys):
    code, out, err = run_cli(capsys, "config", "-c", "no_such_preset")
    assert code == 2
    assert "no_such_preset" in err and "tum_fr1" in err


# --- conventions -----------------------------------------------------------------------------------

def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.startswith("dynslam ")


@pytest.mark.parametrize("argv", [["-v", "config"], ["config", "-v"], ["config", "--verbose"]])
def test_verbose_before_or_after_the_subcommand(argv, capsys):
    from slam.cli import build_parser

    assert build_parser().parse_args(argv).verbose is True
    assert build_parser().parse_args(["config"]).verbose is False


def test_quiet_after_the_subcommand_for_every_command():
    from slam.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["run", "SEQ", "-q"]).quiet is True
    assert parser.parse_args(["-q", "run", "SEQ"]).quiet is True
    assert parser.parse_args(["eval", "a", "b", "--quiet"]).quiet is True
    assert parser.parse_args(["run", "SEQ"]).quiet is False


def test_every_option_of_every_command_has_help():
    import argparse

    from slam.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    missing = [f"{name} {'/'.join(a.option_strings) or a.dest}" for name, sub in commands.items()
               for a in sub._actions if not a.help and not isinstance(a, argparse._HelpAction)]
    assert not missing, missing


def test_demo_movers_list_every_generator_choice():
    from slam.cli import DEMO_MOVERS
    from slam.datasets.synthetic_movers import MOVER_PRESETS
    from slam.datasets.synthetic_scenes import HARD_SCENES

    assert DEMO_MOVERS == tuple(MOVER_PRESETS) + HARD_SCENES
