import numpy as np
import pytest

from occufly.camera import Camera, look_at
from occufly.errors import WorkspaceError
from occufly.scene import Frame, Scene, Visibility, assign_altitudes, bin_altitudes


def test_bin_altitudes_clusters_to_nominal_heights():
    rng = np.random.default_rng(0)
    alt = np.concatenate([50 + rng.normal(0, 0.8, 30), 40 + rng.normal(0, 0.8, 30), 30 + rng.normal(0, 0.8, 30)])
    assert sorted(set(bin_altitudes(alt).tolist())) == [30, 40, 50]
    assert bin_altitudes(np.array([47.0, 33.0]), nominal=[30, 40, 50]).tolist() == [50, 30]


def test_altitude_above_uneven_ground():
    # ground rises 10 m from west to east; cameras fly 45 m above it
    g = np.linspace(0, 200, 201)
    xx, yy = np.meshgrid(g, g)
    zz = xx * 0.05
    xyz = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]).astype(np.float32)
    cam = Camera("SIMPLE_PINHOLE", 60, 40, [50.0, 30.0, 20.0])
    frames = [Frame(f"f{i}", cam, look_at([x, 100.0, x * 0.05 + 45], [x, 100.0, 0.0], up=[0, 1, 0]))
              for i, x in enumerate([20.0, 100.0, 180.0])]
    scene = Scene(frames, xyz, np.zeros_like(xyz, dtype=np.uint8))
    assign_altitudes(scene)
    for f in scene.frames:
        assert f.altitude == pytest.approx(45.0, abs=1.0)
        assert f.nominal_altitude == 45


def test_visibility_csr():
    v = Visibility.from_parts([
        (np.array([0, 2]), np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([5.0, 6.0])),
        (np.zeros(0, int), np.zeros((0, 2)), np.zeros(0)),
        (np.array([2]), np.array([[7.0, 8.0]]), np.array([9.0])),
    ])
    assert v.offsets.tolist() == [0, 2, 2, 3]
    assert v.frame(2)[0].tolist() == [2] and v.frame(1)[0].size == 0
    assert v.views_per_point(4).tolist() == [1, 0, 2, 0]
    assert v.frames_of_entries().tolist() == [0, 0, 2]
    assert v.point_ids.dtype == np.int32 and v.uv.dtype == np.float32


def test_load_rejects_non_workspace(tmp_path):
    with pytest.raises(WorkspaceError, match="not a scene workspace"):
        Scene.load(tmp_path)
    (tmp_path / "scene.json").write_text("{")
    with pytest.raises(WorkspaceError, match="not valid JSON"):
        Scene.load(tmp_path)


def test_failed_save_leaves_nothing(tmp_path, monkeypatch):
    cam = Camera("SIMPLE_PINHOLE", 60, 40, [50.0, 30.0, 20.0])
    scene = Scene([Frame("a", cam, np.eye(4))], np.zeros((3, 3), np.float32), np.zeros((3, 3), np.uint8))

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Scene, "_header", boom)
    with pytest.raises(OSError):
        scene.save(tmp_path / "ws")
    assert list(tmp_path.iterdir()) == []
