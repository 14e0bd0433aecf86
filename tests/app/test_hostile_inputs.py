"""Issue 36: CSRF with a non-Bearer Authorization header, YAML alias bombs in class maps,
bounded error messages, EXIF/XMP values out of range."""

from __future__ import annotations

import pytest


# ---- finding 6: only a Bearer token skips the CSRF check ---------------------------------------
@pytest.mark.parametrize("auth", ["Basic YWRtaW46eA==", "Digest username=\"admin\"", "Bearer ",
                                  "Token abc", "NTLM TlRMTVNTUAAB"])
def test_a_cookie_write_with_another_authorization_scheme_is_still_checked(world, auth):
    env, _hdr, _scene, frames = world
    admin = env.login("admin")  # the session cookie is the credential
    r = admin.post(f"/api/frames/{frames[0]['id']}/mask/versions/1/restore",
                   headers={"Origin": "http://evil.example", "Authorization": auth})
    assert r.status_code == 403 and "cross-site" in r.json()["detail"], r.text


def test_a_bearer_write_is_judged_by_its_token_not_the_cookie(world):
    env, hdr, _scene, frames = world
    admin = env.login("admin")
    url = f"/api/frames/{frames[0]['id']}/mask/versions/999999/restore"
    r = admin.post(url, headers={"Origin": "http://evil.example", **hdr["admin"]})
    assert r.status_code != 403, r.text  # a valid bearer token: no CSRF check (404/428 here)
    # an invalid bearer token is not helped by the cookie beside it
    r = admin.post(url, headers={"Origin": "http://evil.example",
                                 "Authorization": "Bearer not-a-token"})
    assert r.status_code == 401, r.text


# ---- finding 4: YAML alias bombs, non-scalar targets, bounded messages -------------------------
ALIAS_BOMB = "a: &a [x,x,x,x,x,x,x,x,x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},"
    f"*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},"
    f"*{chr(97 + i)}]\n" for i in range(8)) + "vegetation: *i\n"


def _import_with_mapping(env, hdr, scene, name: str, mapping: bytes):  # noqa: ANN001, ANN202
    return env.client.post(f"/api/scenes/{scene['id']}/masks/import", headers=hdr["admin"],
                           data={"format": "png"},
                           files={"archive": ("a.zip", b"PK\x05\x06" + b"\0" * 18),
                                  "mapping": (name, mapping)})


def test_a_yaml_alias_bomb_in_a_class_map_is_refused_at_once(world):
    import time

    env, hdr, scene, _frames = world
    assert len(ALIAS_BOMB) < 600  # 9 ** 9 = 387 M list entries once expanded
    t = time.process_time()
    r = _import_with_mapping(env, hdr, scene, "map.yaml", ALIAS_BOMB.encode())
    assert time.process_time() - t < 2.0
    assert r.status_code == 422 and "aliases" in r.json()["detail"], r.text[:300]
    assert len(r.content) < 2000


def test_class_map_targets_must_be_scalars_and_messages_are_bounded(world):
    env, hdr, scene, _frames = world
    r = _import_with_mapping(env, hdr, scene, "map.yaml", b"vegetation: [1, 2, 3]\n")
    assert r.status_code == 422 and "expected a taxonomy class name" in r.json()["detail"]
    from occufly.io.mask_interchange import resolve_classes
    from occufly.taxonomy import default_taxonomy

    huge = "x" * 900_000  # a 900 KB target (under the 1 MB mapping cap) or class name
    _ids, problems = resolve_classes(["tree", huge], default_taxonomy(), {"tree": huge})
    assert problems and all(len(p) < 2000 for p in problems), [len(p) for p in problems]


def test_every_error_answer_is_bounded():
    from app.errors import MAX_DETAIL_CHARS, bounded

    assert bounded("short") == "short"
    out = bounded("y" * 10_000_000)
    assert len(out) <= MAX_DETAIL_CHARS and out.endswith("characters, cut)")


def test_safe_yaml_refuses_aliases_but_reads_plain_data():
    from occufly import safe_yaml

    assert safe_yaml.load("a: 1\nb: [x, y]\n") == {"a": 1, "b": ["x", "y"]}
    with pytest.raises(safe_yaml.AliasRefused):
        safe_yaml.load("a: &x 1\nb: *x\n")
    assert len(safe_yaml.short("z" * 10_000)) == 80
    assert safe_yaml.short(list(range(10 ** 5))) == "<list of 100000 items>"


# ---- finding 2 (part) / 8: mask imports check names and declared sizes before decoding -----------
def _zip(tmp_path, files: dict, name: str = "a.zip"):  # noqa: ANN001, ANN202
    import zipfile

    p = tmp_path / name
    with zipfile.ZipFile(p, "w") as zf:
        for k, v in files.items():
            zf.writestr(k, v)
    return p


def _cpu_refusal(tmp_path, files, fmt="png", match=""):  # noqa: ANN001, ANN202
    import time

    from occufly.errors import MaskError
    from occufly.io.mask_interchange import read_masks
    from tests.app.conftest import make_tiny_scene

    scene = make_tiny_scene()
    t = time.process_time()
    with pytest.raises(MaskError, match=match) as e:
        read_masks(_zip(tmp_path, files), fmt, scene.frames, scene.taxonomy)
    assert time.process_time() - t < 1.0, "decoded before refusing"
    assert "occufly-masks-" not in str(e.value)  # no temporary path in the message
    return str(e.value)


def test_a_png_bomb_naming_no_frame_is_refused_before_decoding(tmp_path):
    from tests.app.test_hardening import bomb

    # refused while unpacking (its header is larger than any frame) or by the name check
    _cpu_refusal(tmp_path, {"nosuchframe.png": bomb(16000, 12000), "classes.json": '{"1": "tree"}'},
                 match="name no frame|larger than any frame")


def test_a_png_whose_header_is_not_the_frames_size_is_refused_before_decoding(tmp_path):
    from tests.app.conftest import make_tiny_scene
    from tests.app.test_hardening import bomb

    stem = make_tiny_scene().frames[0].stem
    for cmap in ({"classes.json": '{"1": "tree"}'}, {}):
        msg = _cpu_refusal(tmp_path, {f"{stem}.png": bomb(16000, 12000), **cmap},
                           match="16000x12000")
        assert "nothing imported" in msg or "mask is" in msg or "larger than any frame" in msg


def test_a_png_header_of_a_decompression_bomb_is_a_422_not_a_500(tmp_path):
    from tests.app.conftest import make_tiny_scene
    from tests.app.test_hardening import bomb

    stem = make_tiny_scene().frames[0].stem
    _cpu_refusal(tmp_path, {f"{stem}.png": bomb(20000, 20000)[:4096],
                            "classes.json": '{"1": "tree"}'}, match="declares 20000x20000")


def test_a_tiff_named_png_is_refused(tmp_path):
    import io

    from PIL import Image

    from tests.app.conftest import make_tiny_scene

    stem = make_tiny_scene().frames[0].stem
    buf = io.BytesIO()
    Image.new("L", (8, 8)).save(buf, format="TIFF")
    _cpu_refusal(tmp_path, {f"{stem}.png": buf.getvalue(), "classes.json": '{"1": "tree"}'},
                 match="not a PNG")


def test_a_label_studio_brush_of_another_size_is_refused_before_decoding(tmp_path, monkeypatch):
    import json

    from occufly.io import mask_interchange
    from tests.app.conftest import make_tiny_scene

    decoded = {"n": 0}
    monkeypatch.setattr(mask_interchange, "_brush_decoder",
                        lambda: (lambda rle: decoded.__setitem__("n", decoded["n"] + 1)))
    f = make_tiny_scene().frames[0]
    W, H = f.camera.width, f.camera.height
    ok = {"type": "brushlabels", "original_width": W, "original_height": H,
          "value": {"format": "rle", "rle": [0, 0, 0, 1], "brushlabels": ["tree"]}}
    huge = 14000  # 196 MP: under the 200 MP cap, but not this frame's size
    n = huge * huge * 4
    bad = {"type": "brushlabels", "original_width": huge, "original_height": huge,
           "value": {"format": "rle", "rle": list(n.to_bytes(4, "big")), "brushlabels": ["tree"]}}
    # the first result declares the frame's size (the item's size), the second 196 MP
    task = [{"data": {"image": f.name}, "annotations": [{"result": [ok, bad]}]}]
    task[0]["annotations"][0]["result"] = [bad, ok]
    _cpu_refusal(tmp_path, {"tasks.json": json.dumps(task)}, fmt="labelstudio",
                 match="declares 14000x14000")
    assert decoded["n"] == 0


# ---- finding 8: the annotator page's projected review items ------------------------------------
def test_projected_items_show_an_annotator_only_what_it_may_open(world):
    """An item about another frame whose points this frame sees stays hidden from the
    annotator (with its comments); its own frame's item and the scene's frameless 3D item
    show; a reviewer sees all three."""
    from tests.app.test_corrections_api import _seen

    env, hdr, scene, frames = world
    a, rv = hdr["annotator"], hdr["reviewer"]
    fid = env.client.post(f"/api/scenes/{scene['id']}/next", headers=a).json()["id"]
    other = next(f["id"] for f in frames if f["id"] != fid)
    seen = _seen(env, env.settings.workspaces_dir / "tiny", fid)[:30].tolist()
    url = f"/api/scenes/{scene['id']}/review-items"
    made = {}
    for key, frame_id in (("mine", fid), ("other", other), ("frameless", None)):
        r = env.client.post(url, json={"frame_id": frame_id, "point_ids": seen,
                                       "comment": f"about {key}"}, headers=rv)
        assert r.status_code == 201, r.text
        made[key] = r.json()["id"]
    got = env.client.get(f"/api/frames/{fid}/projected-items", headers=a).json()
    assert sorted(it["id"] for it in got) == sorted([made["mine"], made["frameless"]]), got
    assert "about other" not in str(got)
    assert env.client.get(f"/api/review-items/{made['other']}", headers=a).status_code in (403, 404, 405)
    got = env.client.get(f"/api/frames/{fid}/projected-items", headers=rv).json()
    assert sorted(it["id"] for it in got) == sorted(made.values())


# ---- finding 5: a project upload may unpack to a small multiple of itself ------------------------
def test_a_project_upload_unpacks_to_a_multiple_of_its_own_size(env):
    """A 200 KB zip of 100 MB of zeros is refused (the old cap was 4x the 8 GB upload cap:
    it would have kept 100 MB) with nothing left behind; a zip within 10x passes."""
    import io
    import zipfile

    def deflated(entries: dict) -> bytes:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
            for name, data in entries.items():
                z.writestr(name, data)
        return buf.getvalue()

    adm = {**env.bearer("admin"), "Content-Type": "application/zip"}
    bomb = deflated({"p/zeros.bin": b"\0" * (100 << 20)})
    assert len(bomb) < 200_000
    r = env.client.post("/api/imports/upload", params={"name": "bomb"}, content=bomb, headers=adm)
    assert r.status_code == 413 and "10 times the zip's size" in r.json()["detail"], r.text
    up = env.settings.data_dir / "uploads"
    assert not (up / "bomb").exists() and not list((up / ".incoming").iterdir())
    ok = deflated({"p/a.txt": b"x" * 1000})
    r = env.client.post("/api/imports/upload", params={"name": "fine"}, content=ok, headers=adm)
    assert r.status_code == 201, r.text


def test_an_admin_lists_and_deletes_uploads(env):
    """Uploads are listed with their size and the scenes importing from them; one a scene
    uses is kept (409 naming it), another is deleted (audited); only admins."""
    import io
    import zipfile

    from tests.app.conftest import write_tiny_workspace

    adm = env.bearer("admin")
    src = write_tiny_workspace(env.import_root / "ws")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for p in sorted(src.rglob("*")):
            if p.is_file():
                z.write(p, "site/" + p.relative_to(src).as_posix())
    zhead = {**adm, "Content-Type": "application/zip"}
    used = env.client.post("/api/imports/upload", params={"name": "used"}, content=buf.getvalue(),
                           headers=zhead)
    spare = env.client.post("/api/imports/upload", params={"name": "spare"},
                            content=buf.getvalue(), headers=zhead)
    assert used.status_code == spare.status_code == 201, used.text
    r = env.client.post("/api/scenes/import", json={"name": "fromup", "source": used.json()["source"]},
                        headers=adm)
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"], timeout=60)
    sid = r.json()["scene_id"]
    got = {u["name"]: u for u in env.client.get("/api/imports/uploads", headers=adm).json()}
    assert set(got) == {"used", "spare"}
    assert got["used"]["scenes"] == [sid] and got["spare"]["scenes"] == []
    assert got["spare"]["files"] == sum(1 for p in src.rglob("*") if p.is_file())
    assert got["spare"]["bytes"] > 0
    assert env.client.get("/api/imports/uploads", headers=env.bearer("reviewer")).status_code == 403
    assert env.client.delete("/api/imports/uploads/spare",
                             headers=env.bearer("annotator")).status_code == 403
    r = env.client.delete("/api/imports/uploads/used", headers=adm)
    assert r.status_code == 409 and str(sid) in r.json()["detail"]
    assert env.client.delete("/api/imports/uploads/spare", headers=adm).status_code == 204
    assert not (env.settings.data_dir / "uploads" / "spare").exists()
    assert env.client.delete("/api/imports/uploads/spare", headers=adm).status_code == 404
    assert env.client.delete("/api/imports/uploads/.incoming", headers=adm).status_code == 422
    assert [u["name"] for u in env.client.get("/api/imports/uploads", headers=adm).json()] == ["used"]
    from sqlalchemy import select

    from app.audit.models import AuditEvent

    with env.app.state.ctx.sessions() as s:
        assert s.scalars(select(AuditEvent.target).where(
            AuditEvent.action == "upload_delete")).all() == ["spare"]


# ---- finding 8: scene ids are never reused ------------------------------------------------------
def test_a_new_scene_never_takes_a_deleted_scenes_id(env):
    """SQLite gave max(id) + 1: after the newest scene's deletion, the next scene had its id
    (and the audit log mixed the two). Both databases: ids only grow."""
    from sqlalchemy import delete

    from app.scenes import service as scenes
    from app.scenes.models import Scene

    ids = []
    with env.app.state.ctx.sessions() as s:
        for name in ("first", "second"):
            ids.append(scenes.create_scene(session=s, settings=env.settings, name=name,
                                           source=env.import_root).id)
        s.execute(delete(Scene).where(Scene.id == ids[1]))
        s.commit()
        third = scenes.create_scene(session=s, settings=env.settings, name="third",
                                    source=env.import_root).id
        assert third > ids[1], (ids, third)
        s.execute(delete(Scene))
        s.commit()  # every scene gone: still no id handed out twice
        fourth = scenes.create_scene(session=s, settings=env.settings, name="fourth",
                                     source=env.import_root).id
        assert fourth > third
