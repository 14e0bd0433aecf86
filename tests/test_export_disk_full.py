"""Issue 36 (part B, item 1): an export that fills the disk fails in words, naming the path,
and leaves nothing half-written -- a new target is built under a temporary sibling and renamed
at the end, so ENOSPC at any point (a frame's files, the manifest after the last frame, the
staged grids) removes the partial output. Simulated with monkeypatch (no tiny tmpfs here)."""

from __future__ import annotations

import errno
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


# where the disk fills: a frame's files (2nd frame), the manifest rewritten after the last
# frame, the very first write (the staged grid)
CASES = {"second frame": (common, "write_tmp", 6), "final manifest": (dataset, "_atomic_write", 3),
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
