"""Export gating and provenance end to end (issue 23): an export takes accepted versions unless
the request includes submitted / imported ones; it lifts a narrower set again in a scratch
folder; its manifest names every voting mask (version, state, author, reviewer, decided_at,
source, sha256) and lifting exactly those versions again reproduces the labels byte for byte;
``quality.json`` lies beside the manifest; the result never lists drafts as taken frames."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from app import pipeline
from occufly.lifting.relift import labels_digest, relift
from occufly.scene import Scene
from tests.app.conftest import H, W, png

GRASS, ROAD = 6, 1


def _mask(cls: int) -> bytes:
    return png(np.full((H, W), cls, np.uint8))


def _job(env, hdr, sid, body):  # noqa: ANN001
    r = env.client.post(f"/api/scenes/{sid}/export", json=body, headers=hdr)
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"], timeout=180)
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=hdr).json()
    return j


def _manifest(j) -> tuple[dict, Path]:  # noqa: ANN001
    mp = Path(j["result"]["output"]) / "OccuFly_Dataset" / j["result"]["summary"]["scene_id"] / "manifest.json"
    return json.loads(mp.read_text()), mp


def _frame_classes(out: Path, m: dict) -> set[int]:
    from occufly.export.occufly import read_frame

    ids: set[int] = set()
    for fid, a in m["frames"].items():
        lab = read_frame(out, m["scene_id"], a["altitude"], fid, tuple(m["grid_spec"]["shape"]))["label"]
        ids |= {int(v) for v in np.unique(lab)} - {0, 255}
    return ids


def _relift_from_manifest(env, m: dict, ws: Path, tmp: Path):  # noqa: ANN001
    """Lift exactly the versions the manifest names, from the mask store's bytes."""
    store = env.app.state.ctx.store
    scene = Scene.load(ws)
    items = []
    for e in m["provenance"]["masks"]:
        data = store.get(e["sha256"])
        assert hashlib.sha256(data).hexdigest() == e["sha256"]
        items.append((e["frame"], str(e["version"]), pipeline.stored_mask_ids(data, scene.taxonomy)))
    return relift(scene, items, tmp)


def test_export_takes_accepted_versions_by_default_and_records_their_provenance(world, tmp_path):
    env, hdr, scene, _frames = world
    sid, adm, ann, rev = scene["id"], hdr["admin"], hdr["annotator"], hdr["reviewer"]
    lm = env.app.state.ctx.lifting
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    va = env.client.put(f"/api/frames/{fa}/mask?kind=submitted", content=_mask(GRASS),
                        headers={**ann, "If-Match": "none"}).json()["version"]
    fb = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    assert fb != fa
    vb = env.client.put(f"/api/frames/{fb}/mask?kind=submitted", content=_mask(ROAD),
                        headers={**ann, "If-Match": "none"}).json()["version"]
    fc = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    assert fc not in (fa, fb)
    r = env.client.put(f"/api/frames/{fc}/mask", content=_mask(ROAD),
                       headers={**ann, "If-Match": "none"})  # an autosaved draft, in progress
    assert r.status_code == 200 and r.json()["kind"] == "draft"
    r = env.client.post(f"/api/frames/{fa}/review", json={"decision": "accept", "version": va},
                        headers=rev)
    assert r.status_code == 200, r.text
    assert lm.wait_idle(sid, timeout=60, include_fill=True)
    frames = {f["id"]: f["index"] for f in env.client.get(f"/api/scenes/{sid}/frames", headers=adm).json()}
    ia, ib, ic = frames[fa], frames[fb], frames[fc]
    ws = env.settings.workspaces_dir / "tiny"
    live = json.loads((ws / "lifting" / "labels.json").read_text())["versions"]
    assert live == {str(ia): str(va), str(ib): str(vb)}  # the live labels count both

    # what the admin page lists before it asks
    plan = env.client.get(f"/api/scenes/{sid}/export/plan", headers=adm).json()
    assert [t["frame"] for t in plan["taken"]] == [ia]
    assert plan["left_out"]["draft"] == [ic] and plan["left_out"]["submitted"] == [ib]
    assert plan["took"] == "1 accepted frame; left out: 1 draft, 1 submitted"
    assert plan["labels_from_masks"] is True
    assert env.client.get(f"/api/scenes/{sid}/export/plan?include=accepted,bogus",
                          headers=adm).status_code == 422
    assert env.client.get(f"/api/scenes/{sid}/export/plan", headers=rev).status_code == 403

    vox = env.client.post(f"/api/scenes/{sid}/voxelize", json={"voxel_size": 1.0}, headers=adm).json()
    env.app.state.ctx.jobs.wait(vox["id"], timeout=120)

    # default: accepted only -> lifted again without the submitted frame
    j = _job(env, adm, sid, {})
    assert j["status"] == "done", j["message"]
    assert j["params"]["include"] == ["accepted"]
    rv = j["result"]["review"]
    assert rv["n_frames"] == 1 and rv["unreviewed_frames"] == []
    assert ic not in rv["unreviewed_frames"]  # the draft is not passed off as taken
    assert rv["left_out"]["draft"] == [ic] and rv["left_out"]["submitted"] == [ib]
    assert rv["took"] == "1 accepted frame; left out: 1 draft, 1 submitted"
    m, mp = _manifest(j)
    pv = m["provenance"]
    assert pv["policy"]["include"] == ["accepted"] and pv["labels"]["relifted"] is True
    (e,) = pv["masks"]
    assert e["frame"] == ia and e["version"] == va and e["state"] == "accepted"
    assert e["author"] == "annotator" and e["reviewer"] == "reviewer" and e["decided_at"]
    assert "source" in e and len(e["sha256"]) == 64
    res = _relift_from_manifest(env, m, ws, tmp_path / "again")
    assert labels_digest(res) == pv["labels"]["sha256"]
    assert _frame_classes(mp.parents[2], m) == {GRASS}  # no road: frame b's votes left out
    q = json.loads((mp.parent / "quality.json").read_text())
    assert q["format"] == "occufly-quality" and q["policy"]["include"] == ["accepted"]
    assert q["annotated_frames"] == 1 and q["versions"] == {str(ia): str(va)}
    assert not list((env.settings.data_dir / "scratch").glob("*"))  # scratch removed

    # submitted taken in as well: exactly the live labels, their bytes reproduced
    j2 = _job(env, adm, sid, {"include": ["accepted", "submitted", "imported"]})
    assert j2["status"] == "done", j2["message"]
    rv2 = j2["result"]["review"]
    assert rv2["unreviewed_frames"] == [ib] and rv2["left_out"]["draft"] == [ic]
    assert rv2["took"] == "1 accepted, 1 submitted frames; left out: 1 draft"
    m2, mp2 = _manifest(j2)
    assert m2["provenance"]["labels"]["relifted"] is False
    assert {(x["frame"], x["version"], x["state"]) for x in m2["provenance"]["masks"]} == {
        (ia, va, "accepted"), (ib, vb, "submitted")}
    _relift_from_manifest(env, m2, ws, tmp_path / "again2")
    for name in ("labels", "confidence", "origin"):
        assert ((tmp_path / "again2" / "lifting" / f"{name}.npy").read_bytes()
                == (ws / "lifting" / f"{name}.npy").read_bytes()), name
    assert _frame_classes(mp2.parents[2], m2) >= {ROAD}
    assert json.loads((mp2.parent / "quality.json").read_text())["annotated_frames"] == 2

    # the scene's quality report (admin page): admin and reviewer, cached per labels stamp
    # (waiting for the background computation as long as it takes: tests/app/test_quality_cache
    # checks the answers while it runs)
    env.app.state.ctx.settings = dataclasses.replace(env.settings, quality_wait_s=300)
    q1 = env.client.get(f"/api/scenes/{sid}/quality", headers=rev)
    assert q1.status_code == 200, q1.text
    assert q1.json()["annotated_frames"] == 2 and q1.json()["cached"] is False
    assert env.client.get(f"/api/scenes/{sid}/quality", headers=adm).json()["cached"] is True
    from app.review import quality_cache

    quality_cache._CACHE.clear()  # another API process (or a restart) reads the shared file
    q2 = env.client.get(f"/api/scenes/{sid}/quality", headers=adm).json()
    assert q2["cached"] is True and q2["labels_stamp"] == q1.json()["labels_stamp"]
    assert env.client.get(f"/api/scenes/{sid}/quality", headers=ann).status_code == 403


def test_export_with_nothing_accepted_fails_naming_the_policy(world):
    env, hdr, scene, _frames = world
    sid, adm, ann = scene["id"], hdr["admin"], hdr["annotator"]
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    env.client.put(f"/api/frames/{fa}/mask?kind=submitted", content=_mask(GRASS),
                   headers={**ann, "If-Match": "none"})
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    plan = env.client.get(f"/api/scenes/{sid}/export/plan", headers=adm).json()
    assert plan["taken"] == [] and plan["labels_from_masks"] is True  # the page says so first
    j = _job(env, adm, sid, {})
    assert j["status"] == "failed"
    assert "nothing to export" in j["message"] and "accepted" in j["message"]
    assert env.client.post(f"/api/scenes/{sid}/export", json={"include": ["draft"]},
                           headers=adm).status_code == 422
    env.app.state.ctx.settings = dataclasses.replace(env.settings, quality_wait_s=300)
    assert env.client.get(f"/api/scenes/{sid}/quality", headers=adm).status_code == 200


def test_app_cli_scene_export_takes_accepted_versions_unless_told(world, monkeypatch, capsys):
    from occufly.cli import main

    env, hdr, scene, _frames = world
    sid, ann, rev = scene["id"], hdr["annotator"], hdr["reviewer"]
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    va = env.client.put(f"/api/frames/{fa}/mask?kind=submitted", content=_mask(GRASS),
                        headers={**ann, "If-Match": "none"}).json()["version"]
    fb = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    env.client.put(f"/api/frames/{fb}/mask?kind=submitted", content=_mask(ROAD),
                   headers={**ann, "If-Match": "none"})
    env.client.post(f"/api/frames/{fa}/review", json={"decision": "accept", "version": va}, headers=rev)
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    s = env.settings
    for k, v in {"OCCUFLY_DATA_DIR": str(s.data_dir), "OCCUFLY_DATABASE_URL": s.database_url,
                 "OCCUFLY_IMPORT_ROOTS": str(env.import_root), "OCCUFLY_ENV": "development",
                 "OCCUFLY_LIFTING": "off"}.items():
        monkeypatch.setenv(k, v)
    assert main(["scene-export", "tiny", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["include"] == ["accepted"] and out["took"] == "1 accepted frame; left out: 1 submitted"
    m = json.loads((Path(out["output"]) / "OccuFly_Dataset" / f"scene_{sid:02d}" / "manifest.json").read_text())
    assert [(e["version"], e["state"]) for e in m["provenance"]["masks"]] == [(va, "accepted")]
    assert main(["scene-export", "nosuchscene"]) == 2
    assert "no scene with that id or name" in capsys.readouterr().err
