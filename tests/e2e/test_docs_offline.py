"""Issue 26 defect 3: /docs renders Swagger UI with every request outside the app refused
(the network off) -- its assets come from the swagger-ui-bundle package, no CDN."""

from __future__ import annotations

import re

import pytest

from tests.e2e.conftest import REPO


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


@pytest.fixture(scope="module")
def small_site(tmp_path_factory):
    """The documentation site's theme and search (mkdocs.yml) over two of its guides, built
    by mkdocs itself (~2 s; the whole site is built by tests/test_docs.py)."""
    from mkdocs.commands.build import build
    from mkdocs.config import load_config

    root = tmp_path_factory.mktemp("docs_site")
    docs = root / "docs"
    docs.mkdir()
    for src, dst in (("admin.md", "index.md"), ("annotator.md", "annotator.md")):  # no images
        text = (REPO / "docs" / "guide" / src).read_text()
        (docs / dst).write_text(re.sub(r"!\[[^\]]*\]\([^)]*\)", "", text))
    cfg = load_config(config_file=str(REPO / "mkdocs.yml"), docs_dir=str(docs),
                      site_dir=str(root / "site"), strict=False, hooks=[], nav=None,
                      validation={})
    build(cfg)
    assert (root / "site" / "search" / "search_index.json").is_file()
    return root / "site"


def test_docs_site_search_works_served_by_the_app(browser, live, small_site):
    """Issue 40: the site's search (a web worker fetching search_index.json) works at /help/
    under the app's CSP (the theme's inline bootstrap scripts allowed by their hashes), with
    every request outside the app refused."""
    settings = live.app.state.ctx.settings
    before = settings.docs_site_dir
    settings.docs_site_dir = small_site
    ctx = browser.new_context()
    page = ctx.new_page()
    problems: list[str] = []
    page.on("console", lambda m: m.type == "error" and problems.append(m.text))
    page.on("pageerror", lambda e: problems.append(str(e)))
    outside: list[str] = []

    def guard(route):
        if route.request.url.startswith(live.base_url):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", guard)
    try:
        r = page.goto(f"{live.base_url}/help")
        assert r.status == 200 and page.url == f"{live.base_url}/help/"
        assert "script-src 'self' 'sha256-" in r.headers["content-security-policy"]
        page.click("input[data-md-component='search-query']")
        page.keyboard.type("annotator")  # the theme searches on key events
        hits = page.locator(".md-search-result__item")
        hits.first.wait_for(timeout=20_000)
        assert hits.count() >= 1
        text = page.locator(".md-search-result").inner_text()
        assert "annotator" in text.lower() or "Annotator" in text
        hits.first.locator("a").first.click()
        page.wait_for_load_state()
        assert page.url.startswith(f"{live.base_url}/help/")
        assert outside == [] and problems == [], (outside, problems)
        assert httpx_get(live, "/help/../../etc/passwd").status_code == 404
        assert httpx_get(live, "/help/no-such-page/").status_code == 404
    finally:
        settings.docs_site_dir = before
        ctx.close()


def httpx_get(live, path: str):  # noqa: ANN001, ANN201
    import httpx

    return httpx.get(f"{live.base_url}{path}")
