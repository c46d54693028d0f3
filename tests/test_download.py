"""``dynslam download``: fetch, resume, verify and unpack archives from a local HTTP server (no network).

The server is the ``server`` fixture of conftest.py (Range support, records each Range header)."""
from __future__ import annotations

import hashlib
import io
import socket
import tarfile
import warnings
import zipfile
from pathlib import Path

import pytest

from slam.cli import main
from slam.datasets import SyntheticSequence, TumDataset, write_tum_layout
from slam.run.download import DownloadError, archive_spec, download_sequence, unpack

TUM_FOLDER = "rgbd_dataset_freiburg1_tiny"
BONN_FOLDER = "rgbd_bonn_tiny"


@pytest.fixture(scope="module")
def tum_folder(tmp_path_factory) -> Path:
    return write_tum_layout(SyntheticSequence(n_frames=3, width=64, height=48, fx=60, fy=60, cx=32, cy=24),
                            tmp_path_factory.mktemp("src") / TUM_FOLDER)


@pytest.fixture(scope="module")
def tgz_bytes(tum_folder) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        tar.add(tum_folder, arcname=TUM_FOLDER)
    return buffer.getvalue()


@pytest.fixture(scope="module")
def zip_bytes(tum_folder) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(tum_folder.rglob("*")):
            zf.write(path, f"{BONN_FOLDER}/{path.relative_to(tum_folder)}")
    return buffer.getvalue()


def serve_tum(server, data: bytes) -> None:
    server.files[f"/freiburg1/{TUM_FOLDER}.tgz"] = data


def quiet(_done, _total):
    pass


def test_sequence_names_map_to_the_official_urls(monkeypatch):
    monkeypatch.delenv("DYNSLAM_DOWNLOAD_BASE_URL", raising=False)
    for name in ("freiburg3_walking_xyz", "rgbd_dataset_freiburg3_walking_xyz"):
        spec = archive_spec("tum", name)
        assert spec.url == ("https://cvg.cit.tum.de/rgbd/dataset/freiburg3/"
                            "rgbd_dataset_freiburg3_walking_xyz.tgz")
        assert spec.folder == "rgbd_dataset_freiburg3_walking_xyz"
    for name in ("crowd", "rgbd_bonn_crowd"):
        assert archive_spec("bonn", name).url == \
            "https://www.ipb.uni-bonn.de/html/projects/rgbd_dynamic2019/rgbd_bonn_crowd.zip"
    monkeypatch.setenv("DYNSLAM_DOWNLOAD_BASE_URL", "http://mirror/x/")
    assert archive_spec("bonn", "crowd").url == "http://mirror/x/rgbd_bonn_crowd.zip"


@pytest.mark.parametrize("kind, name, words", [("kinect", "xyz", "unknown dataset kind"),
                                                ("tum", "xyz", "freiburg1_xyz"),
                                                ("bonn", "../etc", "bad sequence name")])
def test_bad_kind_or_name_is_a_clear_error(kind, name, words):
    with pytest.raises(DownloadError, match=words):
        archive_spec(kind, name)


def test_tum_download_unpacks_a_folder_tum_dataset_opens(server, tgz_bytes, tmp_path):
    serve_tum(server, tgz_bytes)
    folder = download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url, progress=quiet)
    assert folder == tmp_path / TUM_FOLDER
    assert len(TumDataset(folder)) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == [TUM_FOLDER], "archive and temporaries removed"
    assert server.ranges == [None]


def test_bonn_zip_download_via_the_environment_variable(server, zip_bytes, tmp_path, monkeypatch):
    server.files[f"/{BONN_FOLDER}.zip"] = zip_bytes
    monkeypatch.setenv("DYNSLAM_DOWNLOAD_BASE_URL", server.base_url)
    folder = download_sequence("bonn", "tiny", tmp_path, keep_archive=True, progress=quiet)
    assert len(TumDataset(folder)) == 3
    assert (tmp_path / f"{BONN_FOLDER}.zip").read_bytes() == zip_bytes


def test_resume_sends_a_range_request_and_completes_the_file(server, tgz_bytes, tmp_path):
    serve_tum(server, tgz_bytes)
    (tmp_path / f".{TUM_FOLDER}.tgz.part").write_bytes(tgz_bytes[:1000])
    folder = download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url, progress=quiet)
    assert server.ranges == ["bytes=1000-"]
    assert len(TumDataset(folder)) == 3


def test_server_ignoring_range_restarts_the_part(server, tgz_bytes, tmp_path):
    serve_tum(server, tgz_bytes)
    server.ignore_range = True
    (tmp_path / f".{TUM_FOLDER}.tgz.part").write_bytes(b"stale bytes that are not the archive")
    folder = download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url, progress=quiet)
    assert server.ranges[0] is not None
    assert len(TumDataset(folder)) == 3


def test_complete_part_file_answered_416_is_kept(server, tgz_bytes, tmp_path):
    serve_tum(server, tgz_bytes)
    (tmp_path / f".{TUM_FOLDER}.tgz.part").write_bytes(tgz_bytes)
    download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url, progress=quiet)
    assert server.ranges == [f"bytes={len(tgz_bytes)}-"]
    assert (tmp_path / TUM_FOLDER / "rgb.txt").is_file()


def test_interrupted_transfer_keeps_the_part_and_resumes(server, tgz_bytes, tmp_path):
    serve_tum(server, tgz_bytes)
    server.cut_after = 1500
    with pytest.raises(DownloadError, match="resume"):
        download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url, progress=quiet)
    assert (tmp_path / f".{TUM_FOLDER}.tgz.part").stat().st_size == 1500
    assert not (tmp_path / TUM_FOLDER).exists()
    server.cut_after = None
    download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url, progress=quiet)
    assert server.ranges[-1] == "bytes=1500-"


def test_http_404_is_a_clear_error(server, tmp_path):
    with pytest.raises(DownloadError, match=r"HTTP 404.*no such sequence") as info:
        download_sequence("tum", "freiburg2_nothing", tmp_path, base_url=server.base_url, progress=quiet)
    assert f"{server.base_url}/freiburg2/rgbd_dataset_freiburg2_nothing.tgz" in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_connection_refused_names_the_url(tmp_path):
    with socket.socket() as sock:  # a port nobody listens on: bind, read the number, close
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    base = f"http://127.0.0.1:{port}"
    with pytest.raises(DownloadError, match="cannot reach") as info:
        download_sequence("bonn", "crowd", tmp_path, base_url=base, progress=quiet)
    assert f"{base}/rgbd_bonn_crowd.zip" in str(info.value)
    assert "refused" in str(info.value).lower()


@pytest.mark.parametrize("kind", ["tum", "bonn"])
def test_truncated_archive_is_rejected_and_leaves_no_folder(server, tgz_bytes, zip_bytes, tmp_path, kind):
    if kind == "tum":
        serve_tum(server, tgz_bytes[: len(tgz_bytes) // 2])
    else:
        server.files[f"/{BONN_FOLDER}.zip"] = zip_bytes[: len(zip_bytes) // 2]
    with pytest.raises(DownloadError, match="truncated or corrupt"):
        download_sequence(kind, "freiburg1_tiny" if kind == "tum" else "tiny", tmp_path,
                          base_url=server.base_url, progress=quiet)
    assert list(tmp_path.iterdir()) == [], "no folder, no temporary, no corrupt archive left"


def test_checksum_mismatch_deletes_the_download(server, tgz_bytes, tmp_path):
    serve_tum(server, tgz_bytes)
    with pytest.raises(DownloadError, match="md5"):
        download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url,
                          checksum=("md5", "0" * 32), progress=quiet)
    assert list(tmp_path.iterdir()) == []
    good = ("sha256", hashlib.sha256(tgz_bytes).hexdigest())
    download_sequence("tum", "freiburg1_tiny", tmp_path, base_url=server.base_url, checksum=good, progress=quiet)
    assert (tmp_path / TUM_FOLDER / "rgb.txt").is_file()


@pytest.mark.parametrize("member", ["../escape.txt", "/abs/escape.txt", "seq/../../escape.txt"])
def test_path_traversal_members_are_rejected(tmp_path, member):
    archive = tmp_path / "evil.tgz"
    with tarfile.open(archive, "w:gz") as tar:
        info = tarfile.TarInfo(member)
        info.size = 4
        tar.addfile(info, io.BytesIO(b"evil"))
    (tmp_path / "dest").mkdir()
    with pytest.raises(DownloadError, match="unsafe member"):
        unpack(archive, tmp_path / "dest" / "seq")
    assert list((tmp_path / "dest").iterdir()) == []
    assert not (tmp_path / "escape.txt").exists()


def test_zip_traversal_member_is_rejected(tmp_path):
    archive = tmp_path / "evil.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        zf.writestr("../escape.txt", b"evil")
    with pytest.raises(DownloadError, match="unsafe member"):
        unpack(archive, tmp_path / "seq")
    assert not (tmp_path / "seq").exists()


def test_cli_download_prints_the_folder_and_exits_0(server, tgz_bytes, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    serve_tum(server, tgz_bytes)
    code = main(["download", "tum", "freiburg1_tiny", "-o", str(tmp_path), "--base-url", server.base_url])
    out, err = capsys.readouterr()
    assert code == 0
    assert str(tmp_path / TUM_FOLDER) in out
    assert f"{TUM_FOLDER}.tgz" in err, "progress line on stderr"


def test_cli_download_failure_is_one_line_exit_2(server, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    code = main(["download", "bonn", "nothing", "-o", str(tmp_path), "--base-url", server.base_url])
    _, err = capsys.readouterr()
    assert code == 2
    assert "dynslam download: error:" in err and "HTTP 404" in err and "Traceback" not in err


def test_cli_network_failure_is_exit_1(tmp_path, capsys, monkeypatch):
    """Nothing listens on the port: a failure while running (try again later), not a usage error."""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    with socket.socket() as probe:   # a free loopback port, closed again: connections are refused
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    code = main(["download", "tum", "freiburg1_xyz", "-o", str(tmp_path), "--base-url", f"http://127.0.0.1:{port}"])
    _, err = capsys.readouterr()
    assert code == 1
    assert "dynslam download: error: cannot reach" in err and "Traceback" not in err
