"""The documentation site builds with ``mkdocs build --strict`` (no broken internal link or
anchor, no page left out of the navigation) and every local link and image of the built site
resolves; the generated reference pages hold every CLI command and every API route."""

from __future__ import annotations

import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

REPO = Path(__file__).resolve().parent.parent


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []

    def handle_starttag(self, tag, attrs):  # noqa: ANN001
        for k, v in attrs:
            if k in ("href", "src") and v:
                self.links.append(v)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=600,
                       env={"NO_MKDOCS_2_WARNING": "1", "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, f"mkdocs build --strict failed:\n{r.stdout[-4000:]}\n{r.stderr[-4000:]}"
    return out


def test_every_local_link_resolves(site: Path):
    broken = []
    pages = list(site.rglob("*.html"))
    assert len(pages) > 15
    for page in pages:
        p = _Links()
        p.feed(page.read_text(errors="replace"))
        for link in p.links:
            u = urlsplit(link)
            if u.scheme or link.startswith(("#", "//", "mailto:", "data:")):
                continue
            path = unquote(u.path)
            # the 404 page links from the site root (it is served at any depth)
            target = (site / path.lstrip("/") if path.startswith("/") else page.parent / path).resolve()
            if target.is_dir():
                target = target / "index.html"
            if not target.exists():
                broken.append(f"{page.relative_to(site)} -> {link}")
    assert broken == [], "broken links:\n" + "\n".join(broken[:50])


def test_no_cdn_at_run_time(site: Path):
    """The site must work offline: no script, style or font from another host."""
    remote = []
    for page in site.rglob("*.html"):
        for m in re.finditer(r'<(?:script|link)[^>]+(?:src|href)="(https?:)?//[^"]+"',
                             page.read_text(errors="replace")):
            remote.append(f"{page.relative_to(site)}: {m.group(0)[:120]}")
    assert remote == []


def test_generated_references_are_complete(site: Path):
    from app.access import table
    from occufly.cli import build_parser

    cli = (site / "reference" / "cli" / "index.html").read_text()
    sub = next(a for a in build_parser()._actions if a.dest == "command")  # noqa: SLF001
    missing = [name for name in sub.choices if f"occufly {name}</code>" not in cli]
    assert missing == []
    api = (site / "reference" / "api" / "index.html").read_text()
    missing = [key for key in table() if key.startswith(("GET /api", "POST /api", "PUT /api",
                                                         "DELETE /api", "PATCH /api"))
               and key.replace("{", "").replace("}", "").split(" ", 1)[1]
               not in api.replace("{", "").replace("}", "")]
    assert missing == []
