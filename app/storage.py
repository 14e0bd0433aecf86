"""Content-addressed blob store for mask PNGs: ``<root>/<ab>/<cd>/<sha256>.png``.

A blob is written atomically (temporary name, fsync, rename) and never modified, so two
writers of the same bytes are harmless and a reader sees the whole file or none.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from occufly.fsutil import atomic_write_bytes


class BlobStore:
    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def path(self, sha256: str) -> Path:
        if len(sha256) != 64 or any(c not in "0123456789abcdef" for c in sha256):
            raise ValueError(f"not a sha256 hex digest: {sha256!r}")
        return self.root / sha256[:2] / sha256[2:4] / f"{sha256}.png"

    def put(self, data: bytes) -> str:
        digest = hashlib.sha256(data).hexdigest()
        p = self.path(digest)
        if not p.is_file() or p.stat().st_size != len(data):
            atomic_write_bytes(p, data)
        return digest

    def get(self, sha256: str) -> bytes:
        return self.path(sha256).read_bytes()

    def exists(self, sha256: str) -> bool:
        return self.path(sha256).is_file()

    def count(self) -> int:
        return sum(1 for _ in self.root.rglob("*.png")) if self.root.exists() else 0
