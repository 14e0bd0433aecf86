"""Issue 36 finding 7: EXIF/XMP numbers are finite and in range, or dropped with a warning
naming the photo (a NaN or 1e999 RtkFlag raised out of read_geotag; GPS rationals n/0 gave a
NaN position that counted as a geotag; a latitude of 4.4e9 degrees was accepted)."""

from __future__ import annotations

import pytest
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from occufly.io.exif import read_geotag


def _jpeg(path, *, gps=None, xmp: bytes | None = None):  # noqa: ANN001, ANN202
    exif = Image.Exif()
    if gps is not None:
        exif[0x8825] = gps
    kw = {"exif": exif.tobytes()}
    if xmp is not None:
        kw["xmp"] = xmp
    Image.new("RGB", (8, 8)).save(path, **kw)
    return path


_LON = (IFDRational(2), IFDRational(30), IFDRational(0))
_ALT = IFDRational(120)


def _gps(lat, lon=_LON, alt=_ALT):  # noqa: ANN001, ANN202
    return {1: "N", 2: lat, 3: "W", 4: lon, 5: b"\x00", 6: alt}


OK_LAT = (IFDRational(39), IFDRational(51), IFDRational(1234, 100))


def test_a_good_geotag_is_read(tmp_path):
    g = read_geotag(_jpeg(tmp_path / "good.jpg", gps=_gps(OK_LAT)))
    assert g.has_gps and g.lat == pytest.approx(39 + 51 / 60 + 12.34 / 3600)
    assert g.lon == pytest.approx(-2.5) and g.altitude == 120 and g.warning is None


@pytest.mark.parametrize("label,gps", [
    ("n/0 latitude", _gps((IFDRational(1, 0), IFDRational(0), IFDRational(0)))),
    ("4.4e9 degrees", _gps((IFDRational(4_400_000_000), IFDRational(0), IFDRational(0)))),
    ("n/0 altitude", _gps(OK_LAT, alt=IFDRational(5, 0))),
])
def test_a_gps_value_out_of_range_skips_the_photos_position(tmp_path, label, gps):
    g = read_geotag(_jpeg(tmp_path / "bad.jpg", gps=gps))
    assert not g.has_gps and g.altitude is None, label
    assert g.warning and "bad.jpg" in g.warning and "GPS position is skipped" in g.warning


@pytest.mark.parametrize("value", ["nan", "1e999", "-inf", "4.4e9"])
def test_an_xmp_value_out_of_range_is_dropped_with_a_warning(tmp_path, value):
    xmp = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF><rdf:Description '
           b'drone-dji:RtkFlag="' + value.encode() + b'" drone-dji:GimbalPitchDegree="'
           + value.encode() + b'" drone-dji:RelativeAltitude="50.5"/></rdf:RDF></x:xmpmeta>')
    g = read_geotag(_jpeg(tmp_path / "x.jpg", gps=_gps(OK_LAT), xmp=xmp))
    assert g.rtk_flag is None and g.gimbal_pitch is None and g.relative_altitude == 50.5
    assert g.has_gps  # an XMP value does not drop the EXIF position
    assert "x.jpg" in g.warning and "rtk_flag" in g.warning
