"""Issue 24, finding 5 (canonical mask storage, storage quotas) and from 9: GET /prefill
writes no row per call, writes while the disk is full are a clear 507 with nothing written."""
from __future__ import annotations

import dataclasses
import errno
import hashlib
import struct
import zlib

import numpy as np
from PIL import Image, PngImagePlugin
from sqlalchemy import func, select

from occufly.io.masks import png_chunk
from tests.app.conftest import H, W, mask_png, png


def _padded(m: bytes, pad: int, where: str) -> bytes:
    """``m`` with ``pad`` bytes after IEND, or in a tEXt chunk before IEND."""
    if where == "after_iend":
        return m + b"\x00" * pad
    iend = m.rindex(b"IEND") - 4
    return m[:iend] + png_chunk(b"tEXt", b"comment\x00" + b"A" * pad) + m[iend:]


def _lease(env, hdr, scene, who="annotator") -> int:  # noqa: ANN001
    r = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr[who])
    assert r.status_code == 200, r.text
    return r.json()["id"]


def _store_bytes(env) -> int:  # noqa: ANN001
    root = env.settings.mask_store_dir
    return sum(p.stat().st_size for p in root.rglob("*.png")) if root.exists() else 0


def test_masks_are_stored_canonically(world):
    """Padded uploads (60 KB after IEND, 60 KB in a tEXt chunk), a 16-bit, a palette and a
    colour mask: each is stored as the 8-bit class-id PNG of its decoded ids, no ancillary
    chunk, so ten padded saves grow the store by the size of the canonical mask (before: by
    the padding each time)."""
    env, hdr, scene, _ = world
    fid = _lease(env, hdr, scene)
    a = hdr["annotator"]
    from occufly.io.masks import encode_mask_png

    # the canonical bytes of the ids (the server's encoding, as the editor writes them)
    clean = encode_mask_png(np.asarray(Image.open(__import__("io").BytesIO(mask_png(6)))))
    before = _store_bytes(env)
    cur = "none"
    for i in range(10):
        body = _padded(clean, 60_000, "after_iend" if i % 2 else "text")
        r = env.client.put(f"/api/frames/{fid}/mask", content=body, headers={**a, "If-Match": cur})
        assert r.status_code == 200, r.text
        assert r.json()["sha256"] == hashlib.sha256(clean).hexdigest()
        cur = f'"{r.json()["version"]}"'
    grew = _store_bytes(env) - before
    assert grew <= len(clean), grew  # one canonical blob, not 10 x 60 KB
    got = env.client.get(f"/api/frames/{fid}/mask", headers=a).content
    assert got == clean and b"tEXt" not in got and got.endswith(b"IEND\xaeB`\x82")
    ids = np.asarray(Image.open(__import__("io").BytesIO(clean)))
    # other encodings of the same ids: stored as the same canonical bytes
    import io

    enc = {}
    b16 = io.BytesIO()
    Image.fromarray(ids.astype(np.uint16)).save(b16, format="PNG")
    enc["16-bit"] = b16.getvalue()
    pal = Image.fromarray(ids).convert("P")
    bp = io.BytesIO()
    pal.save(bp, format="PNG")
    enc["palette"] = bp.getvalue()
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", "<script>alert(1)</script>")
    bt = io.BytesIO()
    Image.fromarray(ids).save(bt, format="PNG", pnginfo=info)
    enc["text"] = bt.getvalue()
    for what, body in enc.items():
        r = env.client.put(f"/api/frames/{fid}/mask", content=body, headers={**a, "If-Match": cur})
        assert r.status_code == 200, (what, r.text)
        assert r.json()["sha256"] == hashlib.sha256(clean).hexdigest(), what
        cur = f'"{r.json()["version"]}"'
    assert env.client.get(f"/api/frames/{fid}/mask", headers=a).content == clean



def test_an_upload_that_is_canonical_already_is_stored_as_it_is(world):
    """Issue 29 (save CPU): the editor's uploads are 8-bit grey PNGs with IHDR/IDAT/IEND only;
    they are kept byte for byte instead of being re-encoded (here: deflate level 1, which the
    server's encoder would have turned into other bytes). The same bytes with 5 KB after the
    zlib stream inside IDAT are re-encoded."""
    import io

    env, hdr, scene, _ = world
    fid = _lease(env, hdr, scene)
    a = hdr["annotator"]
    ids = np.asarray(Image.open(io.BytesIO(mask_png(6))))
    b = io.BytesIO()
    Image.fromarray(ids).save(b, format="PNG", compress_level=1)
    fast = b.getvalue()
    assert fast != mask_png(6)
    r = env.client.put(f"/api/frames/{fid}/mask", content=fast, headers={**a, "If-Match": "none"})
    assert r.status_code == 200, r.text
    assert r.json()["sha256"] == hashlib.sha256(fast).hexdigest()
    assert env.client.get(f"/api/frames/{fid}/mask", headers=a).content == fast
    raw = b"".join(b"\x00" + ids[i].tobytes() for i in range(ids.shape[0]))
    padded = (fast[:8] + png_chunk(b"IHDR", struct.pack(">IIBBBBB", ids.shape[1], ids.shape[0], 8, 0, 0,
                                                     0, 0))
              + png_chunk(b"IDAT", zlib.compress(raw) + b"\x00" * 5000) + png_chunk(b"IEND", b""))
    r = env.client.put(f"/api/frames/{fid}/mask", content=padded,
                       headers={**a, "If-Match": f'"{r.json()["version"]}"'})
    assert r.status_code == 200, r.text
    got = env.client.get(f"/api/frames/{fid}/mask", headers=a).content
    assert len(got) < len(padded) - 4000 and np.array_equal(
        np.asarray(Image.open(io.BytesIO(got))), ids)

def test_per_user_quota_counts_conflicts(world):
    """The per-user quota: saves beyond it are 507 naming the quota and nothing is stored;
    conflict versions (a lost lease, a stale If-Match) count toward it."""
    env, hdr, scene, _ = world
    ctx = env.app.state.ctx
    one = len(mask_png(6))
    ctx.settings = dataclasses.replace(ctx.settings, user_quota_bytes=3 * one + 10)
    fid = _lease(env, hdr, scene)
    a = hdr["annotator"]
    v = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(6),
                       headers={**a, "If-Match": "none"}).json()["version"]
    for cid in (8, 9):  # stale If-Match: kept as conflict versions
        r = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(cid),
                           headers={**a, "If-Match": "none"})
        assert r.status_code == 409, r.text
    from app.annotations.models import MaskVersion

    with ctx.sessions() as s:
        n_before = s.scalar(select(func.count()).select_from(MaskVersion))
    store_before = _store_bytes(env)
    r = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(14),
                       headers={**a, "If-Match": f'"{v}"'})
    assert r.status_code == 507, r.text
    assert r.json()["quota"] == "user" and "per-user quota" in r.json()["detail"]
    with ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(MaskVersion)) == n_before
    assert _store_bytes(env) == store_before
    # another user is not held by this one's quota
    fid2 = _lease(env, hdr, scene, "annotator2")
    r = env.client.put(f"/api/frames/{fid2}/mask", content=mask_png(14),
                       headers={**hdr["annotator2"], "If-Match": "none"})
    assert r.status_code == 200, r.text


def test_per_scene_quota(world):
    env, hdr, scene, _ = world
    ctx = env.app.state.ctx
    one = len(mask_png(6))
    ctx.settings = dataclasses.replace(ctx.settings, scene_quota_bytes=2 * one + 10)
    f1, f2 = _lease(env, hdr, scene), _lease(env, hdr, scene, "annotator2")
    assert env.client.put(f"/api/frames/{f1}/mask", content=mask_png(6),
                          headers={**hdr["annotator"], "If-Match": "none"}).status_code == 200
    assert env.client.put(f"/api/frames/{f2}/mask", content=mask_png(8),
                          headers={**hdr["annotator2"], "If-Match": "none"}).status_code == 200
    r = env.client.put(f"/api/frames/{f2}/mask", content=mask_png(9),
                       headers={**hdr["annotator2"], "If-Match": "none"})  # would be a conflict
    assert r.status_code == 507 and r.json()["quota"] == "scene", r.text


def test_disk_full_on_a_mask_save_is_507_and_writes_nothing(world, monkeypatch):
    env, hdr, scene, _ = world
    import app.blobs as storage

    def full(path, data):  # noqa: ANN001, ANN202
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(storage, "atomic_write_bytes", full)
    fid = _lease(env, hdr, scene)
    from app.annotations.models import MaskVersion

    ctx = env.app.state.ctx
    r = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(6),
                       headers={**hdr["annotator"], "If-Match": "none"})
    assert r.status_code == 507, (r.status_code, r.text)
    assert "disk is full" in r.json()["detail"]
    with ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(MaskVersion)) == 0
    assert not list(env.settings.mask_store_dir.rglob("*.tmp")) if env.settings.mask_store_dir.exists() else True


def test_database_disk_full_is_507(world, monkeypatch):
    """A database that reports a full disk (SQLite SQLITE_FULL / PostgreSQL 53100) on a write:
    507, the transaction rolled back."""
    env, hdr, scene, _ = world
    import sqlite3

    from sqlalchemy import event
    from sqlalchemy.exc import OperationalError

    eng = env.app.state.ctx.engine

    def refuse(conn, cursor, statement, params, context, executemany):  # noqa: ANN001
        if statement.lstrip().upper().startswith("INSERT INTO REVIEW_ITEMS"):
            raise OperationalError(statement, params, sqlite3.OperationalError(
                "database or disk is full"))

    event.listen(eng, "before_cursor_execute", refuse)
    try:
        r = env.client.post(f"/api/scenes/{scene['id']}/review-items",
                            json={"comment": "x", "point_ids": [1, 2]}, headers=hdr["reviewer"])
    finally:
        event.remove(eng, "before_cursor_execute", refuse)
    assert r.status_code == 507, (r.status_code, r.text)
    assert "disk is full" in r.json()["detail"]


def test_prefill_get_writes_no_row_per_call(world):
    """GET /prefill handed the same labels to the same user keeps one row (before: a row per
    call: a loop of GETs grew the prefills table without bound)."""
    env, hdr, scene, _ = world
    from app.annotations.models import Prefill

    f1 = _lease(env, hdr, scene)
    r = env.client.put(f"/api/frames/{f1}/mask?kind=submitted", content=png(np.full((H, W), 6, np.uint8)),
                       headers={**hdr["annotator"], "If-Match": "none"})
    assert r.status_code == 200, r.text
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20)
    fid = _lease(env, hdr, scene)
    ids = set()
    for _ in range(20):
        r = env.client.get(f"/api/frames/{fid}/prefill", headers=hdr["annotator"])
        assert r.status_code == 200, r.text
        ids.add((r.headers.get("x-prefill-id"), hashlib.sha256(r.content).hexdigest()))
    with env.app.state.ctx.sessions() as s:
        n = s.scalar(select(func.count()).select_from(Prefill))
    # one row per distinct image handed out (the fill may still change the labels once
    # between calls), never one per call
    images = {h for _i, h in ids}
    assert n == len(images) == len({i for i, _h in ids}) and n <= 3, (n, ids)
