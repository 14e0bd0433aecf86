"""Geotags of drone photos: EXIF GPS (Pillow's GPSInfo IFD) and DJI XMP (drone-dji namespace).

:func:`read_geotag` returns a :class:`Geotag` per image: WGS 84 latitude/longitude (decimal
degrees, signed by the N/S, E/W refs), EXIF GPSAltitude (metres, negative when
GPSAltitudeRef = 1; read as the recorder wrote it, not a verified datum), the 35 mm equivalent
focal length, and, when the JPEG carries DJI's XMP packet, its RelativeAltitude,
AbsoluteAltitude, RTK flag and standard deviations and gimbal angles. Missing tags are None.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path

from PIL import Image

GPS_IFD = 0x8825
EXIF_IFD = 0x8769
_XMP_START, _XMP_END = b"<x:xmpmeta", b"</x:xmpmeta>"
#: DJI XMP tags read, attribute or element form: drone-dji:Name="v" / <drone-dji:Name>v<
_DJI_TAGS = {
    "RelativeAltitude": "relative_altitude", "AbsoluteAltitude": "absolute_altitude",
    "GimbalPitchDegree": "gimbal_pitch", "GimbalYawDegree": "gimbal_yaw",
    "GimbalRollDegree": "gimbal_roll", "RtkFlag": "rtk_flag", "RtkStdLon": "rtk_std_lon",
    "RtkStdLat": "rtk_std_lat", "RtkStdHgt": "rtk_std_hgt",
}


@dataclass
class Geotag:
    name: str
    lat: float | None = None
    lon: float | None = None
    altitude: float | None = None  # EXIF GPSAltitude, metres
    focal_35mm: float | None = None  # EXIF FocalLengthIn35mmFilm, mm
    focal_mm: float | None = None
    make: str | None = None
    model: str | None = None
    relative_altitude: float | None = None  # DJI XMP, metres above take-off
    absolute_altitude: float | None = None
    gimbal_pitch: float | None = None
    gimbal_yaw: float | None = None
    gimbal_roll: float | None = None
    rtk_flag: int | None = None
    rtk_std_lon: float | None = None
    rtk_std_lat: float | None = None
    rtk_std_hgt: float | None = None
    #: why values of this photo were dropped (non-finite or out of range), naming it; None: none
    warning: str | None = None

    @property
    def has_gps(self) -> bool:
        return self.lat is not None and self.lon is not None

    def to_dict(self) -> dict:
        return asdict(self)


def _dms(v, ref) -> float | None:
    """Degrees from EXIF (degrees, minutes, seconds) rationals; NaN when a part is not a finite
    number in range (a rational n/0 reads as NaN), None when the tag is not a triple."""
    try:
        d, m, s = (float(x) for x in v)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None
    if not all(math.isfinite(x) for x in (d, m, s)) or not (0 <= d <= 180 and 0 <= m < 60
                                                            and 0 <= s < 60.001):
        return math.nan
    out = d + m / 60.0 + s / 3600.0
    return -out if str(ref).strip().upper() in ("S", "W") else out


#: the accepted range of every number read (issue 36: NaN, 1e999 and a latitude of 4.4e9
#: degrees were taken as they came); a value outside is dropped with a warning
_RANGES = {"lat": (-90.0, 90.0), "lon": (-180.0, 180.0), "altitude": (-1000.0, 50000.0),
           "focal_35mm": (0.1, 10000.0), "focal_mm": (0.1, 10000.0),
           "relative_altitude": (-10000.0, 50000.0), "absolute_altitude": (-1000.0, 50000.0),
           "gimbal_pitch": (-360.0, 360.0), "gimbal_yaw": (-360.0, 360.0),
           "gimbal_roll": (-360.0, 360.0), "rtk_flag": (0, 1000),
           "rtk_std_lon": (0.0, 1e6), "rtk_std_lat": (0.0, 1e6), "rtk_std_hgt": (0.0, 1e6)}


def _checked(tag: Geotag) -> Geotag:
    """Drop every value of ``tag`` that is not finite or out of range, with a warning naming
    the photo; a bad latitude, longitude or altitude drops the whole GPS position (the photo
    is skipped by the georeferencing)."""
    bad = []
    for key, (lo, hi) in _RANGES.items():
        v = getattr(tag, key)
        if v is None:
            continue
        if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
            bad.append(f"{key} {str(v)[:24]}")
            setattr(tag, key, None)
    if bad:
        gps = any(b.split()[0] in ("lat", "lon", "altitude") for b in bad)
        if gps:
            tag.lat = tag.lon = tag.altitude = None
        tag.warning = (f"photo {tag.name}: {', '.join(bad)} not a finite value in range; "
                       + ("its GPS position is skipped" if gps else "the value is skipped"))
    return tag


def read_xmp(path: str | Path, *, max_bytes: int = 1 << 20) -> dict:
    """DJI XMP values of the image at ``path`` ({} without a packet). The packet is an XML
    block in the JPEG's first segments; only the first ``max_bytes`` are searched."""
    with open(path, "rb") as fh:
        head = fh.read(max_bytes)
    i = head.find(_XMP_START)
    if i < 0:
        return {}
    j = head.find(_XMP_END, i)
    packet = head[i:j if j > 0 else len(head)].decode("utf-8", "replace")
    out: dict = {}
    for tag, key in _DJI_TAGS.items():
        m = (re.search(rf'drone-dji:{tag}\s*=\s*"([^"]*)"', packet)
             or re.search(rf"<drone-dji:{tag}>([^<]*)<", packet))
        if m:
            try:
                val = float(m.group(1).strip()[:64])
            except ValueError:
                continue
            # a non-finite flag stays a float: _checked drops it (int(nan) raised here)
            out[key] = int(val) if key == "rtk_flag" and math.isfinite(val) else val
    return out


def read_geotag(path: str | Path) -> Geotag:
    """The :class:`Geotag` of one image (all None when it has no EXIF)."""
    path = Path(path)
    tag = Geotag(name=path.name)
    try:
        with Image.open(path) as img:
            exif = img.getexif()
    except Exception:  # noqa: BLE001 - PIL raises many types for broken files
        return tag
    tag.make = (str(exif.get(0x010F)).strip("\x00 ")[:64] or None) if exif.get(0x010F) else None
    tag.model = (str(exif.get(0x0110)).strip("\x00 ")[:64] or None) if exif.get(0x0110) else None
    sub = exif.get_ifd(EXIF_IFD)
    if sub.get(0xA405):
        tag.focal_35mm = _number(sub[0xA405])
    if sub.get(0x920A):
        tag.focal_mm = _number(sub[0x920A])
    gps = exif.get_ifd(GPS_IFD)
    if gps:
        if 2 in gps and 4 in gps:
            tag.lat = _dms(gps[2], gps.get(1, "N"))
            tag.lon = _dms(gps[4], gps.get(3, "E"))
        if 6 in gps:
            alt = _number(gps[6])
            ref = gps.get(5, 0)
            ref = ref[0] if isinstance(ref, bytes) and ref else ref
            try:
                below = int(ref or 0) == 1
            except (TypeError, ValueError):
                below = False
            tag.altitude = -alt if below and alt is not None else alt
    for k, v in read_xmp(path).items():
        setattr(tag, k, v)
    return _checked(tag)


def _number(v) -> float | None:  # noqa: ANN001 - an EXIF value (rational, int, bytes, ...)
    try:
        return float(v)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return math.nan  # not a number: dropped with a warning by _checked


def read_geotags(image_dir: str | Path, names: list[str]) -> list[Geotag]:
    """:func:`read_geotag` of ``image_dir / name`` for every name (in order)."""
    return [read_geotag(Path(image_dir) / n) for n in names]
