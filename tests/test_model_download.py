"""``dynslam download model``: the registry, the cache folder, and fetching from a local HTTP server.

The ``server`` fixture (conftest.py) serves files on 127.0.0.1 with Range support and records every
Range header. The registry's pinned digest and size are patched in-process (``pinned``) for a test
file, so no test needs the network or the real model.
"""
from __future__ import annotations

import dataclasses
import hashlib
import socket
import warnings
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

from frontend.model_lookup import locate_model
from slam.cli import main
from slam.core import model_files
from slam.core.dynamic_config import DetectorConfig
from slam.core.model_files import MODELS, UnknownModelError, cache_root, model_spec
from slam.run.download import DownloadError
from slam.run.model_download import ModelChecksumError, download_model, model_url

FAKE_MODEL = np.random.default_rng(7).bytes(300_000)   # stands in for an ONNX file: only bytes matter here
FILE = "yolox_nano_416.onnx"


def quiet(_done, _total):
    pass


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    """An empty cache ($DYNSLAM_CACHE_DIR) and no model given through the environment."""
    monkeypatch.setenv("DYNSLAM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("DYNSLAM_DETECTOR_MODEL", raising=False)
    return tmp_path / "cache" / "models"


def pinned(monkeypatch, server, body: bytes = FAKE_MODEL, name: str = "yolox-nano") -> str:
    """Pin ``body`` as the registry's file for ``name`` and serve it at the entry's URL path."""
    spec = MODELS[name]
    monkeypatch.setitem(MODELS, name, dataclasses.replace(spec, sha256=hashlib.sha256(body).hexdigest(),
                                                          size=len(body)))
    server.files[urlsplit(spec.url).path] = body
    return urlsplit(spec.url).path


def test_registry_names_and_pins():
    assert model_spec("yolox-nano") is model_spec("yolox_nano") is MODELS["yolox-nano"]
    assert model_spec("nanodet").name == "nanodet-m"
    for spec in MODELS.values():
        assert len(spec.sha256) == 64 and spec.size > 1_000_000 and spec.url.startswith("https://")
        assert spec.licence and spec.upstream
    assert MODELS["yolox-nano"].download_command == "dynslam download model yolox-nano"
    with pytest.raises(UnknownModelError, match="yolox-nano, nanodet-m"):
        model_spec("yolov8")


@pytest.mark.parametrize("name", ["yolox-nano", "nanodet-m"])
def test_pins_match_the_development_copies(name):
    """The pins were taken from ../shared/models: they must stay equal to those files."""
    from conftest import MODELS as MODEL_DIR, require_shared

    spec = MODELS[name]
    path = require_shared(MODEL_DIR / spec.file_name, f"detector model {name}")
    assert path.stat().st_size == spec.size
    assert hashlib.sha256(path.read_bytes()).hexdigest() == spec.sha256


def test_cache_root_follows_the_platform_conventions(tmp_path):
    home = Path("/home/u")
    assert cache_root({"DYNSLAM_CACHE_DIR": "/c"}, "linux", home) == Path("/c")
    assert cache_root({"DYNSLAM_CACHE_DIR": "/c"}, "darwin", home) == Path("/c")
    assert cache_root({}, "linux", home) == home / ".cache" / "dynslam"
    assert cache_root({"XDG_CACHE_HOME": "/x"}, "linux", home) == Path("/x/dynslam")
    assert cache_root({"XDG_CACHE_HOME": "rel"}, "linux", home) == home / ".cache" / "dynslam", \
        "a relative XDG_CACHE_HOME is ignored (XDG spec)"
    assert cache_root({"XDG_CACHE_HOME": "/x"}, "darwin", home) == home / "Library" / "Caches" / "dynslam"
    assert cache_root({"LOCALAPPDATA": "/L"}, "win32", home) == Path("/L") / "dynslam" / "Cache"
    assert cache_root({}, "win32", home) == home / "AppData" / "Local" / "dynslam" / "Cache"


def test_base_url_replaces_scheme_and_host_only():
    spec = MODELS["yolox-nano"]
    path = urlsplit(spec.url).path
    assert model_url(spec) == spec.url
    assert model_url(spec, "http://127.0.0.1:8000") == f"http://127.0.0.1:8000{path}"
    assert model_url(spec, "https://mirror.example/models/") == f"https://mirror.example/models{path}"
    with pytest.raises(DownloadError, match="--base-url"):
        model_url(spec, "mirror.example")


def test_download_verifies_caches_and_the_next_lookup_finds_it(server, cache, monkeypatch):
    path = pinned(monkeypatch, server)
    result = download_model("yolox-nano", base_url=server.base_url, progress=quiet)
    assert result.downloaded and result.path == cache / FILE
    assert result.path.read_bytes() == FAKE_MODEL
    assert sorted(p.name for p in cache.iterdir()) == [FILE], "no .part left"
    location = locate_model(DetectorConfig())
    assert (location.path, location.source, location.explicit) == (cache / FILE, "cache", False)
    again = download_model("yolox_nano", base_url=server.base_url, progress=quiet)
    assert not again.downloaded and again.path == result.path
    assert server.ranges == [None], f"one request to {path}, none for the verified copy"


def test_wrong_checksum_is_refused_and_leaves_nothing(server, cache, monkeypatch):
    pinned(monkeypatch, server)
    tampered = bytearray(FAKE_MODEL)
    tampered[1000] ^= 0xFF   # same size, other bytes: only the digest can tell
    server.files[urlsplit(MODELS["yolox-nano"].url).path] = bytes(tampered)
    with pytest.raises(ModelChecksumError, match="nothing was installed") as info:
        download_model("yolox-nano", base_url=server.base_url, progress=quiet)
    assert info.value.exit_code == 1
    assert MODELS["yolox-nano"].sha256 in str(info.value) and hashlib.sha256(tampered).hexdigest() in str(info.value)
    assert list(cache.iterdir()) == [], "neither the model nor its .part"


def test_wrong_size_is_refused_and_leaves_nothing(server, cache, monkeypatch):
    pinned(monkeypatch, server)
    server.files[urlsplit(MODELS["yolox-nano"].url).path] = FAKE_MODEL + b"extra"
    with pytest.raises(ModelChecksumError, match=f"{len(FAKE_MODEL) + 5} bytes, expected {len(FAKE_MODEL)} bytes"):
        download_model("yolox-nano", base_url=server.base_url, progress=quiet)
    assert list(cache.iterdir()) == []


def test_resume_from_a_partial_part_file(server, cache, monkeypatch):
    pinned(monkeypatch, server)
    cache.mkdir(parents=True)
    (cache / f"{FILE}.part").write_bytes(FAKE_MODEL[:120_000])
    result = download_model("yolox-nano", base_url=server.base_url, progress=quiet)
    assert server.ranges == ["bytes=120000-"]
    assert result.path.read_bytes() == FAKE_MODEL and not (cache / f"{FILE}.part").exists()


def test_interrupted_transfer_keeps_the_part_then_resumes(server, cache, monkeypatch):
    pinned(monkeypatch, server)
    server.cut_after = 50_000
    with pytest.raises(DownloadError, match="resume"):
        download_model("yolox-nano", base_url=server.base_url, progress=quiet)
    assert (cache / f"{FILE}.part").stat().st_size == 50_000 and not (cache / FILE).exists()
    server.cut_after = None
    assert download_model("yolox-nano", base_url=server.base_url, progress=quiet).path.read_bytes() == FAKE_MODEL
    assert server.ranges[-1] == "bytes=50000-"


def test_server_ignoring_range_restarts_the_part(server, cache, monkeypatch):
    pinned(monkeypatch, server)
    server.ignore_range = True
    cache.mkdir(parents=True)
    (cache / f"{FILE}.part").write_bytes(b"not the start of the model")
    result = download_model("yolox-nano", base_url=server.base_url, progress=quiet)
    assert server.ranges == ["bytes=26-"] and result.path.read_bytes() == FAKE_MODEL


def test_a_corrupt_cached_model_is_replaced(server, cache, monkeypatch):
    pinned(monkeypatch, server)
    cache.mkdir(parents=True)
    (cache / FILE).write_bytes(b"damaged")
    result = download_model("yolox-nano", base_url=server.base_url, progress=quiet)
    assert result.downloaded and (cache / FILE).read_bytes() == FAKE_MODEL


def test_dir_option_and_expert_sha256(server, tmp_path, monkeypatch, capsys):
    """--sha256 accepts another build of the model (the pinned size is then not enforced)."""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    server.files[urlsplit(MODELS["nanodet-m"].url).path] = b"another build"
    digest = hashlib.sha256(b"another build").hexdigest()
    code = main(["download", "model", "nanodet-m", "--dir", str(tmp_path / "m"), "--base-url", server.base_url,
                 "--sha256", digest])
    out, err = capsys.readouterr()
    assert code == 0 and out.strip() == str(tmp_path / "m" / "nanodet_m_320.onnx")
    assert (tmp_path / "m" / "nanodet_m_320.onnx").read_bytes() == b"another build"
    assert main(["download", "model", "--sha256", "xyz", "--dir", str(tmp_path)]) == 2
    assert "--sha256 expects 64 hexadecimal digits" in capsys.readouterr().err


def test_cli_downloads_then_says_it_is_present(server, cache, monkeypatch, capsys):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    pinned(monkeypatch, server)
    assert main(["download", "model", "yolox-nano", "--base-url", server.base_url]) == 0
    out, err = capsys.readouterr()
    assert out.strip() == str(cache / FILE)
    assert f"{FILE} downloaded and verified (sha256 {hashlib.sha256(FAKE_MODEL).hexdigest()})" in err
    assert main(["download", "model", "--base-url", server.base_url]) == 0, "yolox-nano is the default"
    out, err = capsys.readouterr()
    assert out.strip() == str(cache / FILE) and "already present and verified" in err
    assert (cache / FILE).read_bytes() == FAKE_MODEL


def test_cli_checksum_mismatch_is_exit_1_and_leaves_nothing(server, cache, monkeypatch, capsys):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    pinned(monkeypatch, server)
    server.files[urlsplit(MODELS["yolox-nano"].url).path] = FAKE_MODEL[::-1]
    assert main(["download", "model", "yolox-nano", "--base-url", server.base_url]) == 1
    err = capsys.readouterr().err
    assert "dynslam download: error:" in err and "nothing was installed" in err and "Traceback" not in err
    assert not cache.exists() or list(cache.iterdir()) == []


def test_cli_server_error_is_exit_1_naming_the_url(server, cache, monkeypatch, capsys):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    path = pinned(monkeypatch, server)
    server.fail_status = 503
    assert main(["download", "model", "yolox-nano", "--base-url", server.base_url]) == 1
    err = capsys.readouterr().err
    assert f"{server.base_url}{path}: HTTP 503" in err and "Traceback" not in err
    assert not cache.exists() or list(cache.iterdir()) == []


def test_cli_unreachable_server_is_exit_1_naming_the_url(cache, monkeypatch, capsys):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    with socket.socket() as probe:   # a free loopback port, closed again: connections are refused
        probe.bind(("127.0.0.1", 0))
        base = f"http://127.0.0.1:{probe.getsockname()[1]}"
    assert main(["download", "model", "--base-url", base]) == 1
    err = capsys.readouterr().err
    assert f"cannot reach {base}{urlsplit(MODELS['yolox-nano'].url).path}" in err


def test_cli_unknown_model_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as info:
        main(["download", "model", "yolov8"])
    assert info.value.code == 2 and "invalid choice: 'yolov8'" in capsys.readouterr().err


def test_cli_model_names_match_the_registry():
    from slam import cli

    assert cli.MODEL_NAMES == tuple(model_files.MODELS)
