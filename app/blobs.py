"""Content-addressed blob store for mask PNGs: ``<root>/<ab>/<cd>/<sha256>.png``.

A blob is written atomically (temporary name, fsync, rename) and never modified, so two
writers of the same bytes are harmless and a reader sees the whole file or none.

Versions (and prefills, proposals) with the same bytes share one blob, so a blob may only
be removed when no row references it -- and no save that is about to reference it is under
way (issue 36: a scene deletion removed a blob another scene's concurrent save had found
present and was about to commit). Every blob has a row in ``mask_blobs``; a writer *claims*
the blob (:func:`claim_blob`: upsert of its row, which locks the row on PostgreSQL and takes
the write lock on SQLite) in the transaction that adds the referencing row, and makes sure
the file is there while it holds that lock. :func:`release_blobs` locks the rows first, then
looks for references (a new statement: on PostgreSQL's READ COMMITTED it sees every save
that committed while it waited), deletes the unreferenced rows and unlinks their files
before it commits -- so a claim either commits before the check (and is seen) or waits for
the release and then rewrites the file it finds missing. Only blobs with a row are ever
removed; a blob without one (written before migration 0011 by a path that did not claim)
is kept.
"""

from __future__ import annotations

import hashlib
import logging
from datetime import datetime
from pathlib import Path

from sqlalchemy import DateTime, String, delete, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Mapped, Session, mapped_column

from app.annotations.models import MaskVersion, Prefill
from app.corrections.models import MaskProposal
from app.db import Base, utcnow
from app.errors import DomainError
from occufly.fsutil import atomic_write_bytes

log = logging.getLogger("occufly.storage")


class BlobMissing(DomainError):
    """A row names a blob the store no longer has: a server fault (never the client's)."""
    status_code = 500


class MaskBlob(Base):
    """One blob of the content store (its sha256); written with the row that references it."""

    __tablename__ = "mask_blobs"

    sha256: Mapped[str] = mapped_column(String(64), primary_key=True)
    # when a save last claimed it / a release last checked it (the write takes the row lock)
    touched_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


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

    def get(self, sha256: str, *, owner: str | None = None) -> bytes:
        """The blob's bytes; :class:`BlobMissing` (a JSON 500 naming ``owner``, e.g.
        ``"mask version 12"``, and the digest) when the store lacks it."""
        try:
            return self.path(sha256).read_bytes()
        except FileNotFoundError:
            what = f"{owner}: " if owner else ""
            log.error("%sblob %s is missing from the mask store", what, sha256)
            raise BlobMissing(f"{what}its stored PNG ({sha256}) is missing from the mask store; "
                              "this is a server fault -- tell an admin (restore it from a backup)",
                              sha256=sha256, owner=owner) from None

    def exists(self, sha256: str) -> bool:
        return self.path(sha256).is_file()

    def count(self) -> int:
        return sum(1 for _ in self.root.rglob("*.png")) if self.root.exists() else 0


def _upsert(session: Session, sha256: str) -> None:
    """Insert the blob's row or touch it: either way the row is locked (PostgreSQL) / the
    database write lock is taken (SQLite) until the caller's transaction ends."""
    now = utcnow()
    insert = (postgresql.insert if session.get_bind().dialect.name == "postgresql"
              else sqlite.insert)
    stmt = insert(MaskBlob).values(sha256=sha256, touched_at=now)
    session.execute(stmt.on_conflict_do_update(index_elements=[MaskBlob.sha256],
                                               set_={"touched_at": now}))


def claim_blob(session: Session, store: BlobStore, data: bytes | None = None, *,
               sha256: str | None = None, owner: str | None = None) -> str:
    """Store ``data`` (or reuse the stored ``sha256``) for a row the caller adds and commits
    in this same transaction; returns the digest. The file is written before the lock is
    taken (the common case holds the lock only for a stat) and written again under the lock
    if a concurrent :func:`release_blobs` removed it meanwhile. Reusing a digest whose file
    is gone raises :class:`BlobMissing`."""
    if data is not None:
        sha256 = store.put(data)
    assert sha256 is not None
    _upsert(session, sha256)
    if not store.exists(sha256):
        if data is None:
            session.rollback()
            store.get(sha256, owner=owner)  # raises BlobMissing
        store.put(data)
    return sha256


def referenced_blobs(session: Session, shas: list[str]) -> set[str]:
    """Those of ``shas`` a mask version, prefill or proposal references."""
    out: set[str] = set()
    for col in (MaskVersion.sha256, Prefill.sha256, MaskProposal.sha256,
                MaskProposal.change_sha256):
        out |= set(session.scalars(select(col).where(col.in_(shas)).distinct()))
    return out


def release_blobs(session: Session, store: BlobStore, shas: set[str], *, chunk: int = 200) -> int:
    """Remove those of ``shas`` no row references any more (rows and files), safely against
    concurrent claims (module docstring); commits per chunk. Returns the blobs removed."""
    removed = 0
    wanted = sorted(shas)
    for i in range(0, len(wanted), chunk):
        part = wanted[i:i + chunk]
        try:
            # 1. lock: the rows that exist now (PostgreSQL row locks; SQLite write lock)
            locked = list(session.scalars(
                update(MaskBlob).where(MaskBlob.sha256.in_(part)).values(touched_at=utcnow())
                .returning(MaskBlob.sha256).execution_options(synchronize_session=False)))
            # 2. look (a fresh snapshot: sees whatever committed while step 1 waited)
            free = sorted(set(locked) - referenced_blobs(session, locked)) if locked else []
            # 3. remove rows and files while the lock is held, then commit
            if free:
                session.execute(delete(MaskBlob).where(MaskBlob.sha256.in_(free))
                                .execution_options(synchronize_session=False))
                for h in free:
                    try:
                        store.path(h).unlink(missing_ok=True)
                    except OSError:
                        log.warning("could not remove mask blob %s", h)
            session.commit()
            removed += len(free)
        except Exception:
            session.rollback()
            raise
    return removed
