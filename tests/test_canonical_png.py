"""Issue 29 (save p95): an upload that is already the canonical 8-bit class-id PNG is stored
as it is; everything issue 24's canonical storage strips is still detected and re-encoded."""
from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image, PngImagePlugin

from occufly.io.masks import encode_mask_png, is_canonical_mask_png


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png(ids: np.ndarray, *, z: bytes | None = None, extra: bytes = b"", idat_split: int = 0,
         depth: int = 8, colour: int = 0) -> bytes:
    h, w = ids.shape
    raw = b"".join(b"\x00" + ids[r].tobytes() for r in range(h))
    z = zlib.compress(raw, 6) if z is None else z
    parts = [z] if not idat_split else [z[i:i + idat_split] for i in range(0, len(z), idat_split)]
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0))
            + b"".join(_chunk(b"IDAT", p) for p in parts) + _chunk(b"IEND", b"") + extra)


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
    text = good[:iend] + _chunk(b"tEXt", b"k\x00" + b"A" * 1000) + good[iend:]
    assert not is_canonical_mask_png(text, ids.shape)  # ancillary chunk
    assert not is_canonical_mask_png(_png(ids, z=zlib.compress(raw) + b"\x00" * 500), ids.shape)
    assert not is_canonical_mask_png(good[:iend] + _chunk(b"IDAT", b"\x00" * 50) + good[iend:],
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
