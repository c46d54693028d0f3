"""Fetch and unpack the official TUM RGB-D and Bonn RGB-D Dynamic archives (standard library only).

A download goes to ``<dest>/.<archive>.part`` and continues from where it stopped with an HTTP Range
request (a server that ignores Range sends the whole file again, which then replaces the part). The
finished file is checked against the size the server announced and, when known, a checksum; it is then
unpacked into a temporary folder beside the destination, every member checked to stay inside it, and
renamed into place, so ``<dest>/<sequence>`` either does not exist or is complete.
"""
from __future__ import annotations

import hashlib
import http.client
import os
import re
import shutil
import sys
import tarfile
import tempfile
import time
import urllib.error
import urllib.request
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Callable, Optional, Union

from slam.core.atomic_io import fsync_directory
from slam.core.errors import EXIT_RUNTIME_FAILURE, DynslamError

PathLike = Union[str, Path]
Progress = Callable[[int, Optional[int]], None]

BASE_URL_ENV = "DYNSLAM_DOWNLOAD_BASE_URL"
OFFICIAL_BASE_URLS = {
    "tum": "https://cvg.cit.tum.de/rgbd/dataset",
    "bonn": "https://www.ipb.uni-bonn.de/html/projects/rgbd_dynamic2019",
}
KNOWN_CHECKSUMS: dict[str, tuple[str, str]] = {}
"""Archive name -> (algorithm "md5" or "sha256", hex digest). Neither TUM nor Bonn publishes digests
beside its archives, so this starts empty; entries added here (or ``--checksum``) are enforced."""

CHUNK_BYTES = 1 << 20
TIMEOUT_S = 60.0


class DownloadError(DynslamError, RuntimeError):
    """A sequence could not be fetched, verified or unpacked; the message names the URL or file.
    Exit status 2: the request itself is wrong (name, URL, checksum, archive, 404)."""


class NetworkError(DownloadError):
    """The server could not be reached or the transfer broke off: exit status 1 (run it again)."""

    exit_code = EXIT_RUNTIME_FAILURE


@dataclass(frozen=True)
class ArchiveSpec:
    """Where one sequence's archive lives and what it unpacks to."""

    kind: str        # "tum" or "bonn"
    folder: str      # the sequence folder, e.g. rgbd_dataset_freiburg1_xyz
    archive: str     # the archive's file name, e.g. rgbd_dataset_freiburg1_xyz.tgz
    url: str


def archive_spec(kind: str, sequence: str, base_url: Optional[str] = None) -> ArchiveSpec:
    """URL and names for ``sequence`` of dataset ``kind``.

    TUM names are ``freiburg1_xyz`` or ``rgbd_dataset_freiburg1_xyz`` (the freiburg number picks the
    server folder); Bonn names are ``crowd`` or ``rgbd_bonn_crowd``. ``base_url`` (else
    $DYNSLAM_DOWNLOAD_BASE_URL, else the official server) replaces the server root.
    """
    kind = kind.lower()
    if kind not in OFFICIAL_BASE_URLS:
        raise DownloadError(f"unknown dataset kind '{kind}' (expected one of: {', '.join(OFFICIAL_BASE_URLS)})")
    base = (base_url or os.environ.get(BASE_URL_ENV) or OFFICIAL_BASE_URLS[kind]).rstrip("/")
    name = sequence.strip().strip("/")
    if not name or not re.fullmatch(r"[A-Za-z0-9_\-]+", name):
        raise DownloadError(f"bad sequence name '{sequence}' (letters, digits, '_' and '-' only)")
    if kind == "tum":
        match = re.fullmatch(r"(?:rgbd_dataset_)?freiburg([123])_(\w+)", name)
        if not match:
            raise DownloadError(f"TUM sequence '{sequence}' does not name a camera: expected e.g. "
                                "freiburg1_xyz or rgbd_dataset_freiburg3_walking_xyz")
        number, rest = match.groups()
        folder = f"rgbd_dataset_freiburg{number}_{rest}"
        return ArchiveSpec(kind, folder, f"{folder}.tgz", f"{base}/freiburg{number}/{folder}.tgz")
    folder = name if name.startswith("rgbd_bonn_") else f"rgbd_bonn_{name}"
    return ArchiveSpec(kind, folder, f"{folder}.zip", f"{base}/{folder}.zip")


def download_sequence(kind: str, sequence: str, dest: PathLike = ".", base_url: Optional[str] = None,
                      checksum: Optional[tuple[str, str]] = None, keep_archive: bool = False,
                      progress: Optional[Progress] = None) -> Path:
    """Download, verify and unpack one sequence into ``dest``; returns the sequence folder.

    An existing ``<dest>/<sequence>`` is returned untouched (unpacking is atomic, so it is complete).
    ``checksum`` is (algorithm, hex digest); without it KNOWN_CHECKSUMS is consulted.
    """
    spec = archive_spec(kind, sequence, base_url)
    dest = Path(dest)
    target = dest / spec.folder
    if target.is_dir():
        return target
    dest.mkdir(parents=True, exist_ok=True)
    archive = dest / spec.archive
    if not archive.is_file():
        part = dest / f".{spec.archive}.part"
        line = progress or ProgressLine(spec.archive)
        try:
            fetch(spec.url, part, line)
        finally:
            if isinstance(line, ProgressLine):
                line.end()
        verify_checksum(part, checksum or KNOWN_CHECKSUMS.get(spec.archive))
        os.replace(part, archive)
    unpack(archive, target)
    if not keep_archive:
        archive.unlink()
    return target


def fetch(url: str, part: Path, progress: Progress, missing_hint: str = "no such sequence on the server?") -> int:
    """Download ``url`` into ``part``, continuing an existing part file; returns the final size.

    Raises DownloadError naming the URL for network failures, HTTP errors and a size that differs
    from the one announced; the part file is kept for the next attempt unless it is known bad.
    """
    have = part.stat().st_size if part.is_file() else 0
    request = urllib.request.Request(url, headers={"User-Agent": "dynslam-download"})
    if have:
        request.add_header("Range", f"bytes={have}-")
    try:
        response = urllib.request.urlopen(request, timeout=TIMEOUT_S)
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and have:
            return _range_not_satisfiable(url, part, have, exc, progress, missing_hint)
        error = DownloadError if 400 <= exc.code < 500 else NetworkError   # 4xx: the request; 5xx: the server
        raise error(f"{url}: HTTP {exc.code} {exc.reason}"
                    + (f" ({missing_hint})" if exc.code == 404 else "")) from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as exc:
        reason = getattr(exc, "reason", exc)
        raise NetworkError(f"cannot reach {url}: {reason}") from None
    except ValueError as exc:  # urllib's "unknown url type"
        raise DownloadError(f"bad URL {url}: {exc}") from None
    with response:
        start, total = _response_range(response, have)  # start 0 after a resume: Range was ignored
        _stream(response, url, part, start, total, progress)
    size = part.stat().st_size
    if total is not None and size != total:
        raise NetworkError(f"{url}: got {size} of {total} bytes; run the command again to resume")
    return size


def _response_range(response, have: int) -> tuple[int, Optional[int]]:
    """(offset the body starts at, full size or None) from a 200 or 206 response."""
    if response.status == 206:
        match = re.fullmatch(r"bytes (\d+)-\d+/(\d+|\*)", response.headers.get("Content-Range", "").strip())
        if not match or int(match.group(1)) != have:
            raise DownloadError(f"{response.url}: unexpected Content-Range "
                                f"'{response.headers.get('Content-Range')}' for a resume at byte {have}")
        return have, None if match.group(2) == "*" else int(match.group(2))
    length = response.headers.get("Content-Length")
    return 0, int(length) if length and length.isdigit() else None


def _stream(response, url: str, part: Path, start: int, total: Optional[int], progress: Progress) -> None:
    """Write the body into ``part`` from byte ``start`` (0 restarts it), fsynced so a stop keeps the bytes."""
    done = start
    with open(part, "r+b" if part.exists() else "wb") as out:
        out.truncate(start)
        out.seek(start)
        progress(done, total)
        while True:
            try:
                chunk = response.read(CHUNK_BYTES)
            except (OSError, http.client.HTTPException) as exc:  # reset, timeout, IncompleteRead
                progress(done, total)
                raise NetworkError(f"{url}: connection lost after {done} bytes ({exc.__class__.__name__}: "
                                    f"{exc}); run the command again to resume") from None
            if not chunk:
                break
            out.write(chunk)
            done += len(chunk)
            progress(done, total)
        out.flush()
        os.fsync(out.fileno())
    if total is None:
        progress(done, done)  # size unknown until now: end the progress line


def _range_not_satisfiable(url: str, part: Path, have: int, exc: urllib.error.HTTPError,
                           progress: Progress, missing_hint: str) -> int:
    """HTTP 416 on resume: the part is already complete (size matches) or stale (start over)."""
    match = re.fullmatch(r"bytes \*/(\d+)", (exc.headers.get("Content-Range") or "").strip())
    if match and int(match.group(1)) == have:
        progress(have, have)
        return have
    part.unlink()
    return fetch(url, part, progress, missing_hint)


def verify_checksum(path: Path, checksum: Optional[tuple[str, str]]) -> None:
    """Raise DownloadError (and delete ``path``) when its digest differs from ``checksum``."""
    if checksum is None:
        return
    algorithm, expected = checksum[0].lower(), checksum[1].lower()
    if algorithm not in ("md5", "sha256"):
        raise DownloadError(f"unsupported checksum algorithm '{algorithm}' (md5 or sha256)")
    digest = hashlib.new(algorithm)
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(CHUNK_BYTES), b""):
            digest.update(block)
    if digest.hexdigest() != expected:
        path.unlink()
        raise DownloadError(f"{path}: {algorithm} {digest.hexdigest()} differs from the expected {expected}; "
                            "the corrupt download was deleted, run the command again")


def parse_checksum(text: str) -> tuple[str, str]:
    """'md5:HEX' or 'sha256:HEX' -> (algorithm, digest)."""
    algorithm, _, digest = text.partition(":")
    if algorithm.lower() not in ("md5", "sha256") or not re.fullmatch(r"[0-9a-fA-F]+", digest):
        raise DownloadError(f"--checksum expects md5:HEX or sha256:HEX, got '{text}'")
    return algorithm.lower(), digest.lower()


def unpack(archive: Path, target: Path) -> Path:
    """Unpack a .tgz or .zip into ``target`` atomically; a corrupt archive is deleted.

    Members go to a temporary folder beside ``target``; an archive holding a single top-level folder
    (as TUM's and Bonn's do) has that folder renamed to ``target``, otherwise the temporary folder is.
    """
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".unpacking", dir=target.parent))
    try:
        if archive.name.endswith((".tgz", ".tar.gz", ".tar")):
            _extract_tar(archive, staging)
        elif archive.suffix == ".zip":
            _extract_zip(archive, staging)
        else:
            raise DownloadError(f"{archive}: unknown archive type (expected .tgz or .zip)")
        entries = list(staging.iterdir())
        root = entries[0] if len(entries) == 1 and entries[0].is_dir() else staging
        os.replace(root, target)
        fsync_directory(target.parent)
    except (tarfile.TarError, zipfile.BadZipFile, zlib.error, EOFError) as exc:
        archive.unlink(missing_ok=True)
        raise DownloadError(f"{archive}: truncated or corrupt archive ({exc}); it was deleted, run the "
                            "command again to download it afresh") from None
    except OSError as exc:
        raise DownloadError(f"{archive}: cannot unpack into {target.parent}: {exc}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


def _check_member(archive: Path, name: str) -> None:
    """Reject absolute paths and '..' components: an archive must not write outside its folder."""
    path = PurePosixPath(name.replace("\\", "/"))
    if path.is_absolute() or ".." in path.parts or re.match(r"^[A-Za-z]:", name):
        raise DownloadError(f"{archive}: unsafe member '{name}' would be written outside the destination; "
                            "refusing to unpack")


def _extract_tar(archive: Path, staging: Path) -> None:
    with tarfile.open(archive, "r:*") as tar:
        members = tar.getmembers()  # reads the whole archive: a truncated one fails here, before writing
        for member in members:
            _check_member(archive, member.name)
            if not (member.isfile() or member.isdir()):
                raise DownloadError(f"{archive}: member '{member.name}' is a link or device; refusing to unpack")
        for member in members:
            tar.extract(member, staging, set_attrs=False, **_tar_filter())


def _tar_filter() -> dict:
    """Python's own 'data' filter where this Python has it (3.11.4+), as a second guard."""
    return {"filter": "data"} if hasattr(tarfile, "data_filter") else {}


def _extract_zip(archive: Path, staging: Path) -> None:
    with zipfile.ZipFile(archive) as zf:
        for name in zf.namelist():
            _check_member(archive, name)
        bad = zf.testzip()  # CRC of every member, before anything is written
        if bad is not None:
            raise zipfile.BadZipFile(f"member '{bad}' fails its CRC check")
        zf.extractall(staging)


class ProgressLine:
    """'\\r<name>  12.3/428.0 MB  3%' on stderr, redrawn at most every 0.5 s, ended by a newline."""

    def __init__(self, name: str, stream=None, interval_s: float = 0.5) -> None:
        self.name, self.stream, self.interval_s = name, stream or sys.stderr, interval_s
        self._last = 0.0
        self._line_open = False

    def __call__(self, done: int, total: Optional[int]) -> None:
        now = time.monotonic()
        finished = total is not None and done >= total
        if not finished and now - self._last < self.interval_s:
            return
        self._last = now
        size = f"{done / 1e6:.1f}/{total / 1e6:.1f} MB  {100 * done / max(total, 1):3.0f}%" if total else \
            f"{done / 1e6:.1f} MB"
        self.stream.write(f"\r{self.name}  {size}" + ("\n" if finished else ""))
        self.stream.flush()
        self._line_open = not finished

    def end(self) -> None:
        """Finish an unfinished line (a failed transfer) so the error message starts on its own."""
        if self._line_open:
            self.stream.write("\n")
            self.stream.flush()
            self._line_open = False
