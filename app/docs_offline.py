"""``/docs`` without a CDN (issue 26, defect 3): Swagger UI's assets served from the
``swagger-ui-bundle`` package under ``/docs-assets``, and a page with no inline script
(its initialiser is ``/docs-assets/occufly-init.js``), so a strict CSP (``script-src 'self'``)
allows it. Registered before the frontend's catch-all mount."""

from __future__ import annotations

import swagger_ui_bundle
from fastapi import FastAPI
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

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
