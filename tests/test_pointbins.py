"""The compiled point bins (occufly.pointbins.PointBins) against the numpy construction they
replaced (kept here as the reference: quantile box, inside test, floor of the offsets, a
stable argsort of the bin keys)."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.pointbins import PointBins


def _numpy_bins(xyz: np.ndarray, cell: float | None = None) -> dict:
    xyz = np.asarray(xyz)
    out = {"n": len(xyz), "cell": 1.0, "order": np.zeros(0, np.int64),
           "starts": np.zeros(1, np.int64), "centers": np.zeros((0, 3)),
           "loose": np.zeros(0, np.int64)}
    finite = np.isfinite(xyz).all(axis=1) if len(xyz) else np.zeros(0, bool)
    if not finite.any():
        return out
    fin = xyz[finite]
    sub = fin[:: max(1, len(fin) // 200_000)]
    qlo, qhi = np.quantile(sub, 0.001, axis=0), np.quantile(sub, 0.999, axis=0)
    pad = 0.1 * (qhi - qlo) + 1.0
    lo, hi = (qlo - pad).astype(np.float64), (qhi + pad).astype(np.float64)
    inside = finite & np.all((xyz >= lo) & (xyz <= hi), axis=1)
    out["loose"] = np.flatnonzero(finite & ~inside)
    out["cell"] = float(max(float((hi - lo).max()) / 64.0, 1.0) if cell is None else cell)
    inner = np.flatnonzero(inside)
    ijk = np.floor((xyz[inner] - lo) / out["cell"]).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    o = np.argsort(key, kind="stable")
    out["order"] = inner[o]
    skey = key[o]
    first = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
    out["starts"] = np.r_[first, len(inner)].astype(np.int64)
    u = skey[first]
    ijk_u = np.column_stack([u // (dims[1] * dims[2]), (u // dims[2]) % dims[1], u % dims[2]])
    out["centers"] = lo + (ijk_u + 0.5) * out["cell"]
    return out


def _cloud(n: int, seed: int, dtype=np.float32) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3)) * [60.0, 45.0, 6.0] + [1e3, -2e3, 50.0]
    x[:: 997] *= 300.0  # far outliers: loose points, candidates of every frame
    x = x.astype(dtype)
    x[5] = np.nan
    x[11, 1] = np.inf
    x[12, 2] = -np.inf
    return x


@pytest.mark.parametrize(("n", "seed", "dtype", "cell"), [
    (250_000, 0, np.float32, None), (250_000, 1, np.float32, 3.0), (60_000, 2, np.float64, None),
    (13, 3, np.float32, None), (400_001, 4, np.float32, None), (250_000, 6, np.float32, 400.0)])
def test_compiled_bins_equal_the_numpy_construction(n, seed, dtype, cell):
    xyz = _cloud(n, seed, dtype)
    got, want = PointBins(xyz, cell), _numpy_bins(xyz, cell)
    assert got.n == want["n"] and got.cell == want["cell"]
    for f in ("order", "starts", "centers", "loose"):
        assert np.array_equal(getattr(got, f), want[f]), f
    assert len(got.loose) > 0 or n < 1000
    # every finite point is in exactly one bin or loose; the non-finite ones in neither
    finite = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    assert np.array_equal(np.sort(np.r_[got.order, got.loose]), finite)


def test_memory_mapped_and_degenerate_clouds(tmp_path):
    xyz = _cloud(120_000, 5)
    np.save(tmp_path / "xyz.npy", xyz)
    mm = np.load(tmp_path / "xyz.npy", mmap_mode="r")
    got = PointBins(mm)
    assert np.array_equal(got.order, _numpy_bins(xyz)["order"])
    for bad in (np.zeros((0, 3), np.float32), np.full((4, 3), np.nan, np.float32)):
        b = PointBins(bad)
        assert len(b.order) == 0 and len(b.centers) == 0 and len(b.loose) == 0
    one = PointBins(np.array([[1.0, 2.0, 3.0]], np.float32))
    assert np.array_equal(one.order, [0]) and np.array_equal(one.starts, [0, 1])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        PointBins(np.zeros((5, 2), np.float32))
