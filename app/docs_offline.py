"""``/docs`` without a CDN (issue 26, defect 3): Swagger UI's assets served from the
``swagger-ui-bundle`` package under ``/docs-assets``, and a page with no inline script
(its initialiser is ``/docs-assets/occufly-init.js``), so a strict CSP (``script-src 'self'``)
allows it. Registered before the frontend's catch-all mount.

``/help/`` (issue 40): the documentation site (``mkdocs build``, into ``site/`` or
``OCCUFLY_DOCS_SITE_DIR``) served by the app, so its search works: the theme's search runs in a
web worker that fetches ``search/search_index.json``, which a page opened from ``file://`` may
not do. Each page gets the app's CSP with the sha256 of that page's own inline scripts (the
theme's small bootstrap scripts) added to ``script-src``; no other inline script runs. The
folder is looked up per request: a site built after the app started is served at once."""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path

import swagger_ui_bundle
from fastapi import FastAPI
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles

from app.security import DOCS_CSP

_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title} - API docs</title>
<link rel="stylesheet" href="/docs-assets/swagger-ui.css">
<link rel="icon" href="/docs-assets/favicon-32x32.png"></head>
<body><div id="swagger-ui"></div>
<script src="/docs-assets/swagger-ui-bundle.js"></script>
<script src="/docs-assets/occufly-init.js"></script>
</body></html>
"""

_INIT = """window.ui = SwaggerUIBundle({
  url: %r, dom_id: "#swagger-ui", deepLinking: true, layout: "BaseLayout",
  presets: [SwaggerUIBundle.presets.apis], showExtensions: true,
});
"""


def mount_docs(app: FastAPI) -> None:
    """``GET /docs`` and ``/docs-assets/*`` (the app must be built with ``docs_url=None``)."""
    page = _PAGE.format(title=app.title)
    init = _INIT % (app.openapi_url or "/openapi.json")

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return HTMLResponse(page)

    @app.get("/docs-assets/occufly-init.js", include_in_schema=False)
    def docs_init() -> Response:
        return Response(init, media_type="application/javascript")

    app.mount("/docs-assets", StaticFiles(directory=swagger_ui_bundle.swagger_ui_path),
              name="docs-assets")


SITE_PREFIX = "/help"
_INLINE_SCRIPT = re.compile(rb"<script(?![^>]*\bsrc=)(?![^>]*\btype=\"application/json\")[^>]*>"
                            rb"(.*?)</script>", re.S)


def site_csp(html: bytes) -> str:
    """The docs CSP for one page: ``script-src 'self'`` plus the sha256 of each of its inline
    scripts (JSON data blocks are not scripts and need none)."""
    hashes = sorted({"'sha256-" + base64.b64encode(hashlib.sha256(m.group(1)).digest()).decode()
                     + "'" for m in _INLINE_SCRIPT.finditer(html)})
    return DOCS_CSP.replace("script-src 'self'", " ".join(["script-src 'self'", *hashes]))


def _site_file(site: Path, path: str) -> Path | None:
    """The file of the built site a URL path names (a folder: its index.html); None when it
    is not there or not inside the site."""
    root = site.resolve()
    target = (root / path.lstrip("/")).resolve()
    if not target.is_relative_to(root):
        return None
    if target.is_dir():
        target = target / "index.html"
    return target if target.is_file() else None


def mount_site(app: FastAPI, get_site_dir) -> None:  # noqa: ANN001
    """``GET /help/...``: the built documentation site of ``get_site_dir()`` (public, like the
    login page: it holds no data)."""

    @app.get(SITE_PREFIX, include_in_schema=False)
    def site_root() -> Response:
        return RedirectResponse(f"{SITE_PREFIX}/", status_code=307)

    @app.get(SITE_PREFIX + "/{path:path}", include_in_schema=False)
    def site_page(path: str) -> Response:
        site = Path(get_site_dir())
        if not (site / "index.html").is_file():
            return JSONResponse({"detail": f"the documentation site is not built: run "
                                           f"'mkdocs build -d {site}' (OCCUFLY_DOCS_SITE_DIR)"},
                                status_code=404)
        f = _site_file(site, path)
        if f is None:
            return JSONResponse({"detail": f"{SITE_PREFIX}/{path}: no such page"}, 404)
        if f.suffix == ".html":
            html = f.read_bytes()
            return Response(html, media_type="text/html; charset=utf-8",
                            headers={"content-security-policy": site_csp(html)})
        return FileResponse(f)
