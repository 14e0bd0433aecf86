"""The review computations shared between processes (app.review.disk_cache): one computation
per key across real processes, values that survive the trip (bytes, numpy numbers), pruning,
and the review cache of two processes' memory computing a frame once between them."""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time

import numpy as np
import pytest

from app.review.disk_cache import DiskCache, decode, encode
from app.review.service import _ReviewCache

KEY = ("/data/ws/scene_1", 7, 42, "ab" * 32, ((1, 2), None))


def _value() -> dict:
    return {"version": 42, "figures": {"agreement": np.float32(0.75), "n": np.int64(3),
                                       "per_class": {"road": {"iou": 0.5}}, "none": None,
                                       "arr": np.arange(3)},
            "disagreement_png": b"\x89PNG\r\n\x1a\n\x00\xff"}


def _compute_counted(counter: str, delay: float):
    def compute():
        with open(counter, "a") as f:
            f.write(f"{os.getpid()}\n")
        time.sleep(delay)
        return _value()
    return compute


def _worker(data_dir: str, counter: str, out: str) -> None:
    v = DiskCache("review").get(data_dir, KEY, _compute_counted(counter, 0.6))
    with open(out, "wb") as f:
        f.write(encode(v))


def test_values_survive_the_trip():
    v = decode(encode(_value()))
    assert v["disagreement_png"] == b"\x89PNG\r\n\x1a\n\x00\xff"
    assert v["figures"]["agreement"] == pytest.approx(0.75) and v["figures"]["n"] == 3
    assert v["figures"]["arr"] == [0, 1, 2] and v["figures"]["none"] is None
    assert decode(encode(b"raw")) == b"raw"
    with pytest.raises(TypeError):
        encode({"x": object()})
    with pytest.raises(ValueError):
        decode(b"Xjunk")


def test_one_computation_across_processes(tmp_path):
    counter = str(tmp_path / "computed.txt")
    ctx = mp.get_context("spawn")
    outs = [str(tmp_path / f"out{i}.bin") for i in range(3)]
    procs = [ctx.Process(target=_worker, args=(str(tmp_path), counter, o)) for o in outs]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    with open(counter) as f:
        assert len(f.read().split()) == 1  # one process computed, the others read its entry
    vals = [decode(open(o, "rb").read()) for o in outs]
    assert all(v == vals[0] for v in vals) and vals[0]["disagreement_png"].startswith(b"\x89PNG")
    # this process now reads it without computing
    assert DiskCache("review").get(str(tmp_path), KEY, lambda: pytest.fail("computed again")) == vals[0]


def test_two_processes_memory_caches_compute_a_frame_once(tmp_path):
    """Two _ReviewCache objects (each API process has its own) over one data dir: the page's
    agreement request in one and disagreement request in the other compute once."""
    a, b = (_ReviewCache(3, shared=DiskCache("review")) for _ in range(2))
    calls = []

    def compute():
        calls.append(1)
        time.sleep(0.3)
        return _value()

    got = {}
    ts = [threading.Thread(target=lambda c=c, n=n: got.__setitem__(n, c.get(KEY, compute, tmp_path)))
          for n, c in (("a", a), ("b", b))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert len(calls) == 1 and got["a"]["version"] == got["b"]["version"] == 42
    assert a.has(KEY, tmp_path) and b.has(KEY, tmp_path)
    fresh = _ReviewCache(3, shared=DiskCache("review"))
    assert not fresh.has(KEY) and fresh.has(KEY, tmp_path)  # memory only / shared
    # without a data dir nothing is shared (as before)
    c = _ReviewCache(3, shared=DiskCache("review"))
    c.get(("other",), compute)
    assert len(calls) == 2 and not DiskCache("review").has(tmp_path, ("other",))


def test_prune_keeps_the_newest_entries_within_the_budget(tmp_path):
    dc = DiskCache("review", max_bytes=3 * 1100)
    for i in range(6):
        dc.get(tmp_path, ("k", i), lambda: b"x" * 1000)
        os.utime(dc._entry(tmp_path, ("k", i)), (1000 + i, 1000 + i))
    dc.prune(tmp_path)
    kept = [i for i in range(6) if dc.has(tmp_path, ("k", i))]
    assert kept == [3, 4, 5]
    # an unreadable entry is recomputed, not served
    dc._entry(tmp_path, ("k", 5)).write_bytes(b"garbage")
    assert dc.get(tmp_path, ("k", 5), lambda: b"fresh") == b"fresh"


def test_put_stores_a_value_computed_elsewhere(tmp_path):
    c = _ReviewCache(2, shared=DiskCache("review_render"))
    c.put(("r", 1), b"png-bytes", tmp_path)
    assert c.get(("r", 1), lambda: pytest.fail("computed"), tmp_path) == b"png-bytes"
    other = _ReviewCache(2, shared=DiskCache("review_render"))  # another process
    assert other.get(("r", 1), lambda: pytest.fail("computed"), tmp_path) == b"png-bytes"
    DiskCache("review_render").put(tmp_path, ("r", 1), b"other")  # an entry there is kept
    assert DiskCache("review_render").read(tmp_path, ("r", 1)) == b"png-bytes"
