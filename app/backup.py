"""``occufly backup DIR`` / ``occufly restore DIR``: the database, the mask store and the scene
workspaces, taken while the app runs and restored into a fresh data directory.

Layout of a backup folder::

    manifest.json            revision, created_at, per-table row counts, mask count, scenes
    db/<table>.jsonl         one JSON object per row (datetimes ISO 8601), database-neutral:
                             a SQLite backup restores into PostgreSQL and back
    masks/<ab>/<cd>/<sha256>.png   every mask version's PNG (content-addressed)
    scenes/<name>/...        every scene workspace
    images/<ab>/<sha256><ext>  every frame image that lives outside its workspace (typically
                             in the import folder), content-addressed; the manifest's
                             ``scenes[].external_images`` maps frame index -> sha256 and the
                             original path. A restore puts them under the workspace's
                             ``images_restored/`` and points scene.json at them, so a restore
                             needs neither the import folder nor its path (issue 24, finding 8).
                             ``--no-images``: recorded (path, size, sha256) but not copied; the
                             manifest says ``complete: false`` and a restore checks every one
                             is still there, unchanged, before writing anything.

Consistency while the app runs: the rows are read from one snapshot (PostgreSQL: a REPEATABLE
READ transaction; SQLite: the online backup API copies the database file first). A mask PNG
is stored before the row that names it is committed and is never modified, so every version
in the snapshot has its PNG; each copied PNG is checked against its sha256. Workspace files
are written atomically by the pipeline (temporary name, rename), so each copied file is whole;
derived state there (votes, filled labels) is rebuilt from the masks by the lifting service if
it is older than the masks. The folder is built under a temporary name and renamed into place
when complete: a backup that fails leaves nothing behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import tempfile
from datetime import date, datetime
from pathlib import Path

from sqlalchemy import DateTime, insert, select, text
from sqlalchemy.engine import Engine

from app import db
from app.blobs import BlobStore
from app.config import Settings
from app.models import metadata
from app.scenes.models import Scene
from app.users.models import User
from occufly.errors import OccuflyError
from occufly.fsutil import PathNotConfined, atomic_directory, atomic_write_text, confined
from occufly.workspace import Workspace

FORMAT = "occufly-backup"
VERSION = 2  # 2: external frame images (version-1 backups restore as before)
RESTORED_IMAGES = "images_restored"


class BackupError(OccuflyError):
    """A backup or restore that cannot be done (message names the folder and why)."""


def _tables():
    return list(metadata.sorted_tables)


def _jsonable(v):  # noqa: ANN001, ANN202
    if isinstance(v, (datetime, date)):
        return v.isoformat()
    return v


def _dump_tables(conn, dest: Path) -> dict[str, int]:  # noqa: ANN001
    counts = {}
    (dest / "db").mkdir(parents=True, exist_ok=True)
    for table in _tables():
        n = 0
        with open(dest / "db" / f"{table.name}.jsonl", "w") as f:
            for row in conn.execute(select(table).order_by(*table.primary_key.columns)):
                f.write(json.dumps({k: _jsonable(v) for k, v in row._mapping.items()}) + "\n")
                n += 1
        counts[table.name] = n
    return counts


def _revision(conn) -> str | None:  # noqa: ANN001
    try:
        return conn.execute(text("SELECT version_num FROM alembic_version")).scalar()
    except Exception:  # noqa: BLE001
        return None


def _snapshot_dump(settings: Settings, dest: Path) -> tuple[dict[str, int], str | None]:
    url = settings.database_url
    if url.startswith("sqlite"):
        src_path = url.split("///", 1)[-1]
        with tempfile.TemporaryDirectory(dir=dest) as tmp:
            snap = Path(tmp) / "snapshot.db"
            src = sqlite3.connect(src_path, timeout=60)
            try:
                out = sqlite3.connect(snap)
                with out:
                    src.backup(out)  # a consistent copy even while writers commit
                out.close()
            finally:
                src.close()
            engine = db.make_engine(f"sqlite:///{snap}", pooled=False)
            try:
                with engine.connect() as conn:
                    return _dump_tables(conn, dest), _revision(conn)
            finally:
                engine.dispose()
    engine = db.make_engine(url, pooled=False)
    try:
        with engine.connect().execution_options(isolation_level="REPEATABLE READ") as conn:
            with conn.begin():
                return _dump_tables(conn, dest), _revision(conn)
    finally:
        engine.dispose()


def _rows(folder: Path, table: str):  # noqa: ANN202
    p = folder / "db" / f"{table}.jsonl"
    if not p.is_file():
        return
    with open(p) as f:
        for line in f:
            if line.strip():
                yield json.loads(line)


def _sha_ok(path: Path, sha256: str) -> bool:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest() == sha256


def _copy_tree(src: Path, dst: Path) -> int:
    """Copy a workspace, skipping the pipeline's in-progress temporaries (hidden names)."""
    n = 0
    for root, dirs, files in os.walk(src):
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        rel = Path(root).relative_to(src)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for name in files:
            if name.startswith("."):
                continue
            try:
                shutil.copy2(Path(root) / name, dst / rel / name)
                n += 1
            except FileNotFoundError:  # replaced between listing and copying: the new one
                continue  # is picked up by the next backup; the old one is not needed
    return n


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _external_images(ws: Path) -> list[tuple[int, Path, str]]:
    """(frame index, resolved path, path as scene.json has it) of every frame image that is
    not inside the workspace folder ``ws`` (symlinks followed)."""
    try:
        header = json.loads(Workspace(ws).scene_json.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise BackupError(f"{ws}/scene.json: cannot be read ({e}); the workspace is damaged") \
            from None
    root = Path(os.path.realpath(ws))
    out = []
    for i, f in enumerate(header.get("frames", [])):
        raw = f.get("image_path")
        if not raw:
            continue
        p = Path(raw)
        real = Path(os.path.realpath(p if p.is_absolute() else ws / p))
        if real != root and root not in real.parents:
            out.append((i, real, raw))
    return out


def _backup_images(ws: Path, dest: Path, *, copy: bool, seen: dict[Path, str],
                   roots: list[Path]) -> tuple[list, list, list]:
    """Copy (or, ``copy=False``, record) the workspace's external images; returns the
    manifest entries, the frames whose image is missing, and those left out because they lie
    outside ``roots`` (the import roots and the data dir: the app never serves them, and a
    backup must not carry e.g. /etc/shadow that a legacy scene.json names)."""
    entries, missing, outside = [], [], []
    for i, real, raw in _external_images(ws):
        try:
            confined(real, roots)
        except PathNotConfined:
            outside.append({"frame": i, "path": raw})
            continue
        if not real.is_file():
            missing.append(f"frame {i}: {raw}")
            continue
        sha = seen.get(real)
        if sha is None:
            sha = _sha256(real)
            seen[real] = sha
            if copy:
                out = dest / "images" / sha[:2] / (sha + real.suffix.lower())
                if not out.exists():
                    out.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(real, out)
                    if not _sha_ok(out, sha):  # changed while copying: not a usable copy
                        raise BackupError(f"{real}: changed while it was copied; back up again")
        entries.append({"frame": i, "sha256": sha, "ext": real.suffix.lower(), "path": raw,
                        "resolved": str(real), "size": real.stat().st_size})
    return entries, missing, outside


def backup(settings: Settings, dest: Path, *, images: bool = True) -> dict:
    """Write a complete backup of the app's state to the new folder ``dest``.

    Frame images outside the workspaces (the import folder) are copied too; with
    ``images=False`` they are only recorded and checked, and the backup says it is not
    complete (``complete: false``). An image that is already missing fails the backup."""
    dest = Path(dest).absolute()
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise BackupError(f"{dest}: already exists and is not empty; back up into a new folder")
    if dest.exists():
        dest.rmdir()
    store = BlobStore(settings.mask_store_dir)
    with atomic_directory(dest) as tmp:
        counts, revision = _snapshot_dump(settings, tmp)
        n_masks, missing = 0, []
        seen: set[str] = set()
        for row in _rows(tmp, "mask_versions"):
            sha = row["sha256"]
            if sha in seen:
                continue
            seen.add(sha)
            src = store.path(sha)
            out = tmp / "masks" / src.relative_to(store.root)
            out.parent.mkdir(parents=True, exist_ok=True)
            if not src.is_file():
                missing.append(sha)
                continue
            shutil.copy2(src, out)
            if not _sha_ok(out, sha):
                raise BackupError(f"mask store: {src} does not hash to its name; the store is "
                                  "damaged (restore it from an older backup)")
            n_masks += 1
        if missing:
            raise BackupError(f"mask store: {len(missing)} mask PNG(s) named by the database are "
                              f"missing from {store.root}, e.g. {missing[0]}")
        scenes, seen, lost = [], {}, []
        for row in _rows(tmp, "scenes"):
            ws = Path(row["workspace"])
            if ws.is_dir() and not ws.is_symlink():
                files = _copy_tree(ws, tmp / "scenes" / row["name"])
                ext, missing_img, outside = ([], [], []) if not Workspace(ws).scene_json.is_file() \
                    else _backup_images(ws, tmp, copy=images, seen=seen,
                                        roots=[*settings.import_roots, settings.data_dir])
                lost += [f"scene {row['name']!r} {m}" for m in missing_img]
                scenes.append({"id": row["id"], "name": row["name"], "files": files,
                               "external_images": ext,
                               # never served (outside the import roots): not carried
                               "images_outside_roots": outside})
        if lost:
            raise BackupError(f"{len(lost)} frame image(s) named by the workspaces are missing, "
                              f"e.g. {lost[0]}; a restore could not serve or export them "
                              "(put the import folder back, or remove those scenes)")
        n_ext = sum(len(sc["external_images"]) for sc in scenes)
        manifest = {"format": FORMAT, "version": VERSION, "revision": revision,
                    "created_at": datetime.now().astimezone().isoformat(),
                    "database": settings.database_url.split(":", 1)[0], "tables": counts,
                    "masks": n_masks, "scenes": scenes,
                    "external_images": {"frames": n_ext, "files": len(set(seen.values())),
                                        "copied": images},
                    "complete": images or n_ext == 0}
        if not manifest["complete"]:
            manifest["incomplete_because"] = (
                f"{n_ext} frame image(s) outside the workspaces were recorded but not copied "
                "(--no-images); a restore needs them at their recorded paths, unchanged")
        atomic_write_text(tmp / "manifest.json", json.dumps(manifest, indent=1))
    return {"backup": str(dest), **manifest}


def _convert(table, row: dict) -> dict:  # noqa: ANN001
    out = {}
    for k, v in row.items():
        col = table.columns.get(k)
        if col is None:
            continue  # a column a newer schema dropped
        if v is not None and isinstance(col.type, DateTime):
            v = datetime.fromisoformat(v)
        out[k] = v
    return out


def _restore_images(src: Path, ws: Path, entries: list[dict]) -> None:
    """Copy the backup's external images into ``ws/images_restored/`` and point scene.json's
    frames at them (relative paths: the workspace is self-contained from now on)."""
    if not entries:
        return
    header_path = Workspace(ws).scene_json
    header = json.loads(header_path.read_text())
    (ws / RESTORED_IMAGES).mkdir(exist_ok=True)
    for e in entries:
        name = e["sha256"] + e["ext"]
        out = ws / RESTORED_IMAGES / name
        if not out.exists():
            shutil.copy2(src / "images" / e["sha256"][:2] / name, out)
        header["frames"][e["frame"]]["image_path"] = f"{RESTORED_IMAGES}/{name}"
    atomic_write_text(header_path, json.dumps(header, indent=1))


def _is_empty(engine: Engine) -> bool:
    with engine.connect() as conn:
        return (conn.execute(select(User.id).limit(1)).first() is None
                and conn.execute(select(Scene.id).limit(1)).first() is None)


def restore(settings: Settings, src: Path) -> dict:
    """Restore the backup folder ``src`` into this (fresh) data directory and database."""
    src = Path(src).absolute()
    try:
        manifest = json.loads((src / "manifest.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise BackupError(f"{src}: not a complete OccuFly backup (manifest.json: {e})") from None
    if manifest.get("format") != FORMAT or manifest.get("version", 0) > VERSION:
        raise BackupError(f"{src}/manifest.json: not an OccuFly backup of a known version")
    revision = manifest.get("revision")
    db.upgrade(settings.database_url, revision or "head")
    engine = db.make_engine(settings.database_url, pooled=False)
    try:
        if not _is_empty(engine):
            raise BackupError(f"{settings.database_url.split('@')[-1]}: the database already holds "
                              "users or scenes; restore into a fresh data directory and database")
        ws_root = settings.workspaces_dir.absolute()
        existing = [s["name"] for s in manifest.get("scenes", []) if (ws_root / s["name"]).exists()]
        if existing:
            raise BackupError(f"{ws_root}: workspaces {existing[:5]} already exist; restore into "
                              "a fresh data directory")
        # external frame images checked before anything is written: copied ones against their
        # names, recorded-only ones (--no-images) at their paths against size and sha256
        problems = []
        for sc in manifest.get("scenes", []):
            for e in sc.get("external_images", []):
                if manifest.get("external_images", {}).get("copied", True):
                    p = src / "images" / e["sha256"][:2] / (e["sha256"] + e["ext"])
                    if not p.is_file() or not _sha_ok(p, e["sha256"]):
                        problems.append(f"{p}: missing or damaged (frame {e['frame']} of "
                                        f"{sc['name']!r})")
                else:
                    p = Path(e["resolved"])
                    if not p.is_file() or p.stat().st_size != e["size"] or \
                            not _sha_ok(p, e["sha256"]):
                        problems.append(f"{p}: missing or changed since the backup (frame "
                                        f"{e['frame']} of {sc['name']!r})")
        if problems:
            raise BackupError(f"{src}: {len(problems)} frame image(s) cannot be restored, e.g. "
                              f"{problems[0]}")
        # masks first, each checked against its name: a damaged backup fails before the database
        store = BlobStore(settings.mask_store_dir)
        n_masks = 0
        for p in sorted((src / "masks").rglob("*.png")) if (src / "masks").is_dir() else []:
            sha = p.stem
            if not _sha_ok(p, sha):
                raise BackupError(f"{p}: does not hash to its name; the backup is damaged")
            out = store.path(sha)
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(p, out)
            n_masks += 1
        counts = {}
        with engine.begin() as conn:
            # the migrations seed id_counters in the fresh database: the backup's rows replace
            # them (a backup made before migration 0012 has none: re-seeded below)
            conn.execute(text("DELETE FROM id_counters"))
            for table in _tables():
                batch, n = [], 0
                for row in _rows(src, table.name):
                    row = _convert(table, row)
                    if table.name == "scenes":  # workspaces move with the data directory
                        row["workspace"] = str(ws_root / row["name"])
                    batch.append(row)
                    if len(batch) >= 1000:
                        conn.execute(insert(table), batch)
                        n += len(batch)
                        batch = []
                if batch:
                    conn.execute(insert(table), batch)
                    n += len(batch)
                counts[table.name] = n
            # scene ids continue after every id the restored rows know (never reused, issue 36)
            seen = conn.execute(text(
                "SELECT COALESCE(MAX(i), 0) FROM (SELECT MAX(id) AS i FROM scenes UNION ALL "
                "SELECT MAX(scene_id) FROM audit_events UNION ALL SELECT MAX(scene_id) FROM jobs "
                "UNION ALL SELECT MAX(last_id) FROM id_counters WHERE name = 'scenes') AS seen")
            ).scalar_one()
            if conn.execute(text("UPDATE id_counters SET last_id = :v WHERE name = 'scenes'"),
                            {"v": int(seen)}).rowcount == 0:
                conn.execute(text("INSERT INTO id_counters (name, last_id) VALUES ('scenes', :v)"),
                             {"v": int(seen)})
            if conn.dialect.name == "postgresql":  # ids continue after the restored ones
                for table in _tables():
                    pk = list(table.primary_key.columns)
                    if len(pk) == 1 and pk[0].autoincrement and str(pk[0].type) == "INTEGER":
                        conn.execute(text(
                            f"SELECT setval(pg_get_serial_sequence('{table.name}', '{pk[0].name}'), "
                            f"COALESCE((SELECT MAX({pk[0].name}) FROM {table.name}), 0) + 1, false)"))
        for s in manifest.get("scenes", []):
            folder = src / "scenes" / s["name"]
            if folder.is_dir():
                with atomic_directory(ws_root / s["name"]) as tmp:
                    _copy_tree(folder, tmp)
                    if manifest.get("external_images", {}).get("copied", True):
                        _restore_images(src, tmp, s.get("external_images", []))
        with engine.connect() as conn:
            missing = [sha for (sha,) in conn.execute(text("SELECT DISTINCT sha256 FROM mask_versions"))
                       if not store.exists(sha)]
        if missing:
            raise BackupError(f"{src}: {len(missing)} mask PNG(s) named by the database are not in "
                              f"the backup, e.g. {missing[0]}")
    finally:
        engine.dispose()
    db.upgrade(settings.database_url)  # a backup of an older schema is brought to head
    return {"restored": str(src), "revision": db.current_revision(settings.database_url),
            "tables": counts, "masks": n_masks, "scenes": [s["name"] for s in manifest.get("scenes", [])]}
