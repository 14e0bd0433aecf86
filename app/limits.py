"""Bounded input types for the API schemas (query, path, header and body fields alike).

Every integer a request can carry fits the databases' 32-bit ``INTEGER`` (PostgreSQL raises
``NumericValueOutOfRange`` beyond it, SQLite's driver ``OverflowError`` beyond 64 bits), and
every string has a length bound and holds no NUL byte (PostgreSQL text cannot store one) nor
other control characters (except tab/newline in free text). A value outside these bounds is a
422 naming the field, never a 500.
"""

from __future__ import annotations

import re
from typing import Annotated

from fastapi import Path
from pydantic import AfterValidator, Field

INT32_MAX = 2**31 - 1

_CONTROL_LINE = re.compile(r"[\x00-\x1f\x7f]")
_CONTROL_TEXT = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")


def no_control_line(value: str) -> str:
    """A one-line string: no NUL or other control characters."""
    if _CONTROL_LINE.search(value):
        raise ValueError("must not contain NUL bytes or control characters")
    return value


def no_control_text(value: str) -> str:
    """Free text: tab, newline and carriage return allowed, other control characters not."""
    if _CONTROL_TEXT.search(value):
        raise ValueError("must not contain NUL bytes or control characters")
    return value


Id = Annotated[int, Field(ge=1, le=INT32_MAX)]
"""A database row id (1 .. 2**31-1)."""

IdPath = Annotated[int, Path(ge=1, le=INT32_MAX)]
"""A row id in the URL path."""

Count = Annotated[int, Field(ge=0, le=INT32_MAX)]
"""A non-negative index or count that fits a 32-bit INTEGER (frame index, point id, pixel)."""


def line(max_length: int, min_length: int = 0):  # noqa: ANN201 - an Annotated alias
    """A one-line string of at most ``max_length`` characters without control characters."""
    return Annotated[str, Field(min_length=min_length, max_length=max_length),
                     AfterValidator(no_control_line)]


def text(max_length: int, min_length: int = 0):  # noqa: ANN201
    """Free text (newlines allowed) of at most ``max_length`` characters."""
    return Annotated[str, Field(min_length=min_length, max_length=max_length),
                     AfterValidator(no_control_text)]
