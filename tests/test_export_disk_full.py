"""Issue 36 (part B, item 1): an export that fills the disk fails in words, naming the path,
and leaves nothing half-written -- a new target is built under a temporary sibling and renamed
at the end, so ENOSPC at any point (a frame's files, the manifest after the last frame, the
staged grids) removes the partial output. Simulated with monkeypatch (no tiny tmpfs here)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

import occufly.export.common as common
import occufly.export.dataset as dataset
from occufly.cli import main
from occufly.export import ExportError, export_dataset
from tests.export_fixtures import SPEC, make_grid, make_workspace


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Path:
    ws = make_workspace(tmp_path_factory.mktemp("full"), n_frames=4)
    if not (ws / "grid" / "scene_grid.npz").exists():
        make_grid().save(ws / "grid" / "scene_grid.npz")
    return ws


def _fail_after(monkeypatch, module, name: str, n_ok: int) -> dict:  # noqa: ANN001
    """``module.name`` raises ENOSPC from its ``n_ok + 1``-th call on."""
    real = getattr(module, name)
    calls = {"n": 0}

    def failing(*a, **k):  # noqa: ANN002, ANN003, ANN202
        calls["n"] += 1
        if calls["n"] > n_ok:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*a, **k)

    monkeypatch.setattr(module, name, failing)
    return calls


def _leftovers(parent: Path, name: str) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if name in p.name)


# where the disk fills: a frame's files, the manifest rewritten after the last
# frame, the very first write (the staged grid)
CASES = {"a frame": (common, "write_tmp", 6), "final manifest": (dataset, "_atomic_write", 3),
         "first write": (dataset, "_atomic_write", 0)}


@pytest.mark.parametrize("where", CASES)
def test_cli_export_filling_the_disk_leaves_nothing(ws, tmp_path, monkeypatch, capsys, where):
    module, name, n_ok = CASES[where]
    out = tmp_path / "exports" / "ds"
    out.parent.mkdir()
    calls = _fail_after(monkeypatch, module, name, n_ok)
    rc = main(["export", str(ws), str(out), "--workers", "1", "--grid-shape", "64,48,64",
               "--voxel-size", "1.0"])
    err = capsys.readouterr().err
    assert calls["n"] > n_ok  # the failure was reached
    assert rc == 2, err
    assert f"disk full while exporting to {out}" in err, err
    assert "partial output was removed" in err
    assert "Errno" not in err  # not the OS message
    assert not out.exists()
    assert _leftovers(out.parent, "ds") == []  # no .ds.<pid>-XXXX.partial sibling either


def test_export_into_an_empty_folder_is_emptied_again(ws, tmp_path, monkeypatch):
    """An existing empty folder (a mount point, say) is written in place, never swapped for a
    sibling on another disk; a full disk leaves it empty."""
    out = tmp_path / "mnt"
    out.mkdir()
    _fail_after(monkeypatch, common, "write_tmp", 6)
    with pytest.raises(ExportError, match=f"disk full while exporting to {out}"):
        export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 1, 2])
    assert out.is_dir() and not any(out.iterdir())


def test_a_new_export_that_completes_is_renamed_into_place(ws, tmp_path):
    out = tmp_path / "ok"
    res = export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 1])
    assert res["out"] == str(out) and res["complete"]
    assert (out / "OccuFly_Dataset").is_dir()
    assert _leftovers(tmp_path, "ok") == ["ok"]


def test_other_errors_name_the_target_not_the_temporary_folder(ws, tmp_path):
    out = tmp_path / "bad"
    with pytest.raises(ExportError) as ei:
        export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 9])
    assert ".partial" not in str(ei.value)
    assert not out.exists() and _leftovers(tmp_path, "bad") == []


def test_an_interrupted_new_export_resumes_from_its_partial_folder(ws, tmp_path, monkeypatch):
    """Ctrl-C (or a kill) leaves the hidden partial folder; the next run takes it over once
    its process is gone, keeps its completed frames and renames it into place."""
    out = tmp_path / "resume"
    real = common.write_tmp
    calls = {"n": 0}

    def interrupted(path, data):  # noqa: ANN001, ANN202
        calls["n"] += 1
        if calls["n"] > 14:  # after the first frame's files and marker
            raise KeyboardInterrupt
        return real(path, data)

    monkeypatch.setattr(common, "write_tmp", interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 1, 2])
    monkeypatch.undo()
    assert not out.exists()
    (partial,) = [p for p in tmp_path.iterdir() if p.name.startswith(".resume.")]
    # as if its process had died: a pid that runs nothing
    dead = partial.with_name(partial.name.replace(f".{os.getpid()}-", ".999999999-"))
    partial.rename(dead)
    res = export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 1, 2])
    assert res["complete"] and res["skipped_done"] >= 1 and res["out"] == str(out)
    assert _leftovers(tmp_path, "resume") == ["resume"]
    assert oct(out.stat().st_mode & 0o777) != oct(0o700)  # not mkdtemp's private mode
