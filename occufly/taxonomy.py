"""Class table: raw ids, names, colours, groups, DBSCAN parameters and the tie-break order.

Raw ids are not contiguous. 0 is *empty* and 255 is *invalid/unknown*; neither may be used by
a class. Everything in the pipeline and the UI follows a loaded :class:`Taxonomy`, never the
literals of the default table.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from occufly import safe_yaml
from occufly.errors import InputFormatError, TaxonomyError, check_name

EMPTY = 0
INVALID = 255
GROUPS = ("instance", "ground", "other")


@dataclass(frozen=True)
class SemanticClass:
    """One row of the class table."""

    id: int
    name: str
    rgb: tuple[int, int, int]
    group: str
    freq: float = 0.0
    dbscan_eps: float | None = None
    dbscan_min_points: int | None = None
    # ASPRS LAS 1.4 classification code (2 ground, 5 high vegetation, 6 building, ...) where
    # the class has one; None = no standard code (the LAS export gives it a user code 64+)
    asprs: int | None = None


# id, name, RGB, group, freq %, (eps, minPts) -- FORMATS.md section 1.
_DEFAULT_ROWS: list[tuple] = [
    (1, "road", (128, 0, 128), "ground", 1.8909, None),
    (2, "walkway", (204, 163, 72), "ground", 2.0610, None),
    (3, "dirt", (128, 0, 0), "ground", 2.3584, None),
    (4, "gravel", (192, 192, 192), "ground", 1.4511, None),
    (5, "rock", (246, 120, 40), "other", 0.0402, None),
    (6, "grass", (0, 255, 0), "ground", 8.5614, None),
    (7, "vegetation", (112, 148, 32), "ground", 4.3121, None),
    (8, "tree", (64, 64, 0), "other", 7.5479, None),
    (9, "ground_obstacle", (255, 255, 0), "other", 1.9605, None),
    (11, "person", (255, 16, 255), "instance", 0.0001, (0.3, 10)),
    (12, "bicycle", (255, 204, 153), "instance", 0.0035, (0.4, 80)),
    (13, "vehicle", (0, 128, 128), "instance", 0.5683, (1.0, 500)),
    (14, "water", (0, 0, 255), "ground", 1.7539, None),
    (16, "building", (255, 0, 0), "instance", 62.1534, (4.0, 1000)),
    (17, "roof", (64, 160, 120), "instance", 2.2018, (1.0, 1000)),
    (21, "cable", (255, 160, 0), "other", 0.0018, None),
    (22, "cable_tower", (106, 0, 255), "other", 0.0047, None),
    (33, "parking_lot", (128, 64, 128), "ground", 2.8415, None),
    (34, "construction", (240, 120, 120), "other", 0.2741, None),
    (35, "crane", (255, 255, 128), "instance", 0.0059, (1.0, 500)),
    (36, "truck", (128, 128, 64), "instance", 0.1105, (1.0, 500)),
]

# ASPRS LAS 1.4 (R15) standard classification codes the default classes map to. Only classes
# with a true standard equivalent have one: walkway, parking lot, rock, obstacles, people and
# vehicles have none and get user-definable codes (64+) in the LAS export.
ASPRS_NAMES = {
    0: "Never classified", 1: "Unclassified", 2: "Ground", 3: "Low Vegetation",
    4: "Medium Vegetation", 5: "High Vegetation", 6: "Building", 7: "Low Point (noise)",
    9: "Water", 10: "Rail", 11: "Road Surface", 13: "Wire - Guard", 14: "Wire - Conductor",
    15: "Transmission Tower", 16: "Wire Connector", 17: "Bridge Deck", 18: "High Noise",
    19: "Overhead Structure", 20: "Ignored Ground", 21: "Snow", 22: "Temporal Exclusion",
}
_DEFAULT_ASPRS = {
    "road": 11, "dirt": 2, "gravel": 2, "grass": 3, "vegetation": 4, "tree": 5,
    "water": 9, "building": 6, "roof": 6, "cable": 14, "cable_tower": 15,
}
ASPRS_UNCLASSIFIED = 1   # what an unlabelled point (id 0) becomes
ASPRS_USER_FIRST = 64    # first user-definable code


@dataclass(frozen=True)
class Taxonomy:
    """An ordered, validated class table.

    ``classes`` keeps the file's row order. ``tie_order`` lists class ids from most to least
    preferred when votes tie: more frequent first, then lower id.
    """

    classes: tuple[SemanticClass, ...]
    name: str = "occufly"
    _by_id: dict[int, SemanticClass] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _validate(self.classes, source=self.name)
        object.__setattr__(self, "_by_id", {c.id: c for c in self.classes})

    # ---- lookups -------------------------------------------------------------------------
    @property
    def ids(self) -> np.ndarray:
        """(C,) uint8 raw class ids in table order."""
        return np.array([c.id for c in self.classes], dtype=np.uint8)

    def __len__(self) -> int:
        return len(self.classes)

    def __contains__(self, class_id: object) -> bool:
        return isinstance(class_id, (int, np.integer)) and int(class_id) in self._by_id

    def __getitem__(self, class_id: int) -> SemanticClass:
        try:
            return self._by_id[int(class_id)]
        except KeyError:
            raise TaxonomyError(f"class id {class_id} is not in taxonomy {self.name!r}") from None

    def by_name(self, name: str) -> SemanticClass:
        for c in self.classes:
            if c.name == name:
                return c
        raise TaxonomyError(f"class name {name!r} is not in taxonomy {self.name!r}")

    def group_ids(self, group: str) -> np.ndarray:
        """(K,) uint8 ids of the classes in ``group`` (instance / ground / other)."""
        if group not in GROUPS:
            raise TaxonomyError(f"unknown group {group!r}; expected one of {GROUPS}")
        return np.array([c.id for c in self.classes if c.group == group], dtype=np.uint8)

    @property
    def tie_order(self) -> np.ndarray:
        """(C,) uint8 class ids, most preferred first (frequency descending, then id)."""
        order = sorted(self.classes, key=lambda c: (-c.freq, c.id))
        return np.array([c.id for c in order], dtype=np.uint8)

    def priority_lut(self) -> np.ndarray:
        """(256,) int16 rank of each raw id in the tie order (0 = most preferred); -1 elsewhere."""
        lut = np.full(256, -1, dtype=np.int16)
        lut[self.tie_order] = np.arange(len(self.classes), dtype=np.int16)
        return lut

    def valid_lut(self) -> np.ndarray:
        """(256,) bool, True for raw ids that are classes of this taxonomy."""
        lut = np.zeros(256, dtype=bool)
        lut[self.ids] = True
        return lut

    def colour_lut(self) -> np.ndarray:
        """(256, 3) uint8 RGB per raw id; empty is black, unknown ids are magenta-grey."""
        lut = np.full((256, 3), 96, dtype=np.uint8)
        lut[EMPTY] = 0
        for c in self.classes:
            lut[c.id] = c.rgb
        return lut

    def asprs_lut(self) -> np.ndarray:
        """(256,) uint8 ASPRS LAS classification code per raw id.

        A class's own ``asprs`` code where it has one; classes without get user-definable
        codes 64, 65, ... in table order; empty (0) and unknown ids are 1 (unclassified)."""
        lut = np.full(256, ASPRS_UNCLASSIFIED, dtype=np.uint8)
        user = ASPRS_USER_FIRST
        for c in self.classes:
            if c.asprs is not None:
                lut[c.id] = c.asprs
            else:
                lut[c.id] = min(user, 255)
                user += 1
        return lut

    def learning_map(self) -> dict[int, int]:
        """Raw id -> contiguous training id: 0 = empty, 1..C in table order, 255 stays ignore."""
        m = {EMPTY: 0, INVALID: 255}
        for i, c in enumerate(self.classes, start=1):
            m[c.id] = i
        return m

    # ---- (de)serialisation ---------------------------------------------------------------
    def to_dict(self) -> dict:
        rows = []
        for c in self.classes:
            d = asdict(c)
            d["rgb"] = list(c.rgb)
            rows.append(d)
        return {"name": self.name, "classes": rows}

    @classmethod
    def from_dict(cls, data: object, *, source: str = "<dict>") -> Taxonomy:
        if not isinstance(data, dict) or not isinstance(data.get("classes"), list):
            raise TaxonomyError(f"{source}: expected a mapping with a 'classes' list")
        rows = []
        for i, row in enumerate(data["classes"]):
            rows.append(_parse_row(row, where=f"{source}: classes[{i}]"))
        if data.get("name") == "occufly" and not any(
                isinstance(r, dict) and "asprs" in r for r in data["classes"]):
            # the default table saved before it had ASPRS codes: same classes, same codes
            rows = [replace(r, asprs=_DEFAULT_ASPRS.get(r.name)) for r in rows]
        _validate(tuple(rows), source=source)
        return cls(classes=tuple(rows), name=str(data.get("name", Path(source).stem)))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> Taxonomy:
        """Load a taxonomy from a JSON or YAML file (same columns as the default table)."""
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as e:
            raise TaxonomyError(f"{path}: cannot read taxonomy file ({e.strerror})") from None
        try:
            if path.suffix.lower() in (".yaml", ".yml"):
                data = safe_yaml.load(text)  # no aliases (issue 36)
            else:
                data = json.loads(text)
        except Exception as e:  # noqa: BLE001 - parser errors differ per format
            raise TaxonomyError(f"{path}: not valid {path.suffix.lstrip('.') or 'JSON'}: "
                                f"{str(e)[:300]}") from None
        return cls.from_dict(data, source=str(path))


def _parse_row(row: object, *, where: str) -> SemanticClass:
    if not isinstance(row, dict):
        raise TaxonomyError(f"{where}: expected a mapping with id, name, rgb, group")
    missing = [k for k in ("id", "name", "rgb", "group") if k not in row]
    if missing:
        raise TaxonomyError(f"{where}: missing field(s) {', '.join(missing)}")
    try:
        cid = int(row["id"])
    except (TypeError, ValueError):
        raise TaxonomyError(f"{where}: id must be an integer, got {row['id']!r}") from None
    rgb = row["rgb"]
    if isinstance(rgb, str):
        rgb = [int(v) for v in rgb.replace(",", " ").split()]
    if (
        not isinstance(rgb, (list, tuple))
        or len(rgb) != 3
        or not all(isinstance(v, int) and 0 <= v <= 255 for v in rgb)
    ):
        raise TaxonomyError(f"{where}: rgb must be three integers 0..255, got {row['rgb']!r}")
    eps = row.get("dbscan_eps")
    minpts = row.get("dbscan_min_points")
    try:
        return SemanticClass(
            id=cid,
            name=str(row["name"]),
            rgb=(int(rgb[0]), int(rgb[1]), int(rgb[2])),
            group=str(row["group"]),
            freq=float(row.get("freq", 0.0) or 0.0),
            dbscan_eps=None if eps is None else float(eps),
            dbscan_min_points=None if minpts is None else int(minpts),
            asprs=None if row.get("asprs") is None else int(row["asprs"]),
        )
    except (TypeError, ValueError) as e:
        raise TaxonomyError(f"{where}: {e}") from None


def _validate(classes: tuple[SemanticClass, ...], *, source: str) -> None:
    if not classes:
        raise TaxonomyError(f"{source}: a taxonomy needs at least one class")
    seen_ids: set[int] = set()
    seen_names: set[str] = set()
    for c in classes:
        if c.id in (EMPTY, INVALID):
            raise TaxonomyError(
                f"{source}: class {c.name!r} uses id {c.id}, which is reserved "
                f"({EMPTY} = empty, {INVALID} = invalid)"
            )
        if not 1 <= c.id <= 254:
            raise TaxonomyError(f"{source}: class {c.name!r} id {c.id} is outside 1..254")
        if c.id in seen_ids:
            raise TaxonomyError(f"{source}: duplicate class id {c.id}")
        if c.name in seen_names:
            raise TaxonomyError(f"{source}: duplicate class name {c.name!r}")
        try:  # class names reach pages and the 3D viewer: no markup, no control characters
            check_name(c.name, f"{source}: class {c.id}")
        except InputFormatError as e:
            raise TaxonomyError(str(e)) from None
        if c.group not in GROUPS:
            raise TaxonomyError(
                f"{source}: class {c.name!r} has unknown group {c.group!r}; expected one of "
                f"{', '.join(GROUPS)}"
            )
        if c.group == "instance" and (c.dbscan_eps is None or c.dbscan_min_points is None):
            raise TaxonomyError(
                f"{source}: instance class {c.name!r} needs dbscan_eps and dbscan_min_points"
            )
        if c.asprs is not None and not (c.asprs in ASPRS_NAMES and c.asprs >= 2 or 64 <= c.asprs <= 255):
            raise TaxonomyError(
                f"{source}: class {c.name!r} asprs code {c.asprs} is not a class code of "
                f"ASPRS LAS 1.4 (standard 2-7, 9-11, 13-22; user-definable 64-255)"
            )
        if c.dbscan_eps is not None and c.dbscan_eps <= 0:
            raise TaxonomyError(f"{source}: class {c.name!r} dbscan_eps must be > 0")
        seen_ids.add(c.id)
        seen_names.add(c.name)


def default_taxonomy() -> Taxonomy:
    """The 21-class OccuFly table of FORMATS.md section 1."""
    rows = []
    for cid, name, rgb, group, freq, db in _DEFAULT_ROWS:
        rows.append(
            SemanticClass(
                id=cid,
                name=name,
                rgb=rgb,
                group=group,
                freq=freq,
                dbscan_eps=None if db is None else db[0],
                dbscan_min_points=None if db is None else db[1],
                asprs=_DEFAULT_ASPRS.get(name),
            )
        )
    return Taxonomy(classes=tuple(rows), name="occufly")
