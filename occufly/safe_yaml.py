"""YAML from files a user hands in: plain data only, no aliases (issue 36).

``yaml.safe_load`` builds no objects, but it expands aliases: 458 bytes of nested anchors
(the "billion laughs" of YAML) become gigabytes of lists, and every error message that
shows such a value grows with it. A document with an alias or anchor is refused before it
is composed.
"""

from __future__ import annotations

import yaml


class AliasRefused(yaml.YAMLError):
    pass


class _NoAliasLoader(yaml.SafeLoader):
    def compose_node(self, parent, index):  # noqa: ANN001, ANN201 - PyYAML's hook
        if self.check_event(yaml.AliasEvent):
            ev = self.peek_event()
            raise AliasRefused(f"YAML aliases (*{str(ev.anchor)[:40]}) are not accepted "
                               f"(line {ev.start_mark.line + 1}); write the values out")
        return super().compose_node(parent, index)


def load(text: str):  # noqa: ANN201 - whatever the document holds
    """The document's data (dicts, lists, scalars); :class:`AliasRefused` for an alias."""
    return yaml.load(text, Loader=_NoAliasLoader)  # noqa: S506 - a SafeLoader subclass


def short(value: object, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters: what an error message may show of a value
    a user wrote (never the whole of a huge one)."""
    r = repr(value) if not isinstance(value, (list, dict, tuple, set)) or len(value) < 50 \
        else f"<{type(value).__name__} of {len(value)} items>"
    return r if len(r) <= limit else r[:limit - 3] + "..."
