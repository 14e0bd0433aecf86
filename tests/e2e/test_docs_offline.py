"""Issue 26 defect 3: /docs renders Swagger UI with every request outside the app refused
(the network off) -- its assets come from the swagger-ui-bundle package, no CDN."""

from __future__ import annotations


def test_docs_render_offline(browser, live):
    ctx = browser.new_context()
    page = ctx.new_page()
    outside: list[str] = []

    def guard(route):
        if route.request.url.startswith(live.base_url):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", guard)
    try:
        page.goto(f"{live.base_url}/docs")
        page.wait_for_selector(".opblock", timeout=20_000)
        ops = page.locator(".opblock").count()
        assert ops > 20, ops  # the app's operations, read from /openapi.json
        assert page.locator(".opblock-summary-path", has_text="/api/health").count() == 1
        assert outside == []
    finally:
        ctx.close()
