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
