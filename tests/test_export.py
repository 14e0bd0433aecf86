"""Export: read back literally per FORMATS.md, pooling, resume, refusal, disk full, bad frames,
SSCBench layout, per-altitude grids."""

from __future__ import annotations

import errno
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import yaml

from occufly.errors import WorkspaceError
from occufly.export import ExportError, export_dataset
from occufly.export.common import majority_pool
from occufly.grid import SceneGrid
from occufly.sampling import sample_frame
from occufly.scene import Scene
from occufly.taxonomy import default_taxonomy
from tests.export_fixtures import SPEC, make_grid, make_workspace


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Path:
    return make_workspace(tmp_path_factory.mktemp("exp"), n_frames=4)


@pytest.fixture(scope="module")
def exported(ws, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("out") / "dataset"
    res = export_dataset(ws, out, spec=SPEC, workers=1)
    return out, res


def slow_pool(label: np.ndarray, f: int, tie_order: list[int]) -> np.ndarray:
    """Independent reference of the pooling rule: Python loops over blocks."""
    X, Y, Z = label.shape
    out = np.zeros((X // f, Y // f, Z // f), np.uint8)
    for a in range(X // f):
        for b in range(Y // f):
            for c in range(Z // f):
                blk = label[a * f:(a + 1) * f, b * f:(b + 1) * f, c * f:(c + 1) * f].ravel().tolist()
                counts: dict[int, int] = {}
                for v in blk:
                    if v not in (0, 255):
                        counts[v] = counts.get(v, 0) + 1
                if counts:
                    best = max(counts.values())
                    out[a, b, c] = min((k for k, n in counts.items() if n == best), key=tie_order.index)
                else:
                    out[a, b, c] = 0 if any(v != 255 for v in blk) else 255
    return out


def test_read_back_literally(ws, exported):
    out, res = exported
    assert res["written"] == 4 and res["complete"]
    scene = Scene.load(ws)
    grid = make_grid()
    N = 64 * 48 * 64
    for i, frame in enumerate(scene.frames):
        fid = f"{i:06d}"
        alt = frame.nominal_altitude
        base = out / "OccuFly_Dataset" / "scene_01" / str(alt)
        gtd = base / "ground_truth" / fid
        expect = sample_frame(grid, frame.camera, frame.T_cam_world, scene.origin, SPEC)
        label = np.fromfile(gtd / f"{fid}.label", dtype=np.uint8)
        assert label.size == N
        assert np.array_equal(label.reshape(64, 48, 64), expect.label_with_invalid())
        for name in ("invalid", "occluded", "surface"):
            bits = np.unpackbits(np.fromfile(gtd / f"{fid}.{name}", dtype=np.uint8))[:N]
            assert np.array_equal(bits.reshape(64, 48, 64).astype(bool), getattr(expect, name))
        with open(base / "preprocess" / f"{fid}.pkl", "rb") as fh:
            pkl = pickle.load(fh)
        assert pkl["frame_id"] == fid and pkl["sequence"] == "scene_01" and pkl["altitude"] == alt
        assert pkl["pose"].dtype == np.float32 and pkl["pose"].shape == (4, 4)
        assert np.allclose(pkl["pose"], np.linalg.inv(frame.T_cam_world), atol=1e-4)
        for f, shape in ((1, (64, 48, 64)), (2, (32, 24, 32)), (4, (16, 12, 16)),
                         (8, (8, 6, 8)), (16, (4, 3, 4))):
            assert pkl[f"1_{f}"].dtype == np.uint8 and pkl[f"1_{f}"].shape == shape
        assert np.array_equal(pkl["1_1"], label.reshape(64, 48, 64))
        tie = [int(v) for v in default_taxonomy().tie_order]
        for f in (2, 4, 8, 16) if i == 0 else (8, 16):
            assert np.array_equal(pkl[f"1_{f}"], slow_pool(pkl["1_1"], f, tie)), f
        depth = np.load(base / "depth_maps" / f"{fid}.npy")
        cal = np.loadtxt(base.parent / "calibration.txt")  # scene level (official layout since 2026-08-03)
        assert cal.shape == (6,) and tuple(cal) == (40.0, 40.0, 32.0, 24.0, 64, 48)
        assert depth.dtype == np.float32 and depth.shape == (16 * 12,)
        # the nearly nadir camera sees voxel centres of the ground (z = -0.5) or of the
        # building / tree tops (z = 13.5 / 6.5): depth ~ altitude - height, within tilt
        d = depth[depth > 0]
        assert d.size > 100 and d.min() > alt - 15.0 and d.max() < alt + 1.5
        png = (base / "images" / "visual" / f"{fid}.png").read_bytes()
        assert png == Path(frame.image_path).read_bytes()
    manifest = json.loads((out / "OccuFly_Dataset" / "scene_01" / "manifest.json").read_text())
    assert manifest["complete"] and len(manifest["frames"]) == 4
    assert [c["id"] for c in manifest["taxonomy"]["classes"]] == [int(v) for v in default_taxonomy().ids]


def test_pooling_ties_and_invalid_blocks():
    lab = np.zeros((4, 2, 2), np.uint8)
    lab[0:2] = [[[8, 16], [0, 0]], [[8, 16], [255, 255]]]  # tie 8 vs 16: building more frequent
    lab[2:4] = 255  # all invalid
    prio = default_taxonomy().priority_lut()
    out = majority_pool(lab, 2, prio)
    assert out.ravel().tolist() == [16, 255]
    lab2 = np.zeros((2, 2, 2), np.uint8)
    lab2[0, 0, 0] = 255
    assert majority_pool(lab2, 2, prio).ravel().tolist() == [0]


def test_resume_rewrites_only_incomplete_frames(ws, tmp_path):
    out = tmp_path / "d"
    export_dataset(ws, out, spec=SPEC, workers=1)
    base = out / "OccuFly_Dataset" / "scene_01"
    f1 = base / "30" / "ground_truth" / "000001" / "000001.label"
    f0 = base / "50" / "ground_truth" / "000000" / "000000.label"
    m0 = f0.stat().st_mtime_ns
    # simulate an interruption in frame 1: marker missing, one file truncated
    (out / ".occufly_export" / "occufly" / "scene_01" / "done" / "30_000001.json").unlink()
    good = f1.read_bytes()
    f1.write_bytes(good[:100])
    (base / "30" / "preprocess" / ".000001.pkl.abc.tmp").write_bytes(b"junk")
    res = export_dataset(ws, out, spec=SPEC, workers=1)
    assert res["written"] == 1 and res["skipped_done"] == 3 and res["complete"]
    assert f1.read_bytes() == good
    assert f0.stat().st_mtime_ns == m0  # completed frames untouched
    assert not (base / "30" / "preprocess" / ".000001.pkl.abc.tmp").exists()
    # a file of a completed frame changed size -> detected and rewritten
    f0.write_bytes(b"x")
    res = export_dataset(ws, out, spec=SPEC, workers=1)
    assert res["written"] == 1 and f0.stat().st_size == 64 * 48 * 64


def test_refuses_foreign_target(ws, tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ExportError, match="not an earlier occufly export"):
        export_dataset(ws, out, spec=SPEC, workers=1)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    # an export of another scene under the same scene id is refused, and left untouched
    other = make_workspace(tmp_path / "other", n_frames=2)
    sc = Scene.load(other)
    sc.frames[0].T_cam_world[0, 3] += 1.0
    sc.save(other, overwrite=True)
    make_grid().save(other / "grid" / "scene_grid.npz")
    out2 = tmp_path / "d2"
    export_dataset(ws, out2, spec=SPEC, workers=1, frames=[0])
    before = {p: p.read_bytes() for p in out2.rglob("*") if p.is_file()}
    with pytest.raises(ExportError, match="different scene"):
        export_dataset(other, out2, spec=SPEC, workers=1)
    assert {p: p.read_bytes() for p in out2.rglob("*") if p.is_file()} == before
    # but another scene id in the same root is fine
    res = export_dataset(other, out2, scene_id="scene_02", spec=SPEC, workers=1)
    assert res["written"] == 2


def test_disk_full_leaves_no_half_frame(ws, tmp_path, monkeypatch):
    out = tmp_path / "full"
    export_dataset(ws, out, spec=SPEC, workers=1, frames=[0])
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name not in ("manifest.json", "calibration.txt")}
    import occufly.export.common as common

    real = common.write_tmp
    calls = {"n": 0}

    def failing(path, data):
        calls["n"] += 1
        if calls["n"] == 4:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, data)

    monkeypatch.setattr(common, "write_tmp", failing)
    with pytest.raises(ExportError, match="disk full"):
        export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 1])
    monkeypatch.undo()
    after = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name not in ("manifest.json", "calibration.txt")}
    assert after == before  # frame 1 has no file at all, frame 0 untouched
    assert not list(out.rglob("*.tmp"))
    res = export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 1])
    assert res["written"] == 1 and res["complete"]


def test_frame_without_pose_writes_nothing(tmp_path):
    ws = make_workspace(tmp_path / "np", n_frames=2)
    sc = Scene.load(ws)
    sc.frames[1].T_cam_world = np.full((4, 4), np.nan)
    sc.save(ws, overwrite=True)
    make_grid().save(ws / "grid" / "scene_grid.npz")
    with pytest.raises(WorkspaceError, match=r"frame 1 \(img_001.png\).*no valid pose"):
        export_dataset(ws, tmp_path / "o", spec=SPEC, workers=1)
    assert not (tmp_path / "o").exists()


def test_sscbench_layout(ws, tmp_path):
    out = tmp_path / "ssc"
    export_dataset(ws, out, spec=SPEC, workers=1, layout="sscbench", frames=[0, 1])
    doc = yaml.safe_load((out / "occufly.yaml").read_text())
    lm = doc["learning_map"]
    inv = doc["learning_map_inv"]
    assert lm[0] == 0 and lm[255] == 255 and lm[16] == 14 and inv[14] == 16  # building: row 14
    scene = Scene.load(ws)
    grid = make_grid()
    fr = scene.frames[1]
    seq = out / "data_2d_raw" / "scene_01_30"
    assert sorted(p.name for p in (seq / "voxels").glob("*.bin")) == ["000001.bin"]
    expect = sample_frame(grid, fr.camera, fr.T_cam_world, scene.origin, SPEC)
    raw = np.fromfile(seq / "voxels" / "000001.label", dtype=np.uint16).reshape(64, 48, 64)
    assert np.array_equal(raw, expect.label_with_invalid())
    N = raw.size
    occ = np.unpackbits(np.fromfile(seq / "voxels" / "000001.bin", np.uint8))[:N].reshape(raw.shape)
    assert np.array_equal(occ.astype(bool), (expect.labels != 0) & ~expect.occluded)
    lab11 = np.load(out / "preprocess" / "labels" / "scene_01_30" / "000001_1_1.npy")
    back = np.vectorize(lambda v: 255 if v == 255 else inv[int(v)])(lab11)
    assert np.array_equal(back, expect.label_with_invalid())
    lab18 = np.load(out / "preprocess" / "labels" / "scene_01_30" / "000001_1_8.npy")
    assert lab18.shape == (8, 6, 8)
    assert (seq / "image_00" / "data_rect" / "000001.png").is_file()
    assert np.load(out / "depth" / "scene_01_30" / "000001.npy").shape == (12, 16)


def test_lower_altitudes_sample_the_highest_grid(ws, tmp_path):
    g50 = make_grid()
    g30 = SceneGrid(np.zeros_like(g50.labels), g50.origin, g50.voxel_size)  # empty
    out = tmp_path / "alt"
    res = export_dataset(ws, out, spec=SPEC, workers=1, grid={50: g50, 30: g30}, frames=[1])
    assert res["grid_for_altitude"] == {"30": 50, "50": 50}
    lab = np.fromfile(out / "OccuFly_Dataset/scene_01/30/ground_truth/000001/000001.label", np.uint8)
    assert np.count_nonzero((lab != 0) & (lab != 255)) > 1000
    out2 = tmp_path / "alt2"
    export_dataset(ws, out2, spec=SPEC, workers=1, grid={50: g50, 30: g30}, frames=[1],
                   grid_for_altitude={30: 30})
    lab = np.fromfile(out2 / "OccuFly_Dataset/scene_01/30/ground_truth/000001/000001.label", np.uint8)
    assert not np.any((lab != 0) & (lab != 255))


def test_preview_png(exported, tmp_path):
    from PIL import Image

    from occufly.cli import main

    out, _ = exported
    png = tmp_path / "p.png"
    assert main(["preview", str(out), "--frame", "2", "--out", str(png), "--height", "96"]) == 0
    im = np.asarray(Image.open(png).convert("RGB"))
    assert im.shape[0] == 96 + 16 + 12
    colours = {tuple(c) for c in im.reshape(-1, 3)}
    assert (255, 0, 0) in colours and (0, 255, 0) in colours  # building and grass voxels drawn
    assert main(["preview", str(out), "--frame", "999", "--out", str(png)]) == 2


# ---- the exported image: fast PNG encoding, same pixels -------------------------------------
@pytest.mark.parametrize("shape", [(1, 1), (1, 7, 3), (9, 1, 4), (13, 17), (31, 29, 3), (6, 5, 4)])
def test_encode_png_round_trips_exactly(shape):
    import io

    from PIL import Image

    from occufly.export.common import encode_png

    a = np.random.default_rng(len(shape) * 100 + shape[0]).integers(0, 256, shape, dtype=np.uint8)
    data = encode_png(a)
    assert data == encode_png(a.copy())  # deterministic
    with Image.open(io.BytesIO(data)) as im:
        assert im.format == "PNG"
        assert im.mode == ("L" if a.ndim == 2 else "RGB" if shape[2] == 3 else "RGBA")
        assert np.array_equal(np.asarray(im), a)


def _inflate_png(data: bytes) -> np.ndarray:
    """Independent of PIL: the PNG's chunks parsed, its IDAT streams inflated by zlib and the
    per-row filters undone (this encoder writes filter 2, "Up", on every row)."""
    import struct
    import zlib

    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, hdr = 8, [], None
    while pos < len(data):
        (n,), tag = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + n]
        assert struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])[0] == zlib.crc32(tag + body)
        if tag == b"IHDR":
            hdr = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat.append(body)
        pos += 12 + n
    w, h, depth, colour = hdr[:4]
    ch = {0: 1, 2: 3, 6: 4}[colour]
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, w * ch + 1)
    assert depth == 8 and (raw[:, 0] == 2).all()
    rows = np.cumsum(raw[:, 1:].astype(np.int64), axis=0) % 256  # undo "Up"
    return rows.astype(np.uint8).reshape((h, w) if ch == 1 else (h, w, ch))


@pytest.mark.parametrize("shape", [(700, 801, 3), (1300, 911), (520, 603, 4)])
def test_encode_png_several_bands_and_strided_views(shape):
    """Images taller than one filter band, and views that are not C-contiguous (the RGB of an
    RGBX buffer, a cropped window): PIL and an independent inflate read exactly the array."""
    import io

    from PIL import Image

    from occufly.export.common import encode_png

    rng = np.random.default_rng(shape[0])
    # photo-like: smooth gradients plus noise (long runs and matches for the deflate)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    base = ((yy // 3 + xx // 5) % 256).astype(np.uint8)
    full = base[..., None] if len(shape) == 3 else base
    a = (full + rng.integers(0, 9, shape, dtype=np.uint8)).astype(np.uint8)
    views = [a]
    if a.ndim == 3 and a.shape[2] == 3:
        rgbx = np.zeros((*a.shape[:2], 4), np.uint8)
        rgbx[..., :3] = a
        views.append(rgbx[..., :3])  # strided
    views.append(a[5:-7, 3:-11])  # a window: rows not contiguous
    for v in views:
        data = encode_png(v)
        assert data == encode_png(np.ascontiguousarray(v))  # same bytes from any layout
        assert np.array_equal(_inflate_png(data), v)
        with Image.open(io.BytesIO(data)) as im:
            assert np.array_equal(np.asarray(im), v)


def test_jpeg_export_is_the_same_bytes_in_any_process(tmp_path):
    """JPEG frames go through our PNG encoder: serial, a local pool of 2 processes and a Dask
    cluster write byte-identical files, and every PNG holds exactly PIL's decode of the JPEG."""
    from distributed import LocalCluster
    from PIL import Image

    from occufly.parallel import LocalExecutor, get_executor
    from occufly.scene import Scene

    ws = make_workspace(tmp_path / "s", n_frames=3, image_ext=".jpg")
    export_dataset(ws, tmp_path / "serial", spec=SPEC, workers=1)
    with LocalExecutor(2) as ex:
        export_dataset(ws, tmp_path / "local", spec=SPEC, executor=ex)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cl:
        with get_executor(cl.scheduler_address) as dex:
            export_dataset(ws, tmp_path / "dask", spec=SPEC, executor=dex)

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
                if p.is_file() and p.name != "manifest.json" and ".occufly_export" not in p.parts}

    a = files(tmp_path / "serial")
    assert a == files(tmp_path / "local") == files(tmp_path / "dask")
    scene = Scene.load(ws)
    pngs = sorted(k for k in a if k.endswith(".png"))
    assert len(pngs) == 3
    for k in pngs:
        fr = scene.frames[int(Path(k).stem)]
        with Image.open(fr.image_path) as src:
            assert np.array_equal(_inflate_png(a[k]), np.asarray(src))


@pytest.mark.parametrize("hw,shape", [((48, 64), (12, 16)), ((13, 17), (13, 17)), ((7, 5), (2, 1)),
                                      ((401, 603), (100, 151))])
def test_depth_map_read_only_at_the_samples_it_keeps(tmp_path, hw, shape):
    """The export's depth read (only the kept rows of the file) gives what reading the whole
    COLMAP map and nearest-sampling it gives: non-finite and negative depths 0. A malformed
    file is refused by the full reader, naming the file."""
    from occufly.errors import InputFormatError
    from occufly.sampling import read_depth_map_resampled, resample_depth

    H, W = hw
    x = np.random.default_rng(H).normal(3.0, 2.0, hw).astype(np.float32)  # some < 0
    x[0, 0], x[-1, -1], x[H // 2, 0] = np.nan, np.inf, -np.inf
    p = tmp_path / "f.jpg.geometric.bin"
    p.write_bytes(f"{W}&{H}&1&".encode() + np.asfortranarray(x.T).tobytes(order="F"))  # COLMAP layout
    ref = np.where(np.isfinite(x) & (x >= 0), x, 0).astype(np.float32)
    got = read_depth_map_resampled(p, shape)
    assert got.dtype == np.float32 and got.shape == shape and got.flags.c_contiguous
    assert np.array_equal(got, resample_depth(ref, shape))
    p.write_bytes(p.read_bytes()[:-4])  # truncated
    with pytest.raises(InputFormatError, match=r"f\.jpg\.geometric\.bin: depth map is truncated"):
        read_depth_map_resampled(p, shape)
    p.write_bytes(b"not a depth map")
    with pytest.raises(InputFormatError, match="not a COLMAP depth map"):
        read_depth_map_resampled(p, shape)


def test_encode_png_refuses_other_arrays():
    from occufly.export.common import encode_png

    for bad in (np.zeros((4, 4), np.uint16), np.zeros((4, 4, 2), np.uint8), np.zeros((0, 4), np.uint8)):
        with pytest.raises(ValueError, match="encode_png"):
            encode_png(bad)


def test_encode_png_palette_decodes_to_the_palette_colours():
    """An indexed PNG (the review's overlay): PIL, a reader we did not write, decodes it to
    ``palette[indices]`` -- RGBA through tRNS, RGB without, a short palette, several bands --
    and indices past the palette or a palette of the wrong shape are refused."""
    import io

    from PIL import Image

    from occufly.export.common import encode_png

    rng = np.random.default_rng(11)
    for h, w, P, ch in ((3, 5, 256, 4), (700, 1900, 7, 4), (64, 33, 12, 3), (1, 1, 1, 3)):
        pal = rng.integers(0, 256, (P, ch)).astype(np.uint8)
        idx = rng.integers(0, P, (h, w)).astype(np.uint8)
        idx[: h // 2, : w // 3] = 0  # runs, as an overlay's transparent areas
        data = encode_png(idx, palette=pal)
        with Image.open(io.BytesIO(data)) as im:
            assert im.mode == "P" and im.size == (w, h)
            assert np.array_equal(np.asarray(im), idx)
            got = np.asarray(im.convert("RGBA" if ch == 4 else "RGB"))
        assert np.array_equal(got, pal[idx])
    pal = np.zeros((4, 4), np.uint8)
    with pytest.raises(ValueError, match="index 4 past the 4-colour palette"):
        encode_png(np.full((2, 2), 4, np.uint8), palette=pal)
    for bad in (np.zeros((0, 3), np.uint8), np.zeros((257, 3), np.uint8), np.zeros((4, 2), np.uint8),
                np.zeros((4, 3), np.int32)):
        with pytest.raises(ValueError, match="palette must be"):
            encode_png(np.zeros((2, 2), np.uint8), palette=bad)
    with pytest.raises(ValueError, match="a palette image is"):
        encode_png(np.zeros((2, 2, 3), np.uint8), palette=pal)


def test_exported_jpeg_is_the_same_pixels_and_keeps_icc(tmp_path):
    """A JPEG frame becomes a PNG holding exactly PIL's decoded pixels (and its ICC profile);
    a palette image goes through PIL unchanged in meaning."""
    import io

    from PIL import Image

    from occufly.export.dataset import _image_png

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (40, 56, 3), dtype=np.uint8)
    icc = b"\x00fake-icc-profile" * 10
    p = tmp_path / "f.jpg"
    Image.fromarray(rgb).save(p, quality=90, icc_profile=icc)
    png = _image_png(str(p), "frame f")
    with Image.open(p) as src, Image.open(io.BytesIO(png)) as out:
        assert out.format == "PNG"
        assert np.array_equal(np.asarray(out), np.asarray(src))
        assert out.info.get("icc_profile") == icc
    pal = tmp_path / "p.gif"
    Image.fromarray(rgb).convert("P").save(pal)
    with Image.open(pal) as src, Image.open(io.BytesIO(_image_png(str(pal), "frame p"))) as out:
        assert out.mode == "P"
        assert np.array_equal(np.asarray(out.convert("RGB")), np.asarray(src.convert("RGB")))


def test_export_that_cannot_fit_in_memory_is_refused_before_writing(ws, tmp_path, monkeypatch):
    from occufly.export import dataset
    from occufly.parallel import DaskExecutor, LocalExecutor, SerialExecutor

    out = tmp_path / "big"
    monkeypatch.setattr("occufly.fsutil.available_memory", lambda: 50 * 2**20)
    with pytest.raises(ExportError, match=r"2 local worker\(s\) .* needs about .* GB of memory, 0\.0 GB are available"):
        export_dataset(ws, out, spec=SPEC, workers=2)
    assert not out.exists() or not any(out.rglob("*"))
    # the estimate: workers x (fixed + grid + image + frame grid) + the caller's grid
    grid = SceneGrid.load(ws / "grid" / "scene_grid.npz")
    one = dataset.export_memory_estimate([grid], SPEC, 1000, 0)
    assert dataset.export_memory_estimate([grid], SPEC, 1000, 3) == grid.labels.nbytes + 3 * one
    assert dataset._local_workers(None, None, 5) == 2 and dataset._local_workers(None, 1, 5) == 0
    assert dataset._local_workers(SerialExecutor(), None, 5) == 0
    assert dataset._local_workers(object.__new__(DaskExecutor), None, 5) is None  # remote: unchecked
    with LocalExecutor(3) as ex:
        assert dataset._local_workers(ex, None, 5) == 3
    monkeypatch.setattr("occufly.fsutil.available_memory", lambda: None)
    assert export_dataset(ws, out, spec=SPEC, workers=1)["written"] == 4
