"""Issue 36 (part B, item 1), in the app: an export job that fills the disk fails with a
message naming the export folder (not the OS message) and leaves neither the export nor its
attempt's staging folder; an archive build that fills the disk is a 507 naming the archive,
with no partial archive left. ENOSPC is simulated with monkeypatch, on both databases."""

from __future__ import annotations

import errno
import zipfile

import numpy as np
import pytest

import occufly.export.common as common
import occufly.export.dataset as dataset
from occufly.parallel import get_executor
from tests.app.conftest import H, W, png
from tests.test_export_disk_full import _fail_after


def _export(env, adm, sid):  # noqa: ANN001, ANN202
    r = env.client.post(f"/api/scenes/{sid}/export", json={}, headers=adm)
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"], timeout=180)
    return env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()


@pytest.fixture
def voxelized(world):
    env, hdr, scene, _frames = world
    sid, ann = scene["id"], hdr["annotator"]
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    va = env.client.put(f"/api/frames/{fa}/mask?kind=submitted", content=png(np.full((H, W), 6, np.uint8)),
                        headers={**ann, "If-Match": "none"}).json()["version"]
    r = env.client.post(f"/api/frames/{fa}/review", json={"decision": "accept", "version": va},
                        headers=hdr["reviewer"])
    assert r.status_code == 200, r.text
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    vox = env.client.post(f"/api/scenes/{scene['id']}/voxelize", json={"voxel_size": 1.0},
                          headers=hdr["admin"]).json()
    env.app.state.ctx.jobs.wait(vox["id"], timeout=120)
    return env, hdr["admin"], scene["id"]


@pytest.mark.parametrize("where", ["a frame", "the manifest after the last frame"])
def test_export_job_filling_the_disk_leaves_nothing(voxelized, monkeypatch, where):
    env, adm, sid = voxelized
    # the export's frames in this process, so the simulated full disk reaches them
    monkeypatch.setattr("app.jobs.registry.get_executor",
                        lambda *a, **k: get_executor(None, 1))
    if where == "a frame":
        calls = _fail_after(monkeypatch, common, "write_tmp", 3)
    else:
        real = dataset._atomic_write
        calls = {"n": 0}

        def failing(path, data):  # noqa: ANN001, ANN202
            if path.name == "manifest.json":
                calls["n"] += 1
                if calls["n"] == 2:  # the rewrite that marks the export complete
                    raise OSError(errno.ENOSPC, "No space left on device")
            return real(path, data)

        monkeypatch.setattr(dataset, "_atomic_write", failing)
    j = _export(env, adm, sid)
    assert calls["n"] >= 1, j["message"]
    exports = env.settings.exports_dir
    out = exports / f"job_{j['id']}"
    assert j["status"] == "failed", j
    assert f"disk full while exporting scene {sid} to {out}" in j["message"], j["message"]
    assert "nothing of this export was kept" in j["message"]
    assert "Errno" not in j["message"] and "internal error" not in j["message"]
    assert not out.exists()
    assert [p.name for p in exports.iterdir()] == []  # no .job_N.attempt1 staging left
    scratch = env.settings.data_dir / "scratch"
    assert not scratch.exists() or not any(scratch.iterdir())
    monkeypatch.undo()
    j2 = _export(env, adm, sid)  # space freed: the same export runs
    assert j2["status"] == "done", j2


def test_archive_build_filling_the_disk_is_507_naming_it(voxelized, monkeypatch):
    env, adm, sid = voxelized
    j = _export(env, adm, sid)
    assert j["status"] == "done", j
    _fail_after(monkeypatch, zipfile.ZipFile, "write", 2)
    r = env.client.post(f"/api/jobs/{j['id']}/archive?format=zip", headers=adm)
    assert r.status_code == 507, r.text
    d = r.json()["detail"]
    assert f"export_job_{j['id']}.zip" in d and "disk full" in d and "nothing was kept" in d
    arch = env.settings.data_dir / "cache" / "archives"
    assert not arch.exists() or [p.name for p in arch.iterdir()] == []
    monkeypatch.undo()
    r = env.client.post(f"/api/jobs/{j['id']}/archive?format=zip", headers=adm)
    assert r.status_code == 200 and r.json()["ready"], r.text
