"""Issue 24, finding 2: every value interpolated into viser markdown (rendered as raw HTML by
the viser client, ``rehypeRawDom``: no sanitising) goes through ``app.viewer.markdown_escape.md_text``.

A static check over app/viewer/*.py: each f-string that is assigned to a markdown handle's
``.content`` or passed to ``add_markdown`` may interpolate only ``md_text(...)``, a number
(a format spec such as ``:,``, ``len(...)``, an id) or a constant of the module. Notifications,
dropdown options and labels are rendered as text by the client and are not markdown."""
from __future__ import annotations

import ast
from pathlib import Path

VIEWER = Path(__file__).resolve().parents[2] / "app" / "viewer"
# interpolations known to be numbers or fixed words (name -> why)
SAFE_NAMES = {
    "n": "a count", "k": "a count", "lifted": "one of two fixed phrases",
    "rows": "joined from md_text(class name) pieces (corrections_panel.update_counts)",
}
SAFE_KEYS = {"id", "n_points"}  # edit["id"], edit["n_points"]: integers from the database


def _safe(v: ast.FormattedValue) -> bool:
    e = v.value
    if v.format_spec is not None:  # :,  :.1f ... -- a number
        return True
    if isinstance(e, ast.Call):
        f = e.func
        name = f.id if isinstance(f, ast.Name) else getattr(f, "attr", "")
        return name in ("md_text", "len", "int", "float", "round")
    if isinstance(e, ast.Name):
        return e.id in SAFE_NAMES
    if isinstance(e, ast.IfExp):  # 'undone' if ... else 'redone'
        return isinstance(e.body, ast.Constant) and isinstance(e.orelse, ast.Constant)
    if isinstance(e, ast.Subscript) and isinstance(e.slice, ast.Constant):
        return e.slice.value in SAFE_KEYS
    if isinstance(e, ast.Attribute):  # e.g. ticket.frame, scene.name: data
        return False
    return False


def _markdown_fstrings(tree: ast.AST):
    for node in ast.walk(tree):
        target_val = None
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Attribute) and t.attr == "content" for t in node.targets):
            target_val = node.value
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == "add_markdown" and node.args):
            target_val = node.args[0]
        if target_val is None:
            continue
        for sub in ast.walk(target_val):
            if isinstance(sub, ast.JoinedStr):
                yield node.lineno, sub


def test_every_markdown_interpolation_is_escaped():
    unsafe = []
    checked = 0
    for path in sorted(VIEWER.glob("*.py")):
        tree = ast.parse(path.read_text())
        for lineno, js in _markdown_fstrings(tree):
            for v in js.values:
                if isinstance(v, ast.FormattedValue):
                    checked += 1
                    if not _safe(v):
                        unsafe.append(f"{path.name}:{lineno}: {ast.unparse(v.value)}")
    assert checked >= 10, checked
    assert not unsafe, "interpolated into viser markdown without md_text:\n" + "\n".join(unsafe)


def test_md_text_neutralises_hostile_names():
    from app.viewer.markdown_escape import md_text

    for hostile in ['<iframe srcdoc="<script>parent.fetch(1)</script>">.png',
                    "<img src=x onerror=alert(1)>", "[x](javascript:alert(1))",
                    "`code` **b** _i_ <b>", "a\nb\r\n# h", "&lt;already&gt;"]:
        out = md_text(hostile)
        assert "<" not in out and ">" not in out and "\n" not in out, out
        assert "](" not in out
