"""Annotation masks: single-channel PNGs of raw class ids.

A mask holds one raw class id per pixel: 0 = unpainted (casts no vote), 255 = ignore, any other
value must be a class id of the scene's taxonomy. It has the frame's image size or an exact
integer downscale of it (``width / s`` and ``height / s`` for the same integer ``s``); the
lifting maps a point's pixel ``uv`` to ``floor(uv / s)``.

Accepted encodings: single-channel PNG (mode L, P -- palette *indices* are the ids -- or
16-bit I;16/I with every value <= 255) and RGB/RGBA PNGs whose colours are all in the
taxonomy's colour table (black = unpainted; in RGBA, fully transparent = unpainted).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from occufly.errors import MaskError
from occufly.fsutil import atomic_write_bytes
from occufly.scene import Frame
from occufly.taxonomy import EMPTY, INVALID, Taxonomy

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def mask_scale(shape: tuple[int, int], frame: Frame, *, name: str = "<mask>") -> int:
    """Integer downscale ``s`` of a (h, w) mask for ``frame`` (1 = full resolution).

    Raises MaskError naming ``name`` when the size is neither the image size nor W/s x H/s.
    """
    h, w = int(shape[0]), int(shape[1])
    W, H = frame.camera.width, frame.camera.height
    if w > 0 and h > 0 and W % w == 0 and H % h == 0 and W // w == H // h:
        return W // w
    raise MaskError(
        f"{name}: mask is {w}x{h} pixels but frame {frame.name!r} is {W}x{H}; expected "
        f"{W}x{H} or an exact integer downscale (W/s x H/s)"
    )


def validate_ids(mask: np.ndarray, taxonomy: Taxonomy, *, name: str = "<mask>") -> None:
    """Raise MaskError if ``mask`` holds ids that are neither 0, 255 nor taxonomy classes."""
    ok = taxonomy.valid_lut().copy()
    ok[EMPTY] = ok[INVALID] = True
    present = np.flatnonzero(np.bincount(np.asarray(mask, dtype=np.uint8).ravel(), minlength=256))
    bad = present[~ok[present]]
    if len(bad):
        shown = ", ".join(str(int(b)) for b in bad[:10]) + (" ..." if len(bad) > 10 else "")
        raise MaskError(
            f"{name}: class id(s) {shown} are not in taxonomy {taxonomy.name!r} "
            f"(allowed: 0 = unpainted, 255 = ignore, {', '.join(str(i) for i in taxonomy.ids)})"
        )


def _rgb_to_ids(rgb: np.ndarray, alpha: np.ndarray | None, taxonomy: Taxonomy, name: str) -> np.ndarray:
    """(h, w, 3) uint8 colours -> (h, w) uint8 raw ids through the taxonomy's colour table."""
    code = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    table_codes = [0]
    table_ids = [EMPTY]
    for c in taxonomy.classes:
        table_codes.append((c.rgb[0] << 16) | (c.rgb[1] << 8) | c.rgb[2])
        table_ids.append(c.id)
    table_codes_a = np.asarray(table_codes, dtype=np.uint32)
    order = np.argsort(table_codes_a, kind="stable")
    sorted_codes = table_codes_a[order]
    sorted_ids = np.asarray(table_ids, dtype=np.uint8)[order]
    flat = code.ravel()
    transparent = np.zeros(flat.shape, bool) if alpha is None else (alpha.ravel() == 0)
    pos = np.clip(np.searchsorted(sorted_codes, flat), 0, len(sorted_codes) - 1)
    found = (sorted_codes[pos] == flat) | transparent
    if not found.all():
        bad = np.unique(flat[~found])
        shown = ", ".join(f"({b >> 16},{(b >> 8) & 255},{b & 255})" for b in bad[:8].tolist())
        raise MaskError(
            f"{name}: {int((~found).sum())} pixel(s) have colours not in taxonomy "
            f"{taxonomy.name!r}: {shown}{' ...' if len(bad) > 8 else ''}; expected a "
            f"single-channel PNG of raw ids or the taxonomy's class colours"
        )
    out = sorted_ids[pos]
    out[transparent] = EMPTY
    return out.reshape(code.shape)


def decode_mask_png(src: str | Path | bytes, taxonomy: Taxonomy, *, name: str) -> np.ndarray:
    """Decode a mask PNG into (h, w) uint8 raw ids without checking any frame size."""
    from PIL import Image, UnidentifiedImageError

    if isinstance(src, (bytes, bytearray, memoryview)):
        data = bytes(src)
    else:
        try:
            data = Path(src).read_bytes()
        except OSError as e:
            raise MaskError(f"{name}: cannot read mask ({e.strerror})") from None
    if not data.startswith(PNG_SIGNATURE):
        raise MaskError(f"{name}: not a PNG file; expected a single-channel PNG of raw class ids")
    try:
        img = Image.open(io.BytesIO(data))
        img.load()
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise MaskError(f"{name}: damaged PNG ({e})") from None
    mode = img.mode
    if mode in ("L", "P"):
        ids = np.asarray(img, dtype=np.uint8)
    elif mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img)
        if arr.size and (int(arr.max()) > 255 or int(arr.min()) < 0):
            raise MaskError(
                f"{name}: 16-bit mask holds values up to {int(arr.max())}; raw class ids must be "
                f"0..255"
            )
        ids = arr.astype(np.uint8)
    elif mode == "LA":
        arr = np.asarray(img)
        ids = np.where(arr[..., 1] == 0, EMPTY, arr[..., 0]).astype(np.uint8)
    elif mode in ("RGB", "RGBA"):
        arr = np.asarray(img)
        alpha = arr[..., 3] if mode == "RGBA" else None
        ids = _rgb_to_ids(arr[..., :3], alpha, taxonomy, name)
    else:
        raise MaskError(
            f"{name}: PNG mode {mode!r} is not supported; expected single-channel (L/P/I;16) raw "
            f"ids or RGB class colours"
        )
    if ids.ndim != 2:
        raise MaskError(f"{name}: expected a 2-D image, got shape {ids.shape}")
    return np.ascontiguousarray(ids)


def read_mask(
    src: str | Path | bytes, frame: Frame, taxonomy: Taxonomy, *, name: str | None = None
) -> np.ndarray:
    """Decode and validate a mask PNG for ``frame``.

    src: a file path or the PNG bytes (an upload). Returns (h, w) uint8 raw ids, 0 = unpainted,
    255 = ignore, at the frame's size or an integer downscale of it. Raises
    :class:`occufly.errors.MaskError` naming ``name`` (default: the path, or ``<upload>``) and
    what was expected (size, format, offending ids / colours).
    """
    if name is None:
        name = "<upload>" if isinstance(src, (bytes, bytearray, memoryview)) else str(src)
    ids = decode_mask_png(src, taxonomy, name=name)
    mask_scale(ids.shape, frame, name=name)
    validate_ids(ids, taxonomy, name=name)
    return ids


def encode_mask_png(mask: np.ndarray) -> bytes:
    """(H, W) uint8 raw ids -> single-channel (mode L) PNG bytes."""
    from PIL import Image

    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be (H, W), got shape {mask.shape}")
    if mask.dtype != np.uint8:
        if mask.size and (mask.min() < 0 or mask.max() > 255):
            raise ValueError("mask values must be 0..255")
        mask = mask.astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(mask)).save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    """Atomically write (H, W) uint8 raw ids as a single-channel PNG."""
    atomic_write_bytes(path, encode_mask_png(mask))
