"""Read an export back, in either layout, with numpy and Pillow only.

>>> ds = open_dataset("exports/occufly")          # layout detected from the folder
>>> ds.layout, len(ds), ds.frames[0]
('occufly', 4, FrameKey(scene='scene_01', altitude=50, frame_id='000000', sequence='scene_01_50'))
>>> s = ds[0]
>>> s["image"].shape, s["grids"]["1_8"].shape, s["depth"].shape, s["K"]

Each sample is a dict:

``scene``, ``altitude``, ``frame_id``, ``sequence``
    identity (``sequence`` = ``<scene>_<altitude>``, the SSCBench sequence name).
``image``
    (H, W, 3) uint8 RGB.
``label``
    (X, Y, Z) uint8 raw class ids, 0 empty, 255 invalid (``.label``).
``grids``
    {"1_1", "1_2", ...}: (X/f, Y/f, Z/f) uint8 label grids as the layout stores them --
    raw ids from the ``.pkl`` (OccuFly layout), training ids from ``_1_1.npy`` / ``_1_8.npy``
    (SSCBench layout; 255 = ignore). :meth:`ExportReader.training_ids` maps raw ids.
``invalid``, ``occluded`` (both layouts), ``surface`` (OccuFly layout)
    (X, Y, Z) bool masks.
``depth``
    (h, w) float32 metres at 1/4 resolution, 0 = none (reshaped with the recorded shape).
``depth_full``
    (H, W) float32 (SSCBench layout, when written).
``points``
    (N, 4) float32 velodyne-like points in the camera frame (SSCBench layout, when written).
``K``
    (3, 3) float64 intrinsics of the full image in the COLMAP convention (pixel centres at
    +0.5; the SSCBench ``calib.txt`` stores cx, cy - 0.5 and is converted back).
``pose``
    (4, 4) float64 camera-to-world, scene-local metres.
"""

from __future__ import annotations

import json
import pickle
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from occufly.errors import InputFormatError
from occufly.export.occufly import list_frames, read_calibration, read_splits
from occufly.export.sscbench import read_calib
from occufly.taxonomy import INVALID, Taxonomy, default_taxonomy

LAYOUTS = ("occufly", "sscbench")
_FRAME_ID = re.compile(r"^[0-9]{1,12}$")
_SCENE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

# what an export's .pkl may contain: plain containers, numbers, strings and numpy arrays
_PKL_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"), ("numpy", "dtype"),
}


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles dicts of numpy arrays and nothing else: a .pkl from someone else's dataset
    cannot run code (``pickle.load`` would call any global it names)."""

    def find_class(self, module: str, name: str):
        if (module, name) in _PKL_ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"global {module}.{name} is not allowed in a dataset .pkl")


def load_pkl(path: Path) -> dict:
    """The ``preprocess/<frame>.pkl`` dict, through :class:`_ArrayUnpickler`."""
    try:
        with open(path, "rb") as fh:
            data = _ArrayUnpickler(fh).load()
    except OSError as e:
        raise InputFormatError(f"{path}: cannot read ({e.strerror})") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as e:
        raise InputFormatError(f"{path}: not a dataset .pkl of arrays ({e})") from None
    if not isinstance(data, dict):
        raise InputFormatError(f"{path}: expected a dict, got {type(data).__name__}")
    return data


@dataclass(frozen=True)
class FrameKey:
    scene: str
    altitude: int
    frame_id: str
    sequence: str


def detect_layout(root: Path) -> str:
    root = Path(root)
    if (root / "OccuFly_Dataset").is_dir():
        return "occufly"
    if (root / "manifests").is_dir() and (root / "data_2d_raw").is_dir():
        return "sscbench"
    raise InputFormatError(
        f"{root}: not an export (expected OccuFly_Dataset/ for the OccuFly layout, or "
        "manifests/ and data_2d_raw/ for the SSCBench layout)")


def open_dataset(root: str | Path, *, split: str | None = None, layout: str | None = None) -> ExportReader:
    """A reader of the export at ``root``; ``split`` (train / val / test) keeps the frames of
    that split's scenes / sequences (from the export's splits files)."""
    root = Path(root)
    layout = layout or detect_layout(root)
    if layout == "occufly":
        return OccuFlyReader(root, split=split)
    if layout == "sscbench":
        return SSCBenchReader(root, split=split)
    raise InputFormatError(f"unknown layout {layout!r}; expected one of {', '.join(LAYOUTS)}")


def _unpack(path: Path, n: int, shape: tuple[int, ...]) -> np.ndarray:
    data = np.fromfile(path, dtype=np.uint8)
    if data.size * 8 < n:
        raise InputFormatError(f"{path}: {data.size} bytes, expected {(n + 7) // 8} for grid {shape}")
    return np.unpackbits(data)[:n].reshape(shape).astype(bool)


def read_label_file(path: Path, n: int, shape: tuple[int, ...], dtype: str = "u1") -> np.ndarray:
    """A flat label file of ``n`` ids (uint8, or little-endian uint16 SemanticKITTI-style) as
    an (X, Y, Z) uint8 array; clear errors for a wrong size or ids above 255."""
    try:
        raw = np.fromfile(path, dtype=dtype)
    except OSError as e:
        raise InputFormatError(f"{path}: cannot read ({e.strerror})") from None
    if raw.size != n:
        raise InputFormatError(f"{path}: {raw.size} values, expected {n} for grid {shape}")
    if raw.dtype.itemsize > 1 and raw.max(initial=0) > 255:
        raise InputFormatError(f"{path}: ids above 255 (max {int(raw.max())})")
    return raw.astype(np.uint8, copy=False).reshape(shape)


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputFormatError(f"{path}: not a readable .npy file ({e})") from None


def _image(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except OSError as e:
        raise InputFormatError(f"{path}: cannot read image ({e})") from None


class ExportReader:
    """Common part of the two layouts: manifests, taxonomy, frame list, split filter."""

    layout = ""

    def __init__(self, root: Path, *, split: str | None = None) -> None:
        self.root = Path(root)
        if split is not None and split not in ("train", "val", "test"):
            raise InputFormatError(f"split {split!r}: expected train, val or test")
        self.split = split
        self.manifests: dict[str, dict] = {}
        for sid, mp in self._manifest_paths():
            try:
                self.manifests[sid] = json.loads(mp.read_text())
            except (OSError, ValueError) as e:
                raise InputFormatError(f"{mp}: unreadable manifest ({e})") from None
        if not self.manifests:
            raise InputFormatError(f"{self.root}: no scene manifest found ({self.layout} layout)")
        first = next(iter(self.manifests.values()))
        self.taxonomy: Taxonomy = (Taxonomy.from_dict(first["taxonomy"], source="manifest")
                                   if "taxonomy" in first else default_taxonomy())
        self.grid_shape = tuple(int(v) for v in first.get("grid_spec", {}).get("shape", (192, 128, 128)))
        self.frames: list[FrameKey] = self._list_frames()
        if split is not None:
            keep = set(self.split_members(split))
            # frames split within a scene (``export --split-by``) carry their own split
            self.frames = [k for k in self.frames
                           if (self.frame_record(k).get("split") == split
                               if self.frame_record(k).get("split") else self._split_key(k) in keep)]

    # layout-specific
    def _manifest_paths(self):  # pragma: no cover - abstract
        raise NotImplementedError

    def _list_frames(self) -> list[FrameKey]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _split_key(self, key: FrameKey) -> str:  # pragma: no cover - abstract
        raise NotImplementedError

    def split_members(self, split: str) -> list[str]:  # pragma: no cover - abstract
        raise NotImplementedError

    # shared
    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict:
        if not -len(self.frames) <= i < len(self.frames):
            raise IndexError(f"frame {i} out of range ({len(self.frames)} frames)")
        return self.read(self.frames[i])

    def __iter__(self):
        for k in self.frames:
            yield self.read(k)

    def read(self, key: FrameKey) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError

    def learning_lut(self) -> np.ndarray:
        """(256,) uint8 raw id -> training id (0 empty, 1..C, 255 ignore/unknown)."""
        lut = np.full(256, 255, dtype=np.uint8)
        for k, v in self.taxonomy.learning_map().items():
            lut[k] = v
        return lut

    def training_ids(self, raw: np.ndarray) -> np.ndarray:
        return self.learning_lut()[np.asarray(raw, dtype=np.uint8)]

    def target(self, sample: dict, scale: str = "1_1") -> np.ndarray:
        """(X/f, Y/f, Z/f) uint8 training ids of ``sample`` at ``scale``, 255 = ignore
        (invalid), whatever the layout."""
        if self.layout == "sscbench":
            if scale not in sample["grids"]:
                raise InputFormatError(f"{self.root}: no {scale} labels in the SSCBench layout "
                                       f"(it has {', '.join(sorted(sample['grids']))})")
            return sample["grids"][scale]
        if scale == "1_1":
            t = self.training_ids(sample["label"])
            t[sample["invalid"]] = INVALID
            return t
        if scale not in sample["grids"]:
            raise InputFormatError(f"{self.root}: no {scale} grid in the .pkl")
        return self.training_ids(sample["grids"][scale])

    def frame_record(self, key: FrameKey) -> dict:
        return self.manifests.get(key.scene, {}).get("frames", {}).get(key.frame_id, {})

    def _pose(self, key: FrameKey) -> np.ndarray | None:
        p = self.frame_record(key).get("pose")
        return None if p is None else np.asarray(p, dtype=np.float64).reshape(4, 4)

    def _depth_shape(self, key: FrameKey) -> tuple[int, int] | None:
        s = self.frame_record(key).get("depth_shape") or self.manifests[key.scene].get("depth_map_shape")
        return None if s is None else (int(s[0]), int(s[1]))


class OccuFlyReader(ExportReader):
    layout = "occufly"

    @property
    def ds(self) -> Path:
        return self.root / "OccuFly_Dataset"

    def _manifest_paths(self):
        for mp in sorted(self.ds.glob("*/manifest.json")):
            yield mp.parent.name, mp

    def _list_frames(self) -> list[FrameKey]:
        return [FrameKey(s, a, f, f"{s}_{a}") for s, a, f in list_frames(self.root) if s in self.manifests]

    def _split_key(self, key: FrameKey) -> str:
        return key.scene

    def split_members(self, split: str) -> list[str]:
        return read_splits(self.root)[split]

    def calibration(self, scene: str) -> dict:
        return read_calibration(self.ds / scene / "calibration.txt")

    def read_labels(self, key: FrameKey) -> tuple[np.ndarray, np.ndarray]:
        """(label (X, Y, Z) uint8 raw ids, invalid (X, Y, Z) bool) without the rest."""
        gtd = self.ds / key.scene / str(key.altitude) / "ground_truth" / key.frame_id
        shape = self.grid_shape
        n = int(np.prod(shape))
        lab_path = gtd / f"{key.frame_id}.label"
        label = np.fromfile(lab_path, dtype=np.uint8)
        if label.size != n:
            raise InputFormatError(f"{lab_path}: {label.size} values, expected {n} for grid {shape}")
        return label.reshape(shape), _unpack(gtd / f"{key.frame_id}.invalid", n, shape)

    def read(self, key: FrameKey) -> dict:
        base = self.ds / key.scene / str(key.altitude)
        gtd = base / "ground_truth" / key.frame_id
        shape = self.grid_shape
        n = int(np.prod(shape))
        label, invalid = self.read_labels(key)
        out: dict = {"scene": key.scene, "altitude": key.altitude, "frame_id": key.frame_id,
                     "sequence": key.sequence, "label": label, "invalid": invalid}
        for m in ("occluded", "surface"):
            out[m] = _unpack(gtd / f"{key.frame_id}.{m}", n, shape)
        pkl = load_pkl(base / "preprocess" / f"{key.frame_id}.pkl")
        out["grids"] = {k: np.asarray(v) for k, v in pkl.items() if k.startswith("1_")}
        out["pose"] = np.asarray(pkl["pose"], dtype=np.float64)
        out["image"] = _image(base / "images" / "visual" / f"{key.frame_id}.png")
        cal = self.calibration(key.scene)
        out["K"] = np.array([[cal["fx"], 0.0, cal["cx"]], [0.0, cal["fy"], cal["cy"]], [0.0, 0.0, 1.0]])
        depth = _load_npy(base / "depth_maps" / f"{key.frame_id}.npy")
        dshape = self._depth_shape(key) or cal["depth_shape"]
        if depth.ndim == 1:
            if dshape is None or dshape[0] * dshape[1] != depth.size:
                raise InputFormatError(
                    f"{base / 'depth_maps' / (key.frame_id + '.npy')}: {depth.size} values do not fit the "
                    f"recorded depth shape {dshape}")
            depth = depth.reshape(dshape)
        out["depth"] = depth.astype(np.float32, copy=False)
        return out


class SSCBenchReader(ExportReader):
    layout = "sscbench"

    def _manifest_paths(self):
        for mp in sorted((self.root / "manifests").glob("*.json")):
            yield mp.stem, mp

    def _list_frames(self) -> list[FrameKey]:
        keys = []
        for sid, m in self.manifests.items():
            for fid, fr in sorted(m.get("frames", {}).items()):
                try:
                    alt = int(fr["altitude"])
                except (KeyError, TypeError, ValueError):
                    raise InputFormatError(f"{self.root}/manifests/{sid}.json: frame {fid!r} has no "
                                           "integer altitude") from None
                if not _FRAME_ID.match(str(fid)) or not _SCENE_ID.match(sid) or not 0 <= alt < 100_000:
                    raise InputFormatError(f"{self.root}/manifests/{sid}.json: frame id {fid!r} / "
                                           f"altitude {alt} is not a valid export name")
                seq = f"{sid}_{alt}"
                if (self.root / "data_2d_raw" / seq / "voxels" / f"{fid}.bin").is_file():
                    keys.append(FrameKey(sid, alt, fid, seq))
        return sorted(keys, key=lambda k: (k.sequence, k.frame_id))

    def _split_key(self, key: FrameKey) -> str:
        return key.sequence

    def split_members(self, split: str) -> list[str]:
        p = self.root / "splits" / f"{split}.txt"
        return [ln.strip() for ln in p.read_text().splitlines() if ln.strip()] if p.is_file() else []

    def yaml(self) -> dict:
        return yaml.safe_load((self.root / "occufly.yaml").read_text())

    def read_labels(self, key: FrameKey) -> tuple[np.ndarray, np.ndarray]:
        """(label (X, Y, Z) uint8 raw ids, invalid (X, Y, Z) bool) without the rest."""
        vox = self.root / "data_2d_raw" / key.sequence / "voxels"
        shape = self.grid_shape
        n = int(np.prod(shape))
        raw = read_label_file(vox / f"{key.frame_id}.label", n, shape, dtype="<u2")
        return raw, _unpack(vox / f"{key.frame_id}.invalid", n, shape)

    def read(self, key: FrameKey) -> dict:
        seq_dir = self.root / "data_2d_raw" / key.sequence
        vox = seq_dir / "voxels"
        shape = self.grid_shape
        n = int(np.prod(shape))
        fid = key.frame_id
        label, invalid = self.read_labels(key)
        out: dict = {"scene": key.scene, "altitude": key.altitude, "frame_id": fid,
                     "sequence": key.sequence, "label": label, "invalid": invalid}
        out["occluded"] = _unpack(vox / f"{fid}.occluded", n, shape)
        out["occupied_visible"] = _unpack(vox / f"{fid}.bin", n, shape)
        labels = self.root / "preprocess" / "labels" / key.sequence
        out["grids"] = {}
        for scale in ("1_1", "1_2", "1_4", "1_8", "1_16"):
            p = labels / f"{fid}_{scale}.npy"
            if p.is_file():
                out["grids"][scale] = _load_npy(p)
        out["image"] = _image(seq_dir / "image_00" / "data_rect" / f"{fid}.png")
        cal = read_calib(seq_dir / "calib.txt")
        K = cal["P2"][:3, :3].astype(np.float64).copy()
        K[0, 2] += 0.5
        K[1, 2] += 0.5
        out["K"] = K
        out["P2"] = cal["P2"]
        out["Tr"] = cal["Tr"]
        pose = self._pose(key)
        if pose is not None:
            out["pose"] = pose
        out["depth"] = _load_npy(self.root / "depth" / key.sequence / f"{fid}.npy").astype(np.float32, copy=False)
        full = self.root / "depth_full" / key.sequence / f"{fid}.npy"
        if full.is_file():
            out["depth_full"] = _load_npy(full).astype(np.float32, copy=False)
        pts = seq_dir / "velodyne_points" / "data" / f"{fid}.bin"
        if pts.is_file():
            p = np.fromfile(pts, dtype="<f4")
            if p.size % 4:
                raise InputFormatError(f"{pts}: {p.size} floats, not a multiple of 4 (N x 4)")
            out["points"] = p.reshape(-1, 4)
        return out
