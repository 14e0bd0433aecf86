"""The one escaping function for text that reaches viser's markdown (rendered as HTML).

viser renders markdown to HTML without sanitising it, so every value that comes from data
(frame stems, scene names, class names of a custom taxonomy, comments, error and job
messages) goes through ``md_text`` before it is put into markdown."""
from __future__ import annotations

import re

_HTML = {"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}
_MD = re.compile(r"([\\`*_{}\[\]()#+\-.!|~])")
_CTRL = re.compile(r"[\x00-\x1f\x7f]")


def md_text(value: object) -> str:
    """``value`` as literal text in viser markdown: HTML special characters as entities,
    markdown punctuation backslash-escaped, control characters (newlines included) as spaces."""
    s = _CTRL.sub(" ", str(value))
    s = _MD.sub(r"\\\1", s)
    return "".join(_HTML.get(ch, ch) for ch in s)
