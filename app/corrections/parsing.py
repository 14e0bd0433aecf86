"""The body of ``POST /api/scenes/{sid}/corrections``, read without a Python object per point
(issue 36: a correction naming every point was parsed whole -- json.loads, then pydantic's
list: +63 MB of server peak for 1 M ids, +621 MB for 10 M).

The body is a JSON object: ``to_class``, ``comment``, ``frame_id`` and the points as either

* ``point_ids``: a JSON array of non-negative integers, or
* ``point_ids_b64``: base64 of the ids packed as little-endian uint32 (4 bytes a point, about
  5.3 characters -- the compact form for big lassos).

Before anything is allocated per point, the ids are counted (the array's commas, the base64
length) against ``max_correction_points`` (413 beyond). A plain array of digits is converted
by numpy straight from the text (8 bytes a point); anything else in it (floats, strings,
nesting) falls back to the JSON parser, within the same count, and is refused with a 422.
The other fields are validated by :class:`app.corrections.schemas.EditMeta`.
"""

from __future__ import annotations

import base64
import binascii
import json
import re
from dataclasses import dataclass

import numpy as np
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from app.corrections.schemas import EditMeta
from app.errors import Invalid, PayloadTooLarge

#: characters besides the ids that a body may hold (its comment is at most 10,000)
OTHER_COMMAS = 10_100
_DIGITS = re.compile(r"[0-9\s,]*")
_WS = re.compile(r"\s*")


@dataclass
class ParsedEdit:
    point_ids: np.ndarray  # (K,) int64, as sent (sorted and checked by the service)
    to_class: int
    comment: str | None
    frame_id: int | None


def _too_many(n: int, cap: int, *, so_far: bool = False) -> PayloadTooLarge:
    told = f"more than {n} (counted so far)" if so_far else str(n)
    return PayloadTooLarge(
        f"point_ids: a correction names at most {cap} points "
        f"(OCCUFLY_MAX_CORRECTION_POINTS), this one {told}; split it into several corrections")


def _invalid(field: str, msg: str, kind: str = "value_error") -> RequestValidationError:
    return RequestValidationError([{"loc": ("body", field), "msg": msg, "type": kind}])


def _skip_ws(doc: str, pos: int) -> int:
    return _WS.match(doc, pos).end()


def _array_of_digits(doc: str, pos: int, cap: int) -> tuple[np.ndarray | None, int]:
    """The array starting at ``doc[pos] == '['`` as int64 when it holds only digits, commas
    and whitespace (``(None, pos)`` otherwise), and the position after it."""
    end = doc.find("]", pos)
    if end < 0:
        return None, pos
    inner = doc[pos + 1:end]
    if not _DIGITS.fullmatch(inner):
        return None, pos
    n = inner.count(",") + 1 if inner.strip() else 0
    if n > cap:
        raise _too_many(n, cap)
    if n == 0:
        return np.zeros(0, np.int64), end + 1
    try:  # in C, no object per id; an empty element or a missing comma is a ValueError
        ids = np.fromstring(inner, dtype=np.int64, sep=",")
    except ValueError:
        ids = None
    if ids is None or len(ids) != n:
        raise _invalid("point_ids", "expected a JSON array of point ids (integers)")
    return ids, end + 1


def _ids_from_list(value: object, cap: int) -> np.ndarray:
    if not isinstance(value, list):
        raise _invalid("point_ids", "expected a JSON array of point ids", "list_type")
    if len(value) > cap:
        raise _too_many(len(value), cap)
    if not all(type(v) is int for v in value):
        raise _invalid("point_ids", "every point id must be an integer", "int_type")
    try:
        return np.asarray(value, dtype=np.int64)
    except OverflowError:
        raise _invalid("point_ids", "a point id is out of range") from None


def _ids_from_b64(value: object, cap: int) -> np.ndarray:
    if not isinstance(value, str):
        raise _invalid("point_ids_b64", "expected a base64 string", "string_type")
    n = len(value) * 3 // 4 // 4
    if n > cap:
        raise _too_many(n, cap)
    try:
        raw = base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError):
        raise _invalid("point_ids_b64", "not valid base64") from None
    if len(raw) % 4:
        raise _invalid("point_ids_b64", f"{len(raw)} bytes: expected little-endian uint32 ids "
                                        "(a multiple of 4 bytes)")
    return np.frombuffer(raw, dtype="<u4").astype(np.int64)


def _walk_object(doc: str, cap: int) -> tuple[dict, np.ndarray | None]:
    """The top-level object's fields; ``point_ids`` converted by numpy when it is a plain
    array of digits (then absent from the dict)."""
    dec = json.JSONDecoder()
    pos = _skip_ws(doc, 0)
    if doc[pos:pos + 1] != "{":
        raise _invalid("body", "expected a JSON object", "dict_type")
    fields: dict = {}
    fast: np.ndarray | None = None
    pos = _skip_ws(doc, pos + 1)
    if doc[pos:pos + 1] == "}":
        return fields, fast
    while True:
        key, pos = dec.raw_decode(doc, pos)
        if not isinstance(key, str):
            raise ValueError("object key")
        pos = _skip_ws(doc, pos)
        if doc[pos:pos + 1] != ":":
            raise ValueError("':' expected")
        pos = _skip_ws(doc, pos + 1)
        ids = None
        if key == "point_ids" and doc[pos:pos + 1] == "[":
            ids, pos = _array_of_digits(doc, pos, cap)
        if ids is not None:
            fast = ids
            fields.pop("point_ids", None)
        else:
            fields[key], pos = dec.raw_decode(doc, pos)
            if key == "point_ids":
                fast = None
        pos = _skip_ws(doc, pos)
        if doc[pos:pos + 1] == ",":
            pos = _skip_ws(doc, pos + 1)
            continue
        if doc[pos:pos + 1] == "}" and not doc[pos + 1:].strip():
            return fields, fast
        raise ValueError("',' or '}' expected")


def body_limit(cap: int) -> int:
    """The most bytes a body naming ``cap`` points may need: 12 a point (a 10-digit id, its
    comma, a space) plus 64 KiB for the other fields."""
    return 12 * cap + (64 << 10)


async def read_body(chunks, cap: int) -> bytes:  # noqa: ANN001 - request.stream()
    """The body as it streams in, refused (413) as soon as it holds more commas than ``cap``
    points could need or more bytes than :func:`body_limit` -- a 10 M-id body is never held
    whole."""
    parts: list[bytes] = []
    size = commas = 0
    for_limit = body_limit(cap)
    async for chunk in chunks:
        size += len(chunk)
        commas += chunk.count(b",")
        if commas > cap + OTHER_COMMAS:
            raise _too_many(commas - OTHER_COMMAS, cap, so_far=True)
        if size > for_limit:
            raise PayloadTooLarge(
                f"point_ids: a correction names at most {cap} points "
                f"(OCCUFLY_MAX_CORRECTION_POINTS); its body may be at most {for_limit} bytes")
        parts.append(chunk)
    return b"".join(parts)


def parse_edit(body: bytes, cap: int) -> ParsedEdit:
    """The correction in ``body`` (see the module's docstring); 413 over ``cap`` points,
    422 for anything malformed."""
    # no more ids than commas: a body far over the cap is refused before it is decoded
    if body.count(b",") > cap + OTHER_COMMAS:
        raise _too_many(body.count(b",") - OTHER_COMMAS, cap, so_far=True)
    try:
        doc = body.decode("utf-8")
        fields, ids = _walk_object(doc, cap)
    except RequestValidationError:
        raise
    except (UnicodeDecodeError, ValueError, IndexError) as e:
        raise Invalid(f"the body is not a JSON object ({str(e)[:120]})") from None
    given = [k for k in ("point_ids", "point_ids_b64") if k in fields] + (
        ["point_ids"] if ids is not None else [])
    if len(given) != 1:
        raise _invalid("point_ids", "give the points as exactly one of point_ids (a JSON array) "
                                    "or point_ids_b64 (base64 of little-endian uint32)",
                       "missing" if not given else "value_error")
    if ids is None:
        ids = (_ids_from_list(fields.pop("point_ids"), cap) if "point_ids" in fields
               else _ids_from_b64(fields.pop("point_ids_b64"), cap))
    if len(ids) == 0:
        raise _invalid("point_ids", "a correction needs at least one point id", "too_short")
    if len(ids) > cap:
        raise _too_many(len(ids), cap)
    if ids.min() < 0:
        raise _invalid("point_ids", "point ids are non-negative integers")
    try:
        meta = EditMeta.model_validate(fields)
    except ValidationError as e:
        raise RequestValidationError([{**err, "loc": ("body", *err["loc"])}
                                      for err in e.errors()]) from None
    return ParsedEdit(point_ids=ids, to_class=meta.to_class, comment=meta.comment,
                      frame_id=meta.frame_id)
