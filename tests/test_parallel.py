"""Executors: order, progress, and byte-identical exports on a real Dask LocalCluster."""

from __future__ import annotations

from pathlib import Path

import pytest

from occufly.export import export_dataset
from occufly.parallel import DaskExecutor, LocalExecutor, SerialExecutor, get_executor
from tests.export_fixtures import SPEC, make_workspace


def square(x: int) -> int:
    return x * x


def boom(x: int) -> int:
    raise ValueError(f"bad item {x}")


def frame_bytes(root: Path) -> dict[str, bytes]:
    """Every dataset file (not the manifest, whose timestamps differ, nor our state dir)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != "manifest.json" and ".occufly_export" not in p.parts}


def test_serial_and_local_map_in_order_with_progress():
    seen = []
    assert isinstance(get_executor(workers=1), SerialExecutor)
    with get_executor(workers=2) as ex:
        assert isinstance(ex, LocalExecutor)
        assert ex.map(square, range(7), progress=lambda f, m: seen.append(f)) == [i * i for i in range(7)]
        assert ex.submit(square, 9).result() == 81
        with pytest.raises(ValueError, match="bad item 0"):
            ex.map(boom, [0])
    assert seen[-1] == 1.0 and len(seen) == 7


def test_dask_cluster_export_is_byte_identical(tmp_path):
    from distributed import LocalCluster

    ws = make_workspace(tmp_path / "s", n_frames=3)
    with LocalExecutor(2) as ex:
        export_dataset(ws, tmp_path / "local", spec=SPEC, executor=ex)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster:
        with get_executor(cluster.scheduler_address) as dex:
            assert isinstance(dex, DaskExecutor)
            assert dex.map(square, [3, 1, 2]) == [9, 1, 4]
            res = export_dataset(ws, tmp_path / "dask", spec=SPEC, executor=dex)
    assert res["written"] == 3
    a, b = frame_bytes(tmp_path / "local"), frame_bytes(tmp_path / "dask")
    # 7 files per frame + the scene-level calibration.txt + splits/{train,val,test}.txt
    assert len(a) == 3 * 7 + 1 + 3 and a == b
