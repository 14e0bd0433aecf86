"""Errors a user can cause. Each names the file or field and what was expected.

The CLI prints them as one line and exits 2; the web app maps them to HTTP 4xx. Anything that
is *not* an :class:`OccuflyError` is a bug.
"""

from __future__ import annotations


class OccuflyError(Exception):
    """Base class for every error caused by user input (files, arguments, requests)."""


class TaxonomyError(OccuflyError):
    """A taxonomy file or class id is invalid."""


class InputFormatError(OccuflyError):
    """An input file is missing, unreadable or not in the expected format."""


class WorkspaceError(OccuflyError):
    """A scene workspace is missing, incomplete or would be overwritten."""


class MaskError(OccuflyError):
    """A mask image does not fit its frame or taxonomy."""


class UnsafePathError(InputFormatError):
    """A path read from a project file (scene.json, a camera XML, a symlink) leads outside
    the folders imports may read (the import roots and the data dir)."""


# ---- names that end up in pages -----------------------------------------------------------
#: refused in frame, class and taxonomy names: C0/C1 control characters, the Unicode bidi
#: overrides/isolates (they reorder what a reviewer reads) and the HTML markup characters
#: ``<``, ``>``, ``"`` and the backtick. Everything that reaches a page is escaped as well;
#: this refusal keeps such names out of exports, logs and other tools (docs/security.md).
_BAD_NAME_CHARS = frozenset(
    [chr(c) for c in range(0x20)] + [chr(c) for c in range(0x7F, 0xA0)]
    + ["\u202a", "\u202b", "\u202c", "\u202d", "\u202e", "\u2066", "\u2067", "\u2068",
       "\u2069", "\u200e", "\u200f", "\u061c", "<", ">", '"', "`"])
MAX_NAME_LENGTH = 255


def check_name(name: object, what: str) -> str:
    """``name`` if it is a usable display name (1..255 characters, none of the refused ones
    above); else an InputFormatError naming ``what`` and the first refused character."""
    if not isinstance(name, str) or not name:
        raise InputFormatError(f"{what}: expected a non-empty name, got {name!r:.80}")
    if len(name) > MAX_NAME_LENGTH:
        raise InputFormatError(f"{what}: name {name[:40]!r}... is longer than {MAX_NAME_LENGTH} "
                               "characters")
    for ch in name:
        if ch in _BAD_NAME_CHARS:
            raise InputFormatError(
                f"{what}: name {name[:80]!r} contains {ch!r} (U+{ord(ch):04X}); control "
                "characters, bidi controls and the markup characters < > \" ` are not allowed "
                "in names")
    return name
