"""``dynslam download model``: fetch a detector model from the registry, verified, into the cache.

The file goes to ``<dest>.part`` and continues with an HTTP Range request when a part is there (a
server that ignores Range sends the whole file, which then replaces the part: see
``slam.run.download.fetch``). The finished part must have the pinned size and sha256; then it is
renamed to ``<dest>`` atomically, so ``<dest>`` exists only verified. A part with the wrong size or
digest is deleted, so nothing of a refused download stays behind.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union
from urllib.parse import urlsplit, urlunsplit

from slam.core.atomic_io import fsync_directory
from slam.core.errors import EXIT_RUNTIME_FAILURE
from slam.core.model_files import DEFAULT_MODEL, ModelSpec, model_cache_dir, model_spec
from slam.run.download import CHUNK_BYTES, DownloadError, Progress, ProgressLine, fetch

PathLike = Union[str, Path]


class ModelChecksumError(DownloadError):
    """The downloaded file is not the pinned one (size or sha256): nothing was installed. Exit status 1:
    the request was right, what came back was not (a corrupt transfer, or the server's file changed)."""

    exit_code = EXIT_RUNTIME_FAILURE


@dataclass(frozen=True)
class ModelDownload:
    """Where the model is and whether this call fetched it (False: it was already there, verified)."""

    path: Path
    downloaded: bool
    sha256: str


def model_url(spec: ModelSpec, base_url: Optional[str] = None) -> str:
    """``spec.url``, with its scheme and host replaced by ``base_url`` (a mirror or a test server); a
    path in ``base_url`` is put in front of the original path."""
    if not base_url:
        return spec.url
    base, original = urlsplit(base_url), urlsplit(spec.url)
    if not base.scheme or not base.netloc:
        raise DownloadError(f"--base-url expects scheme://host[:port][/path], got '{base_url}'")
    return urlunsplit((base.scheme, base.netloc, base.path.rstrip("/") + original.path, original.query, ""))


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(CHUNK_BYTES), b""):
            digest.update(block)
    return digest.hexdigest()


def download_model(name: str = DEFAULT_MODEL, dest_dir: Optional[PathLike] = None, base_url: Optional[str] = None,
                   sha256: Optional[str] = None, progress: Optional[Progress] = None) -> ModelDownload:
    """Fetch model ``name`` (``yolox-nano``, ``nanodet-m``) into ``dest_dir`` (default: the cache's
    ``models`` folder) and verify it; returns where it is.

    ``sha256`` replaces the pinned digest (an expert option for a mirror serving another build of the
    model; the pinned size is then not enforced). A file already at the destination with the right
    digest is kept as it is; one with another digest is replaced.
    """
    spec = model_spec(name)
    expected = _parse_sha256(sha256) if sha256 else spec.sha256
    size = None if sha256 else spec.size
    folder = Path(dest_dir).expanduser() if dest_dir is not None else model_cache_dir()
    dest = folder / spec.file_name
    if dest.is_file() and file_sha256(dest) == expected:
        return ModelDownload(dest, False, expected)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DownloadError(f"cannot create the model folder {folder}: {exc.strerror or exc}") from None
    url = model_url(spec, base_url)
    part = dest.with_name(dest.name + ".part")
    if size is not None and part.is_file() and part.stat().st_size > size:
        part.unlink()   # longer than the model can be: not a prefix of it, start over
    line = progress or ProgressLine(spec.file_name)
    try:
        fetch(url, part, line, missing_hint="no such file on the server?")
    finally:
        if isinstance(line, ProgressLine):
            line.end()
    _verify(part, url, spec, expected, size)
    os.replace(part, dest)
    fsync_directory(folder)
    return ModelDownload(dest, True, expected)


def _verify(part: Path, url: str, spec: ModelSpec, expected: str, size: Optional[int]) -> None:
    """Delete ``part`` and raise ModelChecksumError unless it has ``size`` bytes and digest ``expected``."""
    got_size = part.stat().st_size
    got = file_sha256(part) if size is None or got_size == size else None
    if got == expected:
        return
    part.unlink()
    what = f"sha256 {got}" if got is not None else f"{got_size} bytes"
    pinned = f"sha256 {expected}" if got is not None else f"{size} bytes"
    caveat = f" Note: {spec.caveat}." if spec.caveat else ""
    raise ModelChecksumError(f"{url}: the downloaded {spec.file_name} has {what}, expected {pinned}; it was "
                             f"deleted and nothing was installed (a corrupt transfer: run the command again; "
                             f"a changed file on the server: check it and pass --sha256).{caveat}")


def _parse_sha256(text: str) -> str:
    digest = text.strip().lower()
    digest = digest[len("sha256:"):] if digest.startswith("sha256:") else digest
    if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
        raise DownloadError(f"--sha256 expects 64 hexadecimal digits, got '{text}'")
    return digest
