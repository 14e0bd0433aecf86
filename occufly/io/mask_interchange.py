"""Masks in and out of the field's 2D annotation tools: CVAT, COCO, Label Studio, plain PNGs.

Formats (``FORMATS``):

- ``cvat``: a CVAT export, either *CVAT for images 1.1* (``annotations.xml``: polygons and RLE
  masks) or *Segmentation mask 1.1* (``labelmap.txt`` + ``SegmentationClass/*.png``); which one
  is told by the files. ``cvat_images`` / ``cvat_mask`` name one of them (export writes
  ``cvat_images`` for ``cvat``).
- ``coco``: COCO instances (``annotations/instances_*.json``: polygons or RLE).
- ``coco_panoptic``: COCO panoptic (``annotations/panoptic_*.json`` + segment PNGs).
- ``labelstudio``: a Label Studio JSON export (brush RLE and polygon results).
- ``png``: plain single-channel (indexed) or colour PNGs named after the frames, with a class
  map beside them (``labelmap.txt`` as CVAT/VOC write it, Datumaro's ``dataset_meta.json``, or
  ``classes.json`` {pixel value or "#rrggbb": class name}); without one the values are the
  taxonomy's raw ids (or its colours), as the annotator stores them.

The parsing is the format libraries': Datumaro (the format framework CVAT itself uses) reads
and writes CVAT, VOC-style segmentation masks and COCO (its COCO masks go through
pycocotools); polygons are rasterised by pycocotools; Label Studio's brush RLE is decoded and
encoded by HumanSignal's ``label_studio_converter.brush``. They are heavy optional imports,
made inside the functions that need them (the ``masks`` extra of pyproject.toml).

Class names are mapped to the scene taxonomy by name (case, spaces and hyphens do not matter),
through an optional mapping {external name: taxonomy name | id | "ignore" | "unpainted"}; the
names ``background`` / ``_background_`` map to unpainted (0) and ``ignore`` / ``void`` to ignore
(255) unless the mapping says otherwise. Everything is checked before anything is returned:
unknown classes, images that name no frame and masks of the wrong size are one
:class:`MaskImportError` listing them all, so a caller stores nothing.
"""

from __future__ import annotations

import json
import re
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np
from PIL import Image

from occufly import safe_yaml
from occufly.errors import MaskError
from occufly.io.masks import MAX_MASK_PIXELS, decode_mask_png, encode_mask_png, mask_scale
from occufly.safe_yaml import short
from occufly.scene import Frame
from occufly.taxonomy import EMPTY, INVALID, Taxonomy

FORMATS = ("cvat", "cvat_images", "cvat_mask", "coco", "coco_panoptic", "labelstudio", "png")
#: the tool a format comes from, for a version's ``source`` ("imported from CVAT")
TOOL_NAMES = {"cvat": "CVAT", "cvat_images": "CVAT", "cvat_mask": "CVAT", "coco": "COCO",
              "coco_panoptic": "COCO panoptic", "labelstudio": "Label Studio", "png": "PNG"}
#: Datumaro's format name for the formats it reads and writes
_DATUMARO = {"cvat_images": "cvat", "cvat_mask": "voc_segmentation", "coco": "coco_instances",
             "coco_panoptic": "coco_panoptic"}
#: class names that mean "no class" without a mapping entry
_DEFAULT_SPECIAL = {"background": EMPTY, "_background_": EMPTY, "unpainted": EMPTY, "ignore": INVALID,
                    "void": INVALID}
_SPECIAL_TARGETS = {"ignore": INVALID, "unpainted": EMPTY, "background": EMPTY}
#: Label Studio brush strokes are RGBA; a pixel belongs to the stroke from this alpha on
BRUSH_ALPHA = 128
LS_FROM_NAME, LS_TO_NAME = "tag", "image"  # the names in the labeling config we write


class MaskImportError(MaskError):
    """An archive that cannot be imported; ``problems`` lists every reason."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.problems = problems
        shown = problems[:30]
        more = f"; ... and {len(problems) - 30} more" if len(problems) > 30 else ""
        super().__init__(f"{source}: nothing imported: " + "; ".join(shown) + more)


@dataclass
class _Shape:
    label: str
    z: int = 0
    mask: Callable[[], np.ndarray] | np.ndarray | None = None  # (h, w) bool, or a loader
    polygon: list[float] | None = None  # x0, y0, x1, y1, ... in pixels
    size: tuple[int, int] | None = None  # (h, w) the mask declares, checked before decoding


@dataclass
class _Item:
    name: str
    size: tuple[int, int] | None  # (h, w)
    shapes: list[_Shape] = field(default_factory=list)
    raw: Callable[[], np.ndarray] | None = None  # png without a class map: raw ids loader


@dataclass
class ImportedMasks:
    """What :func:`read_masks` found: raw-id masks by frame index, all checked."""

    fmt: str
    masks: dict[int, np.ndarray]
    item_names: dict[int, str]
    classes: dict[str, int]  # external class name -> raw id used
    skipped_empty: list[str]  # items with no annotation (not imported)

    @property
    def tool(self) -> str:
        return TOOL_NAMES[self.fmt]


# ---- archives -------------------------------------------------------------------------------
MAX_ARCHIVE_BYTES = 8 << 30  # uncompressed; a zip claiming more is refused before extracting
#: entries of a zip, read from its end record before its directory is parsed (issue 36 attack
#: pass: 199,000 empty members in a 19 MB zip took +218 MB and 28 s of CPU at 200,000)
MAX_ARCHIVE_MEMBERS = 50_000
#: what one zip may unpack to (what the format needs of it): this many times its own size,
#: and never less than INFLATE_FLOOR (issue 36: a 2 MB zip wrote 2.2 GiB)
INFLATE_FACTOR = 20
INFLATE_FLOOR = 64 << 20
#: an annotation file (JSON / XML / text) is parsed whole by the formats' readers (json,
#: Datumaro's iterparse): its size and its count of values bound what parsing it allocates
#: (issue 36: 1 MB of zipped whitespace JSON took +2 GB). 16 MB of the densest JSON (floats)
#: parses to < 200 MB.
MAX_TEXT_MEMBER_BYTES = 16 << 20
MAX_TEXT_NODES = 1_000_000  # JSON strings + objects + arrays; XML tags
MAX_JSON_VALUES = 3_000_000  # JSON values (commas): 3 M floats parse to ~100 MB
#: the files each format reads, by suffix: nothing else of an archive is unpacked (the images
#: a CVAT or COCO export may carry are never read)
_NEEDS = {"cvat": (".xml", ".txt", ".png"), "cvat_images": (".xml",),
          "cvat_mask": (".txt", ".png"), "coco": (".json",), "coco_panoptic": (".json", ".png"),
          "labelstudio": (".json",), "png": (".png", ".txt", ".json", ".yaml", ".yml")}
_TEXT = (".json", ".xml", ".txt", ".yaml", ".yml")
_CHUNK = 1 << 20


def _text_nodes(suffix: str, chunk: bytes) -> int:
    if suffix == ".xml":
        return chunk.count(b"<")
    if suffix == ".json":
        return chunk.count(b'"') // 2 + chunk.count(b"{") + chunk.count(b"[")
    return chunk.count(b"\n")


def _json_values(suffix: str, chunk: bytes) -> int:
    return chunk.count(b",") if suffix == ".json" else 0


def _member_path(src: Path, name: str) -> PurePosixPath:
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or ".." in p.parts or (p.parts and ":" in p.parts[0]) or "\x00" in name:
        raise MaskError(f"{src.name}: archive member {short(name)} points outside the "
                        f"archive; expected relative paths")
    return p


def _check_member(src_name: str, name: str, suffix: str, head: bytes, written: int,
                  nodes: int, max_side: tuple[int, int] | None) -> None:
    """Refuse a member while it is unpacked: a text file over its caps, a PNG whose header
    is not a PNG's or is larger than every frame (checked on its first bytes)."""
    if suffix in _TEXT and written > MAX_TEXT_MEMBER_BYTES:
        raise MaskError(f"{src_name}: archive member {short(name)} is larger than the "
                        f"{MAX_TEXT_MEMBER_BYTES >> 20} MB an annotation file may be")
    if suffix in _TEXT and nodes > MAX_TEXT_NODES:
        raise MaskError(f"{src_name}: archive member {short(name)} holds more values than an "
                        f"annotation file may ({MAX_TEXT_NODES} strings, objects, arrays or XML "
                        f"tags; {MAX_JSON_VALUES} JSON values)")
    if suffix == ".png" and len(head) >= 24 and max_side is not None:
        if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
            raise MaskError(f"{src_name}: archive member {short(name)} is not a PNG file (no PNG "
                            f"signature and IHDR header)")
        w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        if h > max_side[0] or w > max_side[1]:
            raise MaskError(f"{src_name}: archive member {short(name)} declares {w}x{h} pixels, "
                            f"larger than any frame of the scene ({max_side[1]}x{max_side[0]})")


def _extract(src: Path, dest: Path, fmt: str = "png", *,
             max_side: tuple[int, int] | None = None) -> Path:
    """``src`` (a folder, a zip, or one annotation file) laid out under ``dest``; the folder.

    Of a zip only the members ``fmt`` reads are unpacked (:data:`_NEEDS`), streamed and
    counted as they are written: at most :data:`INFLATE_FACTOR` times the zip's size in all
    (and the free space of ``dest`` is checked first), annotation files within their caps,
    PNGs with a PNG header no larger than ``max_side`` (h, w; the largest frame)."""
    if src.is_dir():  # linked into ``dest``, so that missing folders can be added there
        for p in src.iterdir():
            (dest / p.name).symlink_to(p.resolve(), target_is_directory=p.is_dir())
        return dest
    if not src.is_file():
        raise MaskError(f"{src}: no such archive, folder or file")
    if not zipfile.is_zipfile(src):
        if src.suffix.lower() in _TEXT and src.stat().st_size > MAX_TEXT_MEMBER_BYTES:
            raise MaskError(f"{src.name}: larger than the {MAX_TEXT_MEMBER_BYTES >> 20} MB an "
                            f"annotation file may be")
        shutil.copy(src, dest / src.name)
        return dest
    try:
        with open(src, "rb") as fh:
            end = zipfile._EndRecData(fh)  # noqa: SLF001 - the entry count, before the directory
        if end is not None and end[zipfile._ECD_ENTRIES_TOTAL] > MAX_ARCHIVE_MEMBERS:  # noqa: SLF001
            raise MaskError(f"{src.name}: {end[zipfile._ECD_ENTRIES_TOTAL]} files in the "  # noqa: SLF001
                            f"archive, more than the {MAX_ARCHIVE_MEMBERS} accepted")
        zf = zipfile.ZipFile(src)
    except (zipfile.BadZipFile, OSError) as e:
        raise MaskError(f"{src.name}: damaged zip archive ({e})") from None
    needs = _NEEDS[fmt]
    budget = max(INFLATE_FLOOR, INFLATE_FACTOR * src.stat().st_size)
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_ARCHIVE_MEMBERS:
            raise MaskError(f"{src.name}: {len(infos)} files in the archive, more than the "
                            f"{MAX_ARCHIVE_MEMBERS} accepted")
        plan = []
        for info in infos:
            p = _member_path(src, info.filename)
            if (info.external_attr >> 16) & 0o170000 == 0o120000:
                raise MaskError(f"{src.name}: archive member {short(info.filename)} is a "
                                f"symbolic link")
            if info.is_dir() or p.suffix.lower() not in needs or "__MACOSX" in p.parts:
                continue
            plan.append((info, p))
        total = sum(i.file_size for i, _ in plan)
        if total > min(budget, MAX_ARCHIVE_BYTES):
            raise MaskError(f"{src.name}: the archive's {fmt} files unpack to {total} bytes, more "
                            f"than the {min(budget, MAX_ARCHIVE_BYTES)} accepted for a "
                            f"{src.stat().st_size}-byte archive ({INFLATE_FACTOR} times its size, "
                            f"at least {INFLATE_FLOOR >> 20} MB)")
        free = shutil.disk_usage(dest).free
        if total + (64 << 20) > free:
            raise InsufficientSpace(f"{src.name}: unpacking it needs {total} bytes; the server's "
                                    f"temporary folder has {free} free")
        written = 0
        for info, p in plan:
            target = dest.joinpath(*p.parts)
            suffix = p.suffix.lower()
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                n = nodes = values = 0
                head = b""
                with zf.open(info) as fin, open(target, "xb") as out:
                    while chunk := fin.read(_CHUNK):
                        n += len(chunk)
                        written += len(chunk)
                        if len(head) < 24:
                            head += chunk[:24]
                        if suffix in _TEXT:
                            nodes += _text_nodes(suffix, chunk)
                            values += _json_values(suffix, chunk)
                        if n > info.file_size or written > budget:
                            raise MaskError(f"{src.name}: archive member {short(info.filename)} "
                                            f"unpacks to more than it declares")
                        _check_member(src.name, info.filename, suffix, head, n,
                                      max(nodes, values * MAX_TEXT_NODES // MAX_JSON_VALUES),
                                      max_side)
                        out.write(chunk)
            except (FileExistsError, IsADirectoryError, NotADirectoryError):
                raise MaskError(f"{src.name}: archive member {short(info.filename)} clashes with "
                                f"another (the same name twice, or a file and a folder)") from None
            except (zipfile.BadZipFile, OSError, RuntimeError, EOFError) as e:
                raise MaskError(f"{src.name}: damaged zip archive ({e})") from None
    # a zip of one folder (CVAT's task_x_dataset.zip is flat; a zipped folder is not)
    entries = [p for p in dest.iterdir() if not p.name.startswith((".", "__MACOSX"))]
    if len(entries) == 1 and entries[0].is_dir() and entries[0].name not in _LAYOUT_DIRS:
        return entries[0]
    return dest


class InsufficientSpace(MaskError):
    """Not enough free space to unpack an archive (HTTP 507)."""


#: folder names of the formats' own layouts (a zip holding only one of them is not a zipped
#: folder of an export)
_LAYOUT_DIRS = {"annotations", "images", "SegmentationClass", "SegmentationObject", "ImageSets",
                "JPEGImages", "masks"}


def _files(root: Path, pattern: str) -> list[Path]:
    return sorted(p for p in root.rglob(pattern) if p.is_file() and "__MACOSX" not in p.parts)


# ---- class names ----------------------------------------------------------------------------
def _norm(name: str) -> str:
    return re.sub(r"[\s\-]+", "_", str(name).strip().lower())


def load_class_map(path: str | Path) -> dict[str, int]:
    """A mapping file {external class name: taxonomy name | id | "ignore" | "unpainted" |
    null} (JSON or YAML) as {external name: target}; targets are checked by
    :func:`resolve_classes`."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise MaskError(f"{path}: cannot read class mapping ({e.strerror})") from None
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            data = safe_yaml.load(text)  # no aliases: a 458-byte alias bomb took 2.3 GB
        else:
            data = json.loads(text)
    except Exception as e:  # noqa: BLE001 - parser errors differ per format
        raise MaskError(f"{path.name}: class mapping is not valid "
                        f"{'YAML' if path.suffix.lower() in ('.yaml', '.yml') else 'JSON'}: "
                        f"{str(e)[:300]}") from None
    if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
        raise MaskError(f"{path.name}: expected a mapping {{external class name: taxonomy class "
                        f"name, id, \"ignore\" or \"unpainted\"}}")
    bad = [k for k, v in data.items() if not (v is None or isinstance(v, (str, int, float)))]
    if bad:
        raise MaskError(f"{path.name}: the target of {safe_yaml.short(bad[0])} is a "
                        f"{type(data[bad[0]]).__name__}; expected a taxonomy class name, id, "
                        f"\"ignore\" or \"unpainted\"" + (f" ({len(bad)} such entries)"
                                                          if len(bad) > 1 else ""))
    return data


def resolve_classes(names: Sequence[str], taxonomy: Taxonomy, class_map: dict | None = None,
                    *, source: str = "<mapping>") -> tuple[dict[str, int], list[str]]:
    """{external name: raw id} for ``names`` and the list of problems (unknown classes, bad
    mapping targets), each naming what was expected."""
    by_norm = {_norm(c.name): c.id for c in taxonomy.classes}
    cmap = {_norm(k): v for k, v in (class_map or {}).items()}
    out: dict[str, int] = {}
    problems: list[str] = []
    unknown: list[str] = []
    for name in names:
        key = _norm(name)
        if key in cmap:
            target = cmap[key]
            if target is None:
                out[name] = EMPTY
            elif isinstance(target, bool):
                problems.append(f"mapping {short(name)} -> {short(target)} is not a class")
            elif isinstance(target, int):
                if target in taxonomy or target in (EMPTY, INVALID):
                    out[name] = int(target)
                else:
                    problems.append(f"mapping {short(name)} -> id {short(target)} is not a class id of "
                                    f"taxonomy {taxonomy.name!r}")
            elif isinstance(target, str) and _norm(target) in by_norm:
                out[name] = by_norm[_norm(target)]
            elif isinstance(target, str) and _norm(target) in _SPECIAL_TARGETS:
                out[name] = _SPECIAL_TARGETS[_norm(target)]
            else:
                problems.append(f"mapping {short(name)} -> {short(target)} names no class of taxonomy "
                                f"{taxonomy.name!r}")
        elif key in by_norm:
            out[name] = by_norm[key]
        elif key in _DEFAULT_SPECIAL:
            out[name] = _DEFAULT_SPECIAL[key]
        else:
            unknown.append(name)
    if unknown:
        shown = ", ".join(short(u) for u in sorted(unknown)[:50]) + (
            f" ... ({len(unknown)} in all)" if len(unknown) > 50 else "")
        problems.insert(0, f"unknown class(es) {shown}: "
                           f"not in taxonomy {taxonomy.name!r} and not in the class mapping "
                           f"(taxonomy classes: {', '.join(c.name for c in taxonomy.classes)})")
    return out, problems


# ---- frame names ----------------------------------------------------------------------------
_LS_UPLOAD_PREFIX = re.compile(r"^[0-9a-f]{8}-")  # Label Studio prefixes uploaded files


def _frame_lookup(frames: Sequence[Frame]) -> dict[str, int]:
    look: dict[str, int] = {}
    for i, f in enumerate(frames):
        for key in (f.name, Path(f.name).name, f.stem):
            look.setdefault(key.lower(), i)
    return look


def match_frame(name: str, look: dict[str, int]) -> int | None:
    """The frame index an archive's image name denotes (its path, file name or stem), or None."""
    s = str(name).replace("\\", "/")
    s = s.split("?d=")[-1]  # Label Studio local-files URLs
    base = PurePosixPath(s).name
    cands = [s, base, PurePosixPath(base).stem]
    stripped = _LS_UPLOAD_PREFIX.sub("", base)
    if stripped != base:
        cands += [stripped, PurePosixPath(stripped).stem]
    for c in cands:
        if c.lower() in look:
            return look[c.lower()]
    return None


# ---- readers --------------------------------------------------------------------------------
def _datumaro_items(dataset) -> tuple[list[_Item], list[str]]:  # noqa: ANN001
    from datumaro.components.annotation import AnnotationType

    labels = dataset.categories().get(AnnotationType.label)
    names = [c.name for c in labels] if labels is not None else []
    items: list[_Item] = []
    try:
        loaded = list(dataset)
    except Exception as e:  # noqa: BLE001 - Datumaro's item errors are its own classes
        raise MaskError(f"cannot read the archive: {e}") from None
    for it in loaded:
        size = None
        if it.media is not None:
            try:
                size = it.media.size
            except Exception:  # noqa: BLE001 - an image file that is not there has no size
                size = None
        shapes: list[_Shape] = []
        for ann in it.annotations:
            if ann.type not in (AnnotationType.mask, AnnotationType.polygon):
                continue  # boxes, points, tags: not masks
            if ann.label is None or not 0 <= ann.label < len(names):
                label = f"<label {ann.label}>"
            else:
                label = names[ann.label]
            z = int(getattr(ann, "z_order", 0) or 0)
            if ann.type == AnnotationType.mask:
                rle = getattr(ann, "rle", None)  # COCO RLE: {"size": [h, w], "counts": ...}
                declared = None
                if isinstance(rle, dict) and isinstance(rle.get("size"), (list, tuple)):
                    try:
                        declared = tuple(int(v) for v in rle["size"][:2])
                    except (TypeError, ValueError):
                        declared = (-1, -1)
                shapes.append(_Shape(label, z, size=declared,
                                     mask=(lambda a=ann: np.asarray(a.image, bool))))
            else:
                shapes.append(_Shape(label, z, polygon=[float(v) for v in ann.points]))
        items.append(_Item(it.id, tuple(int(v) for v in size) if size else None, shapes))
    return items, names


def _read_cvat_images(root: Path) -> list[_Item]:
    """CVAT for images 1.1 XML through Datumaro's CVAT parser; CVAT's annotation-only export
    has no images, which Datumaro's item loader insists on, so the images' sizes come from
    the XML (``<image width height>``) instead."""
    from datumaro.components.dataset_base import DatasetItem  # heavy optional dependency
    from datumaro.components.media import Image
    from datumaro.plugins.data_formats.cvat.base import CvatBase, CvatImporter

    class _AnnotationsOnly(CvatBase):
        @classmethod
        def _parse_shape_ann(cls, ann, categories, image):  # noqa: ANN001, ANN206 - Datumaro's
            if ann.get("type") == "mask":  # its sizes checked before anything is allocated
                _check_cvat_mask(ann, image)
            return super()._parse_shape_ann(ann, categories, image)

        def _load_items(self, parsed):  # noqa: ANN001, ANN202 - Datumaro's hook
            out = {}
            for frame_id, desc in parsed.items():
                name = desc.get("name", f"frame_{int(frame_id):06d}.png")
                size = (desc.get("height"), desc.get("width"))
                media = Image.from_file(path=str(Path(self._images_dir or ".") / name),
                                        size=tuple(map(int, size)) if all(size) else None)
                out[frame_id] = DatasetItem(id=str(PurePosixPath(name).with_suffix("")),
                                            subset=self._subset, media=media,
                                            annotations=desc.get("annotations"))
            return out

    from datumaro.components.dataset import Dataset

    try:
        sources = CvatImporter.find_sources(str(root))
    except Exception as e:  # noqa: BLE001 - Datumaro's errors are its own classes
        raise MaskError(f"{root}: not a CVAT for images 1.1 export ({e})") from None
    if not sources:
        raise MaskError(f"{root}: no CVAT XML (annotations.xml) found; expected a CVAT for "
                        f"images 1.1 export")
    items: list[_Item] = []
    for src in sources:
        try:
            base = _AnnotationsOnly(src["url"], **(src.get("options") or {}))
        except MaskError:
            raise
        except Exception as e:  # noqa: BLE001
            raise MaskError(f"{src['url']}: not a CVAT for images 1.1 XML ({e})") from None
        got, _ = _datumaro_items(Dataset.from_extractors(base))
        items += got
    return items


def _check_cvat_mask(ann: dict, image: dict | None) -> None:
    """A CVAT ``<mask rle left top width height>`` must lie inside its ``<image width
    height>`` (which is checked against the frame before painting) and hold at most one run
    per pixel: Datumaro allocates both the mask and the image canvas from these numbers."""
    where = f"image {short((image or {}).get('name'))}: a {short(ann.get('label'))} <mask>"
    try:
        left, top, w, h = (int(ann.get(k)) for k in ("left", "top", "width", "height"))
        img_w, img_h = int((image or {}).get("width")), int((image or {}).get("height"))
    except (TypeError, ValueError):
        raise MaskError(f"{where} (or its <image>) without integer left/top/width/height; "
                        f"expected a mask inside a sized <image>") from None
    if img_w <= 0 or img_h <= 0 or img_w * img_h > MAX_MASK_PIXELS:
        raise MaskError(f"{where}: its image declares {img_w}x{img_h} pixels; expected at most "
                        f"{MAX_MASK_PIXELS}")
    if w <= 0 or h <= 0 or left < 0 or top < 0 or left + w > img_w or top + h > img_h:
        raise MaskError(f"{where} declares {w}x{h} pixels at ({left}, {top}), outside its "
                        f"{img_w}x{img_h} image")
    if str(ann.get("rle") or "").count(",") + 1 > w * h:
        raise MaskError(f"{where} holds more runs than its {w}x{h} pixels")


def _datumaro_image_backend() -> None:
    """Datumaro picks its image codec (cv2 or PIL) in a ContextVar set once, when it is first
    imported, in that thread's context: a server's other worker threads (a request runs in a
    copy of the event loop's context) found it unset and every image read failed with
    ``LookupError: <ContextVar name='IMAGE_BACKEND'>`` (Segmentation mask imports, on a real
    server). Set here, in the caller's context, when missing."""
    from datumaro.util import image as dm_image  # heavy optional dependency

    try:
        dm_image.IMAGE_BACKEND.get()
    except LookupError:
        dm_image.IMAGE_BACKEND.set(dm_image.ImageBackend.cv2 if hasattr(dm_image, "cv2")
                                   else dm_image.ImageBackend.PIL)


def _read_datumaro(root: Path, fmt: str) -> list[_Item]:
    from datumaro.components.dataset import Dataset  # heavy optional dependency

    if fmt in ("coco", "coco_panoptic") and not (root / "images").exists():
        (root / "images").mkdir()  # Datumaro's COCO reader wants it; exports carry no images
    try:
        ds = Dataset.import_from(str(root), _DATUMARO[fmt])
    except Exception as e:  # noqa: BLE001 - Datumaro's errors are its own classes
        cause = e.__cause__ or e
        raise MaskError(f"{root}: not a {TOOL_NAMES[fmt]} {_FORMAT_TITLES[fmt]} export "
                        f"({cause})") from None
    items, _ = _datumaro_items(ds)
    return items


_FORMAT_TITLES = {"cvat_mask": "Segmentation mask 1.1", "coco": "instances",
                  "coco_panoptic": "panoptic", "cvat_images": "for images 1.1"}


def _read_labelstudio(root: Path) -> list[_Item]:
    """Every task of the Label Studio JSON exports under ``root``, read one task at a time
    (ijson): what is kept of a task is compact (a brush RLE as bytes), so memory is bounded by
    one task and the compact tasks, not by the parsed file (issue 36)."""
    files = [p for p in _files(root, "*.json") if p.name != "dataset_meta.json"]
    if not files:
        raise MaskError(f"{root}: no Label Studio JSON export (*.json) found")
    items: list[_Item] = []
    for path in files:
        items.extend(_ls_file_items(path))
    return items


def _ls_file_items(path: Path) -> Iterator[_Item]:
    import ijson  # the masks extra; streams the list of tasks

    not_tasks = f"{path}: expected a Label Studio JSON export (a list of tasks)"
    try:
        with open(path, "rb") as fh:
            head = fh.read(64).lstrip()[:1]
            fh.seek(0)
            if head == b"{":  # one task (the member is at most MAX_TEXT_MEMBER_BYTES)
                task = json.load(fh)
                yield _ls_task(task, f"{path.name}: task {task.get('id', 0)}")
                return
            if head != b"[":
                raise MaskError(not_tasks)
            for ti, task in enumerate(ijson.items(fh, "item", use_float=True)):
                if not isinstance(task, dict):
                    raise MaskError(not_tasks)
                yield _ls_task(task, f"{path.name}: task {task.get('id', ti)}")
    except (OSError, ValueError, ijson.JSONError) as e:
        raise MaskError(f"{path}: not a Label Studio JSON export ({e})") from None


def _compact_rle(rle: list, where: str) -> np.ndarray:
    """A brush RLE (a list of byte values) as uint8: one byte a value instead of a list."""
    try:
        arr = np.asarray(rle, dtype=np.int64)
    except (TypeError, ValueError, OverflowError):
        raise MaskError(f"{where}: damaged brush RLE (values must be bytes 0..255)") from None
    if arr.ndim != 1 or (arr.size and (arr.min() < 0 or arr.max() > 255)):
        raise MaskError(f"{where}: damaged brush RLE (values must be bytes 0..255)")
    return arr.astype(np.uint8)


def _ls_task(task: dict, where: str) -> _Item:
    data = task.get("data") or {}
    image = data.get("image") or next((v for v in data.values() if isinstance(v, str)), None)
    if not image:
        raise MaskError(f"{where}: no image in the task's data")
    anns = [a for a in task.get("annotations") or [] if not a.get("was_cancelled")]
    if not anns:
        return _Item(str(image), None, [])
    ann = max(anns, key=lambda a: (str(a.get("updated_at") or a.get("created_at") or ""),
                                   a.get("id") or 0))
    shapes: list[_Shape] = []
    size = None
    for r in ann.get("result") or []:
        kind = r.get("type")
        v = r.get("value") or {}
        if kind not in ("brushlabels", "polygonlabels"):
            continue
        try:
            w, h = int(r["original_width"]), int(r["original_height"])
        except (KeyError, TypeError, ValueError):
            raise MaskError(f"{where}: a {kind} result without original_width/height") from None
        size = (h, w)
        names = v.get(kind) or []
        if not names:
            raise MaskError(f"{where}: a {kind} result without a label")
        if kind == "brushlabels":
            if v.get("format", "rle") != "rle" or not isinstance(v.get("rle"), list):
                raise MaskError(f"{where}: brush result not in Label Studio's RLE format")
            compact = _compact_rle(v["rle"], where)
            shapes.append(_Shape(names[0], size=(h, w),
                                 mask=lambda rle=compact, h=h, w=w: _ls_brush(rle, h, w, where)))
        else:
            pts = np.asarray(v.get("points") or [], float).reshape(-1, 2)
            pts = pts * np.array([w / 100.0, h / 100.0])  # Label Studio: percent of the image
            shapes.append(_Shape(names[0], polygon=pts.ravel().tolist()))
    return _Item(str(image), size, shapes)


def _brush_decoder() -> Callable[[list[int]], np.ndarray]:
    """Label Studio's brush RLE decoder: the Rust port (label-studio-brush-rle-rs, ~40x faster:
    a 12 MP stroke in 0.13 s instead of 5.3 s) when installed, else HumanSignal's own
    ``label_studio_converter.brush.decode_rle`` (the reference; both decode the same bytes to
    the same values, tests/test_mask_interchange.py)."""
    try:
        from label_studio_brush_rle_rs import decode_rle as rs_decode  # optional, compiled
    except ImportError:
        from label_studio_converter.brush import decode_rle  # heavy optional dependency

        return lambda rle: np.asarray(decode_rle([int(v) for v in rle]), np.uint8)
    return lambda rle: np.asarray(rs_decode([int(v) for v in rle], False), np.uint8)


def _ls_brush(rle: np.ndarray, h: int, w: int, where: str) -> np.ndarray:
    # the stream's first 32 bits count its values: checked before anything is allocated
    num = int.from_bytes(bytes(int(v) & 255 for v in rle[:4]), "big") if len(rle) >= 4 else -1
    if num != h * w * 4 or h * w > MAX_MASK_PIXELS:
        raise MaskError(f"{where}: brush RLE declares {num} values, expected {h}x{w}x4 "
                        f"(original_width x original_height RGBA, at most {MAX_MASK_PIXELS} "
                        f"pixels)")
    try:
        flat = _brush_decoder()(rle)
    except (ValueError, IndexError, OverflowError, TypeError) as e:
        raise MaskError(f"{where}: damaged brush RLE ({e})") from None
    if flat.size != h * w * 4:
        raise MaskError(f"{where}: brush RLE holds {flat.size} values, expected {h}x{w}x4 "
                        f"(original_width x original_height RGBA)")
    return flat.reshape(h, w, 4)[..., 3] >= BRUSH_ALPHA


def _read_class_map_png(root: Path) -> tuple[dict, str] | None:
    """{pixel value (int) or (r, g, b): class name} from the class map beside the PNGs."""
    lm = _files(root, "labelmap.txt")
    if lm:
        from datumaro.plugins.data_formats.voc.format import parse_label_map  # heavy optional

        try:
            labels = parse_label_map(str(lm[0]))
        except Exception as e:  # noqa: BLE001
            raise MaskError(f"{lm[0]}: not a labelmap.txt (name:r,g,b:: per line) ({e})") from None
        return {tuple(int(c) for c in v[0]): k for k, v in labels.items() if v[0]}, str(lm[0])
    meta = _files(root, "dataset_meta.json")
    if meta:
        from datumaro.util.meta_file_util import parse_meta_file  # heavy optional dependency

        try:
            labels = parse_meta_file(str(meta[0].parent))
        except Exception as e:  # noqa: BLE001
            raise MaskError(f"{meta[0]}: not a Datumaro dataset_meta.json ({e})") from None
        out: dict = {}
        for i, (k, v) in enumerate(labels.items()):
            out[tuple(int(c) for c in v[0]) if v and v[0] else i] = k
        return out, str(meta[0])
    for name in ("classes.json", "classmap.json", "classes.yaml", "classmap.yaml"):
        found = _files(root, name)
        if found:
            raw = load_class_map(found[0])
            out = {}
            for k, v in raw.items():
                ks = k.strip()
                if re.fullmatch(r"\d+", ks):
                    out[int(ks)] = v
                elif re.fullmatch(r"#[0-9a-fA-F]{6}", ks):
                    out[tuple(int(ks[i:i + 2], 16) for i in (1, 3, 5))] = v
                elif re.fullmatch(r"\d+\s*,\s*\d+\s*,\s*\d+", ks):
                    out[tuple(int(c) for c in ks.split(","))] = v
                else:
                    raise MaskError(f"{found[0]}: key {short(k)} is neither a pixel value (0..255) "
                                    f"nor a colour (#rrggbb or r,g,b)")
            return out, str(found[0])
    return None


def _png_header_size(p: Path) -> tuple[int, int]:
    """(h, w) from the file's PNG header, nothing decoded; a file that is not a PNG (a TIFF or
    EPS named .png), or declares a decompression bomb, is a MaskError (issue 36)."""
    with open(p, "rb") as fh:
        head = fh.read(24)
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise MaskError(f"{p.name}: not a PNG file (no PNG signature and IHDR header)")
    w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if w * h > MAX_MASK_PIXELS:
        raise MaskError(f"{p.name}: the PNG header declares {w}x{h} pixels, more than the "
                        f"{MAX_MASK_PIXELS} any frame has")
    return h, w


def _read_png(root: Path, taxonomy: Taxonomy) -> list[_Item]:
    pngs = [p for p in _files(root, "*.png")]
    if not pngs:
        raise MaskError(f"{root}: no PNG masks found; expected <image stem>.png files")
    cmap = _read_class_map_png(root)
    items: list[_Item] = []
    for p in pngs:
        size = _png_header_size(p)
        if cmap is None:
            items.append(_Item(p.stem, size, [],
                               raw=lambda p=p: decode_mask_png(p, taxonomy, name=p.name)))
            continue
        table, src = cmap

        def shapes_of(p: Path = p, table: dict = table, src: str = src) -> list[_Shape]:
            img = Image.open(p)
            colour = any(isinstance(k, tuple) for k in table)
            if colour:
                arr = np.asarray(img.convert("RGB"))
                code = ((arr[..., 0].astype(np.uint32) << 16) | (arr[..., 1].astype(np.uint32) << 8)
                        | arr[..., 2])
                keys = {((k[0] << 16) | (k[1] << 8) | k[2]): v for k, v in table.items()
                        if isinstance(k, tuple)}
            else:
                if img.mode not in ("L", "P", "I;16", "I"):
                    raise MaskError(f"{p}: the class map {src} gives pixel values; expected a "
                                    f"single-channel (indexed) PNG, got mode {img.mode}")
                code = np.asarray(img).astype(np.int64)
                keys = {k: v for k, v in table.items() if isinstance(k, int)}
            values = np.unique(code)
            missing = [int(v) for v in values if int(v) not in keys]
            if missing:
                shown = ", ".join(f"#{m:06x}" if colour else str(m) for m in missing[:8])
                raise MaskError(f"{p}: pixel value(s) {shown} are not in the class map {src}")
            return [_Shape(keys[int(v)], mask=code == v) for v in values]

        items.append(_Item(p.stem, size, [], raw=None))
        items[-1].shapes = shapes_of  # type: ignore[assignment] - decoded after the name check
    return items


def _detect_cvat(root: Path) -> str:
    if _files(root, "*.xml") and not _files(root, "labelmap.txt"):
        return "cvat_images"
    if _files(root, "labelmap.txt") or (root / "SegmentationClass").is_dir():
        return "cvat_mask"
    if _files(root, "*.xml"):
        return "cvat_images"
    raise MaskError(f"{root}: neither a CVAT for images 1.1 export (annotations.xml) nor a "
                    f"Segmentation mask 1.1 export (labelmap.txt, SegmentationClass/)")


#: per image: at most this many shapes, of which at most MAX_MASKS_PER_ITEM full-image masks,
#: and polygons whose bounding boxes cover at most POLYGON_AREA_FACTOR images (issue 36: 20,000
#: small polygons in a 39 KB zip cost 14.6 s of CPU)
MAX_SHAPES_PER_ITEM = 10_000
MAX_MASKS_PER_ITEM = 1_000
POLYGON_AREA_FACTOR = 64


def _polygon_box(points: list[float], h: int, w: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the polygon's bounding box (one pixel of margin) clipped to the image."""
    xy = np.asarray(points, float).reshape(-1, 2)
    if not np.isfinite(xy).all():
        return 0, 0, 0, 0
    x0, y0 = np.floor(xy.min(axis=0)).astype(int)
    x1, y1 = np.ceil(xy.max(axis=0)).astype(int) + 2
    return max(0, y0), min(h, y1), max(0, x0), min(w, x1)


def _polygon_mask(points: list[float], h: int, w: int) -> np.ndarray:
    from pycocotools import mask as mask_utils  # heavy optional dependency

    if len(points) < 6:
        return np.zeros((h, w), bool)
    rle = mask_utils.frPyObjects([list(points)], h, w)
    return mask_utils.decode(mask_utils.merge(rle)).astype(bool)


def _check_shape_budget(it: _Item, frame: Frame) -> str | None:
    """A problem when ``it`` paints more than a frame's worth of shapes (before any is
    rasterised or decoded), else None."""
    if len(it.shapes) > MAX_SHAPES_PER_ITEM:
        return (f"{short(it.name)}: {len(it.shapes)} shapes, more than the "
                f"{MAX_SHAPES_PER_ITEM} accepted per image")
    n_masks = sum(1 for s in it.shapes if s.polygon is None)
    if n_masks > MAX_MASKS_PER_ITEM:
        return (f"{short(it.name)}: {n_masks} masks, more than the {MAX_MASKS_PER_ITEM} "
                f"accepted per image")
    h, w = it.size or (frame.camera.height, frame.camera.width)
    area = 0
    for s in it.shapes:
        if s.polygon is not None and len(s.polygon) >= 6:
            y0, y1, x0, x1 = _polygon_box(s.polygon, h, w)
            area += max(0, y1 - y0) * max(0, x1 - x0)
    if area > POLYGON_AREA_FACTOR * h * w:
        return (f"{short(it.name)}: its polygons' bounding boxes cover {area / (h * w):.0f} "
                f"images' worth of pixels, more than the {POLYGON_AREA_FACTOR} accepted")
    return None


def read_masks(archive: str | Path, fmt: str, frames: Sequence[Frame], taxonomy: Taxonomy, *,
               class_map: dict | None = None) -> ImportedMasks:
    """Read an export of another tool into raw-id masks of ``frames`` (checked; nothing is
    written). ``archive``: a zip, a folder or one annotation file. Raises MaskImportError
    listing every unknown class, unmatched image name and wrong-sized mask."""
    if fmt not in FORMATS:
        raise MaskError(f"format {fmt!r} is not supported; expected one of {', '.join(FORMATS)}")
    archive = Path(archive)
    with tempfile.TemporaryDirectory(prefix="occufly-masks-") as tmp:
        max_side = (max((f.camera.height for f in frames), default=0),
                    max((f.camera.width for f in frames), default=0))
        root = _extract(archive, Path(tmp), fmt, max_side=max_side)
        try:
            if fmt == "cvat":
                fmt = _detect_cvat(root)
            if fmt in _DATUMARO:
                _datumaro_image_backend()
            if fmt == "cvat_images":
                items = _read_cvat_images(root)
            elif fmt in _DATUMARO:
                items = _read_datumaro(root, fmt)
            elif fmt == "labelstudio":
                items = _read_labelstudio(root)
            else:
                items = _read_png(root, taxonomy)
            return _resolve(items, fmt, frames, taxonomy, class_map, archive.name)
        except MaskError as e:  # name the archive, not the temporary folder it was unpacked in
            if isinstance(e, MaskImportError) or str(root) not in str(e):
                raise
            raise MaskError(str(e).replace(str(root), archive.name)) from None


def _resolve(items: list[_Item], fmt: str, frames: Sequence[Frame], taxonomy: Taxonomy,
             class_map: dict | None, source: str) -> ImportedMasks:
    look = _frame_lookup(frames)
    problems: list[str] = []
    unmatched = [it.name for it in items if (it.shapes or it.raw) and match_frame(it.name, look)
                 is None]
    if unmatched:
        problems.append(f"{len(unmatched)} image(s) name no frame of the scene: "
                        + ", ".join(short(u) for u in unmatched[:50])
                        + (" ..." if len(unmatched) > 50 else ""))
    for it in items:  # png with a class map: decode now (the shapes name the classes)
        if callable(it.shapes):  # its header's size checked against the frame first
            if unmatched:  # no image is decoded while a name matches no frame (issue 36)
                it.shapes = []
                continue
            try:
                mask_scale(it.size, frames[match_frame(it.name, look)], name=short(it.name))
            except MaskError as e:
                problems.append(str(e))
                it.shapes = []
                continue
            it.shapes = it.shapes()
    names = sorted({s.label for it in items for s in it.shapes})
    ids, class_problems = resolve_classes(names, taxonomy, class_map, source=source)
    problems += class_problems
    seen: dict[int, str] = {}
    for it in items:
        fi = match_frame(it.name, look)
        if fi is None or not (it.shapes or it.raw):
            continue
        if (budget := _check_shape_budget(it, frames[fi])) is not None:
            problems.append(budget)
        if fi in seen:
            problems.append(f"frame {frames[fi].name!r} has masks in two items, {short(seen[fi])} "
                            f"and {short(it.name)}")
        seen[fi] = it.name
    if problems:
        raise MaskImportError(source, problems)
    masks: dict[int, np.ndarray] = {}
    names_of: dict[int, str] = {}
    skipped: list[str] = []
    for it in items:
        if not (it.shapes or it.raw):
            skipped.append(it.name)
            continue
        fi = match_frame(it.name, look)
        frame = frames[fi]
        try:
            if it.raw is not None and it.size is not None:  # the header, before decoding
                mask_scale(it.size, frame, name=short(it.name))
            out = it.raw() if it.raw is not None else _paint(it, frame, ids)
            mask_scale(out.shape, frame, name=f"{it.name}")
        except MaskError as e:
            problems.append(str(e))
            continue
        if not out.any():  # nothing painted casts no vote: not a version worth storing
            skipped.append(it.name)
            continue
        masks[fi] = out
        names_of[fi] = it.name
    if problems:
        raise MaskImportError(source, problems)
    used = {n: i for n, i in ids.items()}
    return ImportedMasks(fmt, masks, names_of, used, skipped)


def _paint(it: _Item, frame: Frame, ids: dict[str, int]) -> np.ndarray:
    """The item's shapes painted into one raw-id mask, lowest z first, later shapes on top."""
    h, w = it.size or (frame.camera.height, frame.camera.width)
    mask_scale((h, w), frame, name=it.name)  # the frame's size (or a downscale) before decoding
    out = np.zeros((h, w), np.uint8)
    for s in sorted(it.shapes, key=lambda s: s.z):  # stable: file order within a z level
        if s.polygon is not None:  # rasterised within its bounding box
            if len(s.polygon) < 6:
                continue
            y0, y1, x0, x1 = _polygon_box(s.polygon, h, w)
            if y1 <= y0 or x1 <= x0:
                continue
            xy = np.asarray(s.polygon, float).reshape(-1, 2) - (x0, y0)
            out[y0:y1, x0:x1][_polygon_mask(xy.ravel().tolist(), y1 - y0, x1 - x0)] = \
                ids[s.label]
            continue
        else:
            if s.size is not None and tuple(s.size) != (h, w):  # before decoding (issue 36)
                raise MaskError(f"{short(it.name)}: a {short(s.label)} mask declares "
                                f"{s.size[1]}x{s.size[0]} pixels in a {w}x{h} image")
            try:
                m = s.mask() if callable(s.mask) else s.mask
            except MaskError:
                raise
            except Exception as e:  # noqa: BLE001 - the format library's decode failed
                raise MaskError(f"{short(it.name)}: cannot decode its {short(s.label)} mask "
                                f"({type(e).__name__}: {e})") from None
            if m.shape != (h, w):
                raise MaskError(f"{short(it.name)}: a {short(s.label)} mask is {m.shape[1]}x{m.shape[0]} "
                                f"pixels in a {w}x{h} image")
        out[m] = ids[s.label]
    return out


# ---- writers --------------------------------------------------------------------------------
def _full_size(mask: np.ndarray, frame: Frame) -> np.ndarray:
    s = mask_scale(mask.shape, frame, name=frame.name)
    return mask if s == 1 else np.repeat(np.repeat(mask, s, axis=0), s, axis=1)


def _class_list(taxonomy: Taxonomy, masks: dict[int, np.ndarray]) -> list[tuple[int, str, tuple]]:
    """(raw id, name, rgb) of every class, plus ``ignore`` when a mask holds 255."""
    rows = [(c.id, c.name, tuple(c.rgb)) for c in taxonomy.classes]
    if any(bool((m == INVALID).any()) for m in masks.values()):
        rows.append((INVALID, "ignore", (255, 255, 255)))
    return rows


def write_masks(out: str | Path, fmt: str, masks: dict[int, np.ndarray],
                frames: Sequence[Frame], taxonomy: Taxonomy, *,
                prediction: bool = False) -> dict:
    """Write raw-id masks (frame index -> (h, w) uint8, the frame's size or an integer
    downscale) in ``fmt``: a zip when ``out`` ends in .zip, a folder otherwise. Frames with a
    mask of only 0 are listed with no annotation. ``prediction``: Label Studio gets them as
    pre-annotations (``predictions``) instead of annotations. Returns a summary."""
    if fmt not in FORMATS:
        raise MaskError(f"format {fmt!r} is not supported; expected one of {', '.join(FORMATS)}")
    if fmt == "cvat":
        fmt = "cvat_images"
    out = Path(out)
    as_zip = out.suffix.lower() == ".zip"
    if out.exists() and (as_zip or not out.is_dir() or any(out.iterdir())):
        raise MaskError(f"{out}: already exists; expected a new file or an empty folder")
    full = {fi: _full_size(np.asarray(m, np.uint8), frames[fi]) for fi, m in masks.items()}
    rows = _class_list(taxonomy, full)
    with tempfile.TemporaryDirectory(prefix="occufly-masks-out-") as tmp:
        stage = Path(tmp) / "out"
        stage.mkdir()
        if fmt in _DATUMARO:
            _datumaro_image_backend()
            _write_datumaro(stage, fmt, full, frames, rows)
        elif fmt == "labelstudio":
            _write_labelstudio(stage, full, frames, rows, prediction)
        else:
            _write_png(stage, full, frames, rows)
        if as_zip:
            out.parent.mkdir(parents=True, exist_ok=True)
            part = out.with_name(out.name + ".part")
            with zipfile.ZipFile(part, "w", zipfile.ZIP_DEFLATED) as zf:
                for p in sorted(stage.rglob("*")):
                    if p.is_file():
                        zf.write(p, p.relative_to(stage).as_posix())
            part.replace(out)
        else:
            out.mkdir(parents=True, exist_ok=True)
            for p in stage.iterdir():
                shutil.move(str(p), out / p.name)
    return {"format": fmt, "tool": TOOL_NAMES[fmt], "out": str(out), "frames": len(full),
            "annotated_frames": sum(1 for m in full.values() if m.any()),
            "classes": [name for cid, name, _ in rows
                        if any(bool((m == cid).any()) for m in full.values())]}


def _write_datumaro(stage: Path, fmt: str, masks: dict[int, np.ndarray],
                    frames: Sequence[Frame], rows: list) -> None:
    from datumaro.components.annotation import (  # heavy optional dependency
        AnnotationType,
        LabelCategories,
        Mask,
        MaskCategories,
    )
    from datumaro.components.dataset import Dataset
    from datumaro.components.dataset_base import DatasetItem
    from datumaro.components.media import Image

    index = {cid: k for k, (cid, _n, _c) in enumerate(rows)}
    items = []
    for fi in sorted(masks):
        m, f = masks[fi], frames[fi]
        present = np.flatnonzero(np.bincount(m.ravel(), minlength=256))
        anns = [Mask(image=(m == cid), label=index[int(cid)], id=k + 1, group=k + 1)
                for k, cid in enumerate(present) if cid != EMPTY]
        items.append(DatasetItem(id=Path(f.name).stem, subset="default",
                                 media=Image.from_file(path=Path(f.name).name,
                                                       size=(f.camera.height, f.camera.width)),
                                 annotations=anns))
    cats = {AnnotationType.label: LabelCategories.from_iterable([n for _i, n, _c in rows]),
            AnnotationType.mask: MaskCategories(colormap={k: c for k, (_i, _n, c)
                                                          in enumerate(rows)})}
    ds = Dataset.from_iterable(items, categories=cats)
    kw = {"voc_segmentation": {"label_map": "source"},
          "coco_instances": {"segmentation_mode": "mask", "reindex": True},
          "coco_panoptic": {"reindex": True}}.get(_DATUMARO[fmt], {})
    ds.export(str(stage), _DATUMARO[fmt], save_media=False, **kw)
    if fmt == "cvat_images":  # CVAT's own export and import name it annotations.xml
        for x in stage.glob("*.xml"):
            x.rename(stage / "annotations.xml")
            break


def _write_labelstudio(stage: Path, masks: dict[int, np.ndarray], frames: Sequence[Frame],
                       rows: list, prediction: bool) -> None:
    # HumanSignal's encoder (the Rust port's encoder is slower: 4-22 s for a 12 MP stroke
    # against 3 s)
    from label_studio_converter.brush import mask2rle  # heavy optional dependency

    names = {cid: n for cid, n, _c in rows}
    tasks = []
    for fi in sorted(masks):
        m, f = masks[fi], frames[fi]
        h, w = m.shape
        result = []
        for cid in np.flatnonzero(np.bincount(m.ravel(), minlength=256)):
            if cid == EMPTY:
                continue
            rle = mask2rle(((m == cid) * 255).astype(np.uint8))
            result.append({"id": f"{Path(f.name).stem}_{int(cid)}", "type": "brushlabels",
                           "from_name": LS_FROM_NAME, "to_name": LS_TO_NAME,
                           "original_width": w, "original_height": h, "image_rotation": 0,
                           "value": {"format": "rle", "rle": [int(v) for v in rle],
                                     "brushlabels": [names[int(cid)]]}})
        entry = ({"model_version": "occufly-prefill", "score": 1.0, "result": result}
                 if prediction else {"result": result, "was_cancelled": False})
        tasks.append({"data": {"image": Path(f.name).name},
                      ("predictions" if prediction else "annotations"): [entry] if result else []})
    (stage / "tasks.json").write_text(json.dumps(tasks))
    labels = "\n".join(f'    <Label value="{n}" background="#{c[0]:02x}{c[1]:02x}{c[2]:02x}"/>'
                       for _i, n, c in rows)
    (stage / "labeling_config.xml").write_text(
        f'<View>\n  <Image name="{LS_TO_NAME}" value="$image" zoom="true"/>\n'
        f'  <BrushLabels name="{LS_FROM_NAME}" toName="{LS_TO_NAME}">\n{labels}\n'
        f'  </BrushLabels>\n</View>\n')


def _write_png(stage: Path, masks: dict[int, np.ndarray], frames: Sequence[Frame],
               rows: list) -> None:
    for fi, m in masks.items():
        (stage / f"{frames[fi].stem}.png").write_bytes(encode_mask_png(m))
    table = {str(cid): n for cid, n, _c in rows}
    (stage / "classes.json").write_text(json.dumps({"0": "unpainted", **table}, indent=1))
