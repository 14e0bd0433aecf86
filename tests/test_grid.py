"""SceneGrid: geometry, round trip through .npz, bad files."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.errors import InputFormatError
from occufly.grid import SceneGrid
from occufly.workspace import Workspace


def test_index_centers_lookup_round_trip(tmp_path):
    origin = np.array([654_321.25, 5_123_456.5, 212.0])
    lab = np.zeros((10, 8, 6), np.uint8)
    lab[3, 4, 5] = 16
    lab[0, 0, 0] = 6
    g = SceneGrid(lab, origin, 0.5)
    c = g.centers()
    assert np.allclose(c, origin + np.array([[0.25, 0.25, 0.25], [1.75, 2.25, 2.75]]))
    ijk, inside = g.index_of(c)
    assert inside.all() and ijk.tolist() == [[0, 0, 0], [3, 4, 5]]
    assert g.lookup(c).tolist() == [6, 16]
    out = origin + [[-0.01, 1, 1], [5.0, 1, 1], [1, 1, 2.99]]
    assert g.index_of(out)[1].tolist() == [False, False, True]
    ijk_l, inside_l = g.index_of_local(np.float32([[1.75, 2.25, 2.75]]) + np.float32(0.0), origin)
    assert inside_l.all() and ijk_l.tolist() == [[3, 4, 5]]
    assert g.class_counts() == {6: 1, 16: 1}
    p = g.save(Workspace(tmp_path).grid_path())
    assert p == tmp_path / "grid" / "scene_grid.npz"
    h = SceneGrid.load(p)
    assert np.array_equal(h.labels, lab) and np.array_equal(h.origin, origin) and h.voxel_size == 0.5
    with np.load(p) as z:  # the documented layout, readable without occufly
        assert set(z.files) == {"labels", "origin", "voxel_size"} and z["labels"].dtype == np.uint8


def test_bad_grids(tmp_path):
    with pytest.raises(InputFormatError, match="not found"):
        SceneGrid.load(tmp_path / "nope.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, labels=np.zeros((2, 2, 2), np.uint8), origin=np.zeros(3))
    with pytest.raises(InputFormatError, match="missing array.*voxel_size"):
        SceneGrid.load(bad)
    np.savez(bad, labels=np.zeros((2, 2), np.uint8), origin=np.zeros(3), voxel_size=1.0)
    with pytest.raises(InputFormatError, match="3-D uint8"):
        SceneGrid.load(bad)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputFormatError, match="not a readable"):
        SceneGrid.load(tmp_path / "junk.npz")
    with pytest.raises(ValueError, match="voxel_size"):
        SceneGrid(np.zeros((2, 2, 2), np.uint8), np.zeros(3), 0.0)
