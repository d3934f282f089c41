"""Files of a bake: publishing under a temporary name, cleaning what killed writers left, safe names.

A finished file is never written in place: it is written under a temporary name unique to the
writing process (``.<name>.<host>-<pid>-<token>.partial<suffix>``, in the same folder, so the
rename cannot cross file systems), flushed to disk, then renamed over the final name in one
atomic step. A reader therefore sees either the previous file or the complete new one. A writer
that fails or is interrupted removes its temporary file; one killed outright (SIGKILL, power
loss) leaves it behind, and :func:`remove_stale_temps` removes it later once its process is
gone. Temporary files of live processes (another shard of the same bake) are left alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import secrets
import socket
import unicodedata
import zipfile
from pathlib import Path
from typing import Iterator

import numpy as np

_HOST = re.sub(r"[^A-Za-z0-9]", "-", socket.gethostname())[:40] or "host"
_TEMP = re.compile(r"^\.(?P<final>.+)\.(?P<host>[A-Za-z0-9-]+)-(?P<pid>\d+)-(?P<token>[0-9a-f]{8})\.partial(\.\w+)?$")


def temp_path(path: str | os.PathLike) -> Path:
    """A temporary name beside ``path``, unique to this process and call, with the same suffix
    (image writers choose the format by the suffix)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{_HOST}-{os.getpid()}-{secrets.token_hex(4)}.partial{path.suffix}")


def is_temp(path: str | os.PathLike) -> bool:
    """Whether ``path`` is named like a temporary file of :func:`temp_path`."""
    return _TEMP.match(Path(path).name) is not None


def _fsync(path: Path, directory: bool = False) -> None:
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        if directory:  # not every platform opens folders; the rename itself is still atomic
            return
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(fd)


@contextlib.contextmanager
def publishing(path: str | os.PathLike) -> Iterator[Path]:
    """Write to the yielded temporary path; on success it is flushed and renamed to ``path``.

    On any exception (including an interrupt) the temporary file is removed and the exception
    propagates; ``path`` is untouched. ``path`` must not be a folder.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"cannot write {path}: it is a folder; give a file name, e.g. {path / 'texture.exr'}")
    tmp = temp_path(path)
    try:
        yield tmp
        if not tmp.is_file():
            raise FileNotFoundError(f"nothing was written to {tmp} for {path}")
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync(path.parent, directory=True)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Publish ``data`` as ``path`` (temporary name, flush, atomic rename)."""
    with publishing(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


def save_arrays(path: str | os.PathLike, **arrays) -> None:
    """``np.savez`` of ``arrays`` at ``path`` (its folder made), published as :func:`publishing` does: a reader
    (another process, a later session) sees the previous file or the complete new one. For cache entries."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with publishing(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def load_arrays(path: str | os.PathLike) -> dict | None:
    """The arrays of an ``.npz`` file (:func:`save_arrays`), or None when it is missing or cannot be read (a cache
    entry damaged on disk is a miss, not an error)."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
        return None


def _process_gone(host: str, pid: int) -> bool:
    if host != _HOST:
        return False  # another machine's writer: it cannot be checked from here, so it is left alone
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # alive, owned by someone else
    return False


def remove_stale_temps(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files in ``folder`` whose writing process (on this machine) is gone."""
    removed = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = _TEMP.match(entry.name)
        if m and _process_gone(m.group("host"), int(m.group("pid"))):
            with contextlib.suppress(OSError):
                entry.unlink()
                removed.append(entry)
    return removed


_RESERVED = {"CON", "PRN", "AUX", "NUL", *(f"COM{i}" for i in range(1, 10)), *(f"LPT{i}" for i in range(1, 10))}
_MAX_STEM_BYTES = 120


def safe_file_name(name: str) -> str:
    """A file-name stem for ``name`` that stays inside its folder on every platform.

    Letters (any script), digits and ``- _ . ( ) +`` and spaces are kept; anything else (path
    separators, control characters, ``:*?"<>|``) becomes ``_``; leading dots and spaces and
    trailing dots and spaces are dropped, and over-long names are cut. Whenever the result differs
    from ``name`` it ends in ``-`` and eight hex digits of the name's SHA-256, so two different
    names never share a file (``a/b`` and ``a_b`` give ``a_b-1c5a40e4`` and ``a_b``).
    """
    if not isinstance(name, str):
        raise TypeError(f"a file name must be a string, got {type(name).__name__} {name!r}")
    text = unicodedata.normalize("NFC", name)
    kept = "".join(c if (c.isalnum() or c in "-_.()+ ") and c.isprintable() else "_" for c in text)
    kept = kept.lstrip(". ").rstrip(". ")
    while len(kept.encode("utf-8")) > _MAX_STEM_BYTES:
        kept = kept[:-1]
    if kept == name and kept and kept.split(".")[0].upper() not in _RESERVED:
        return kept
    digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:8]
    return f"{kept or 'unnamed'}-{digest}"
