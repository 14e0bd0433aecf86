"""The review computations shared between the app's processes: ``<data dir>/cache/<name>/``.

A frame's review (leave-one-out labels, renderings, figures, disagreement PNG) costs a second or
more of CPU on a 20 MP frame. Each API process, the lifting worker's after-fill refresh and the
background prefetch used to keep their own copies in memory, so with ``occufly serve --workers
2`` the page's parallel requests for a frame (agreement, disagreement) computed it once per
process that received one, the next-frame prefetch helped only the process that ran it, and
the after-fill refresh of the list's frames helped no API process at all.

An entry is one file named by a digest of its key (the frame, its mask version and the stamps
of every file it is computed from; see :mod:`app.review.service`), written atomically. One
computation per key across processes: the computing process holds an exclusive ``flock`` on
``<digest>.lock``; a process that waited for it reads the entry instead of computing it again.
Values are JSON (numbers, strings, lists, dicts; numpy scalars and arrays are written as
numbers and lists) with ``bytes`` values kept as base64, or plain ``bytes``: no pickle.
The folder is pruned to ``max_bytes``, oldest entries first (a new stamp makes the old
entries unreachable: they only wait to be pruned).
"""

from __future__ import annotations

import base64
import fcntl
import hashlib
import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from occufly.fsutil import atomic_write_bytes

log = logging.getLogger(__name__)

_BYTES = b"B"  # the entry's first byte: raw bytes follow
_JSON = b"J"   # JSON follows
_MAX_BYTES = 512 * 2**20
_STALE_LOCK_S = 600.0  # lock files older than this and without an entry are pruned


def _default(o: Any) -> Any:  # noqa: ANN401
    if isinstance(o, (bytes, bytearray)):
        return {"__bytes__": base64.b64encode(bytes(o)).decode("ascii")}
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"review cache: cannot store {type(o).__name__}")


def _hook(d: dict) -> Any:  # noqa: ANN401
    if len(d) == 1 and "__bytes__" in d:
        return base64.b64decode(d["__bytes__"])
    return d


def encode(value: Any) -> bytes:  # noqa: ANN401
    if isinstance(value, (bytes, bytearray)):
        return _BYTES + bytes(value)
    return _JSON + json.dumps(value, default=_default, separators=(",", ":")).encode()


def decode(data: bytes) -> Any:  # noqa: ANN401
    if data[:1] == _BYTES:
        return data[1:]
    if data[:1] == _JSON:
        return json.loads(data[1:], object_hook=_hook)
    raise ValueError("not a review cache entry")


class DiskCache:
    """Entries under ``<data_dir>/cache/<name>/`` (see the module's docstring)."""

    def __init__(self, name: str, max_bytes: int = _MAX_BYTES) -> None:
        self.name = name
        self.max_bytes = max_bytes

    def folder(self, data_dir: str | Path) -> Path:
        return Path(data_dir) / "cache" / self.name

    @staticmethod
    def digest(key: Any) -> str:  # noqa: ANN401
        return hashlib.sha256(repr(key).encode()).hexdigest()[:40]

    def _entry(self, data_dir: str | Path, key: Any) -> Path:  # noqa: ANN401
        return self.folder(data_dir) / f"{self.digest(key)}.entry"

    def read(self, data_dir: str | Path, key: Any) -> Any | None:  # noqa: ANN401
        """The stored value of ``key``, or None (none stored, or unreadable)."""
        p = self._entry(data_dir, key)
        try:
            return decode(p.read_bytes())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            log.warning("review cache: unreadable entry %s", p, exc_info=True)
            return None

    def has(self, data_dir: str | Path, key: Any) -> bool:  # noqa: ANN401
        return self._entry(data_dir, key).is_file()

    def get(self, data_dir: str | Path, key: Any, compute: Callable[[], Any],  # noqa: ANN401
            valid: Callable[[], bool] | None = None) -> Any:  # noqa: ANN401
        """The stored value of ``key``, else ``compute()`` -- once across processes: the
        computing process holds the key's lock, a process waiting on it then reads. With
        ``valid``, a computed value is stored only where ``valid()`` (called after it) holds."""
        v = self.read(data_dir, key)
        if v is not None:
            return v
        d = self.folder(data_dir)
        d.mkdir(parents=True, exist_ok=True)
        dig = self.digest(key)
        with open(d / f"{dig}.lock", "a+b") as lk:
            fcntl.flock(lk, fcntl.LOCK_EX)
            try:
                v = self.read(data_dir, key)  # computed by the process we waited for
                if v is not None:
                    return v
                v = compute()
                if valid is None or valid():
                    self._write(d, dig, v)
            finally:
                fcntl.flock(lk, fcntl.LOCK_UN)
        self.prune(data_dir)
        return v

    def put(self, data_dir: str | Path, key: Any, value: Any) -> None:  # noqa: ANN401
        """Store ``value`` for ``key`` unless an entry is there (best effort)."""
        if self.has(data_dir, key):
            return
        d = self.folder(data_dir)
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError:
            log.warning("review cache: could not create %s", d, exc_info=True)
            return
        if self._write(d, self.digest(key), value):
            self.prune(data_dir)

    @staticmethod
    def _write(d: Path, dig: str, value: Any) -> bool:  # noqa: ANN401
        """Write the entry atomically; False where it could not be (a full disk costs the
        sharing, not the answer)."""
        try:
            atomic_write_bytes(d / f"{dig}.entry", encode(value))
            return True
        except (OSError, TypeError):
            log.warning("review cache: could not store an entry in %s", d, exc_info=True)
            return False

    def prune(self, data_dir: str | Path) -> None:
        """Remove the oldest entries beyond ``max_bytes``, and lock files left without an
        entry for ``_STALE_LOCK_S``."""
        d = self.folder(data_dir)
        entries, total, now = [], 0, time.time()
        try:
            with os.scandir(d) as it:
                for e in it:
                    try:
                        st = e.stat()
                    except OSError:
                        continue
                    if e.name.endswith(".entry"):
                        entries.append((st.st_mtime, st.st_size, e.path))
                        total += st.st_size
                    elif e.name.endswith(".lock") and now - st.st_mtime > _STALE_LOCK_S \
                            and not os.path.exists(e.path[:-5] + ".entry"):
                        _unlink(e.path)
        except OSError:
            return
        if total <= self.max_bytes:
            return
        for _mtime, size, path in sorted(entries):
            _unlink(path)
            total -= size
            if total <= self.max_bytes:
                break


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass
