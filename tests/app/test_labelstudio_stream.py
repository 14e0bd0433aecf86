"""Issue 36 (part B, item 4): a Label Studio JSON export is read one task at a time (ijson),
each brush RLE kept as bytes (one byte a value, not a Python list), so the server's memory is
bounded by one task, not by the file. Measured on the server process itself (the app in a
child process; tests/app/test_import_memory.py's fixture)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.app.test_import_memory import _held, _zip, server  # noqa: F401 - the fixture

pytestmark = pytest.mark.usefixtures("server")


def _tasks(n_tasks: int, n_values: int, name=lambda i: f"nosuch_{i}.png") -> str:  # noqa: ANN001
    rng = np.random.default_rng(0)
    rle = rng.integers(0, 256, n_values).tolist()
    return json.dumps([{"id": i, "data": {"image": name(i)}, "annotations": [{"result": [
        {"type": "brushlabels", "original_width": 64, "original_height": 48,
         "value": {"format": "rle", "rle": rle, "brushlabels": ["tree"]}}]}]}
        for i in range(n_tasks)])


def test_many_tasks_within_the_caps_cost_one_task(server):  # noqa: F811
    """1,100 tasks of 2,600 RLE values each (2.9 M values, 10 MB: the densest the value cap
    lets through): refused for the names (nothing matches a frame) after the whole file was
    read. Parsed whole (json.loads) this took +38 MB of server peak; streamed, +4 MB."""
    body = _tasks(1100, 2600)
    r, mb, cpu = server.import_masks(_zip({"tasks.json": body}), "labelstudio")
    print(f"LS {len(body) / 2**20:.1f} MB of tasks")
    _held(r, mb, cpu, status=(422,), words="nosuch_", cpu_max=10.0)
    assert mb <= 15, f"the server's peak grew {mb:.0f} MB"


def test_a_non_task_is_refused_at_the_first_item(server):  # noqa: F811
    """(parsed whole: +7 MB, 0.21 s CPU; streamed: +1 MB, 0.03 s)"""
    body = "[" + "[1, 2, 3]," * 100_000 + "1]"
    r, mb, cpu = server.import_masks(_zip({"tasks.json": body}), "labelstudio")
    _held(r, mb, cpu, status=(422,), words="list of tasks", cpu_max=1.0)


def test_a_streamed_export_still_imports(server, tmp_path):  # noqa: F811
    from occufly.io import mask_interchange
    from tests.app.conftest import H, W, make_tiny_scene

    sc = make_tiny_scene()
    mask = np.zeros((H, W), np.uint8)
    mask[:, : W // 3] = 8
    out = tmp_path / "ls.zip"
    mask_interchange.write_masks(out, "labelstudio", {1: mask, 2: mask}, sc.frames, sc.taxonomy)
    r, _mb, _cpu = server.import_masks(out.read_bytes(), "labelstudio")
    assert r.status_code == 200 and r.json()["frames_imported"] in (1, 2), r.text[:300]
