"""Issue 29 (save p95): an upload that is already the canonical 8-bit class-id PNG is stored
as it is; everything issue 24's canonical storage strips is still detected and re-encoded."""
from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image, PngImagePlugin

from occufly.io.masks import encode_mask_png, is_canonical_mask_png, png_chunk


def _png(ids: np.ndarray, *, z: bytes | None = None, extra: bytes = b"", idat_split: int = 0,
         depth: int = 8, colour: int = 0) -> bytes:
    h, w = ids.shape
    raw = b"".join(b"\x00" + ids[r].tobytes() for r in range(h))
    z = zlib.compress(raw, 6) if z is None else z
    parts = [z] if not idat_split else [z[i:i + idat_split] for i in range(0, len(z), idat_split)]
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0))
            + b"".join(png_chunk(b"IDAT", p) for p in parts) + png_chunk(b"IEND", b"") + extra)


@pytest.fixture()
def ids():
    rng = np.random.default_rng(0)
    return rng.integers(0, 21, size=(48, 64), dtype=np.uint8)


def test_canonical_encodings_are_recognised(ids):
    assert is_canonical_mask_png(encode_mask_png(ids), ids.shape)
    assert is_canonical_mask_png(_png(ids), ids.shape)
    assert is_canonical_mask_png(_png(ids, idat_split=100), ids.shape)  # many IDATs
    b = io.BytesIO()
    Image.fromarray(ids).save(b, format="PNG", compress_level=1)
    assert is_canonical_mask_png(b.getvalue(), ids.shape)


def test_everything_canonical_storage_strips_is_refused(ids):
    raw = b"".join(b"\x00" + ids[r].tobytes() for r in range(ids.shape[0]))
    good = _png(ids)
    assert not is_canonical_mask_png(good + b"\x00" * 100, ids.shape)  # after IEND
    iend = good.rindex(b"IEND") - 4
    text = good[:iend] + png_chunk(b"tEXt", b"k\x00" + b"A" * 1000) + good[iend:]
    assert not is_canonical_mask_png(text, ids.shape)  # ancillary chunk
    assert not is_canonical_mask_png(_png(ids, z=zlib.compress(raw) + b"\x00" * 500), ids.shape)
    assert not is_canonical_mask_png(good[:iend] + png_chunk(b"IDAT", b"\x00" * 50) + good[iend:],
                                     ids.shape)  # an IDAT after the stream ended
    assert not is_canonical_mask_png(_png(ids, z=zlib.compress(raw[:-10])), ids.shape)  # short
    assert not is_canonical_mask_png(_png(ids), (ids.shape[0], ids.shape[1] + 1))  # other size
    assert not is_canonical_mask_png(_png(ids, colour=3), ids.shape)  # palette
    bad = bytearray(good)
    bad[40] ^= 0xFF  # inside the IDAT: its CRC no longer matches
    assert not is_canonical_mask_png(bytes(bad), ids.shape)
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", "x")
    b = io.BytesIO()
    Image.fromarray(ids).save(b, format="PNG", pnginfo=info)
    assert not is_canonical_mask_png(b.getvalue(), ids.shape)
    assert not is_canonical_mask_png(b"\x89PNG\r\n\x1a\n", ids.shape)


# ---- the fast decode of canonical uploads (issue 29: a save's CPU is mostly the decode) -----
def _filtered(ids: np.ndarray, filters: list[int]) -> bytes:
    """Rows filtered as a PNG encoder does: 0 None, 1 Sub, 2 Up (per row)."""
    out = []
    prev = np.zeros(ids.shape[1], np.uint8)
    for r in range(ids.shape[0]):
        row = ids[r]
        f = filters[r % len(filters)] if r else filters[0]
        if f == 0:
            fr = row
        elif f == 1:
            fr = (row.astype(np.int16) - np.concatenate([[0], row[:-1]])).astype(np.uint8)
        else:
            fr = (row.astype(np.int16) - prev).astype(np.uint8)
        out.append(bytes([f]) + fr.tobytes())
        prev = row
    return b"".join(out)


@pytest.mark.parametrize("filters", [[0, 2], [2], [0], [0, 2, 2, 0, 2], [0, 1, 2], [1]])
def test_fast_decode_equals_pil(ids, filters):
    """The editor's rows (row 0 None, the rest Up), runs of None / Up, and filters the fast
    path leaves to PIL (Sub) all decode to the image's ids, as PIL decodes them."""
    from occufly.io.masks import decode_mask_png
    from occufly.taxonomy import default_taxonomy

    tax = default_taxonomy()
    ids = ids.copy()
    ids[10:30, 5:40] = 7  # a constant area: Up turns it into zero runs
    png = _png(ids, z=zlib.compress(_filtered(ids, filters), 6))
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png))), ids)  # a valid PNG
    info: dict = {}
    got = decode_mask_png(png, tax, name="x", info=info)
    assert info["canonical"] is True
    assert got.dtype == np.uint8 and got.flags.c_contiguous and np.array_equal(got, ids)
    # a PIL-written PNG (its own filter choice) decodes the same, canonical or not
    b = io.BytesIO()
    Image.fromarray(ids).save(b, format="PNG", compress_level=9)
    assert np.array_equal(decode_mask_png(b.getvalue(), tax, name="x"), ids)


def test_fast_decode_refuses_what_it_must(ids):
    from occufly.errors import MaskError
    from occufly.io.masks import decode_mask_png
    from occufly.taxonomy import default_taxonomy

    tax = default_taxonomy()
    raw = bytearray(_filtered(ids, [0, 2]))
    raw[(ids.shape[1] + 1) * 3] = 9  # row 3's filter byte: no such PNG filter
    with pytest.raises(MaskError, match="x: damaged PNG"):
        decode_mask_png(_png(ids, z=zlib.compress(bytes(raw))), tax, name="x")
    # a stream that inflates past the rows (a bomb in miniature) is not canonical: the fast
    # path stops one byte past the rows; then it is refused on the first byte past what the
    # image can hold (issue 36: PIL read only the rows and the bomb was stored)
    big = zlib.compress(_filtered(ids, [0, 2]) + b"\x00" * 10_000_000)
    info: dict = {}
    with pytest.raises(MaskError, match="x: its image data inflates to more than"):
        decode_mask_png(_png(ids, z=big), tax, name="x", info=info)
    assert info["canonical"] is False
