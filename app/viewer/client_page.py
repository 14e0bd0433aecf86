"""viser's browser client re-packaged so the viewer runs under a strict Content-Security-Policy.

viser (1.1) ships its client as ONE ``index.html``: an inline ``<script>`` carries the app as a
zstd frame (base-88 text in ``data-p``) plus a gzip'd zstd WebAssembly decoder; at load time it
decodes both and injects the CSS as an inline ``<style>`` and the app as an inline
``<script type="module">`` (``textContent``). Under ``script-src 'self'`` none of that runs.

:func:`client_assets` does the unpacking once, on the server, from the installed viser's own
file (nothing downloaded): the page becomes plain HTML referencing same-origin files

- ``client.css`` -- the app's stylesheet,
- ``zstd.wasm`` -- viser's zstd decoder (the app decodes its websocket messages with it),
- ``loader.js`` -- ours: compiles ``zstd.wasm``, publishes it as
  ``globalThis.__viserZstdWasm`` (what viser's loader does) and imports ``client.js``,
- ``client.js`` -- the app itself, unchanged.

Not allowed, deliberately: ``'unsafe-eval'``. viser builds two things from strings with
``Function()``: its Gaussian-splat sorter (emscripten embind glue, compiled at load; its
refusal is reported as a console warning by ``loader.js``) and the server's
``RunJavascriptMessage`` (arbitrary script sent by the Python side, which OccuFly never uses).
Both stay refused: splats are unavailable in OccuFly's viewer, nothing else is affected.

What the viewer still needs beyond the app pages' policy (:data:`app.security.VIEWER_CSP`),
and why: ``'wasm-unsafe-eval'`` (compiling the zstd decoder and the mesh decoders it inlines;
it allows WebAssembly, not JavaScript ``eval``), ``worker-src blob:`` (viser builds its
websocket and decoder workers from inlined sources as ``blob:`` URLs), ``style-src
'unsafe-inline'`` (its UI library, Mantine/emotion, injects ``<style>`` elements) and
``data:`` for images, fonts and ``connect-src`` (inlined icons, fonts and WebAssembly). No
inline or ``eval``'d *script* runs.

If a viser upgrade changes the single-file layout, :class:`ClientLayoutError` names what was
not found; the viewer page then answers 502 rather than falling back to the inline page.
"""

from __future__ import annotations

import gzip
import hashlib
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import zstandard

ASSET_DIR = "__occufly"  # /viewer/__occufly/<name>
_B88 = "".join(chr(c) for c in range(0x21, 0x7F) if chr(c) not in "\"&<>'`")
_LUT = {ch: i for i, ch in enumerate(_B88)}
_MAX_CLIENT_BYTES = 64 << 20  # the decompressed client (2.7 MB for viser 1.1.1)

_LOADER = """// OccuFly: viser's zstd decoder is compiled here (not by an inline script) so the
// viewer runs under script-src 'self' 'wasm-unsafe-eval' (app/viewer/client_page.py)
// viser compiles its Gaussian-splat sorter at load with emscripten's embind, which builds
// functions from strings (eval); the policy refuses that, so splats (never sent by OccuFly)
// cannot be shown. That one refusal is reported as a warning, not an uncaught error.
addEventListener("unhandledrejection", (e) => {
  if (e.reason instanceof EvalError) {
    e.preventDefault();
    console.warn("3D viewer: viser's splat sorter needs eval, refused by the CSP (splats unavailable)");
  }
});
const wasm = await WebAssembly.compileStreaming(fetch(new URL("./zstd.wasm?v=%(tag)s", import.meta.url)));
globalThis.__viserZstdWasm = wasm;
await import("./client.js?v=%(tag)s");  // relative to this module, not the page
"""


class ClientLayoutError(RuntimeError):
    """The installed viser's client page is not the single-file layout this module unpacks."""


@dataclass(frozen=True)
class ClientAssets:
    page: bytes
    files: dict[str, tuple[bytes, str]]  # name -> (body, content type)
    tag: str


def b88decode(text: str) -> bytes:
    """viser's base-88 (4 bytes -> 5 characters; a final group of k characters: k-1 bytes)."""
    try:
        vals = [_LUT[ch] for ch in text]
    except KeyError as e:
        raise ClientLayoutError(f"viser client: character {e} is not base-88") from None
    out = bytearray()
    n = len(vals) // 5
    for g in range(n):
        v = 0
        for x in vals[g * 5:g * 5 + 5]:
            v = v * 88 + x
        out += v.to_bytes(4, "big")
    r = len(vals) % 5
    if r:
        v = 0
        for x in vals[n * 5:]:
            v = v * 88 + x
        out += v.to_bytes(r - 1, "big")
    return bytes(out)


def viser_index() -> Path:
    import viser  # the viewer's one dependency, imported where it is used (the app runs without it)

    return Path(viser.__file__).parent / "client" / "build" / "index.html"


def unpack(html: str) -> ClientAssets:
    """The CSP-clean page and its files from viser's single-file ``index.html``."""
    m = re.search(r"<script\s+([^>]*)>(.*?)</script>", html, flags=re.S)
    if m is None:
        raise ClientLayoutError("viser client: no inline loader <script> in index.html")
    attrs = dict(re.findall(r'data-(\w+)="([^"]*)"', m.group(1)))
    if not {"p", "ss", "cs"} <= set(attrs):
        raise ClientLayoutError(f"viser client: loader attributes data-p/ss/cs not found "
                                f"(got {sorted(attrs)})")
    w = re.search(r'gzWasm="([^"]*)"', m.group(2))
    if w is None:
        raise ClientLayoutError("viser client: the loader's gzWasm decoder was not found")
    try:
        ss, cs = int(attrs["ss"]), int(attrs["cs"])
    except ValueError:
        raise ClientLayoutError("viser client: data-ss/data-cs are not byte counts") from None
    if not 0 <= ss + cs <= _MAX_CLIENT_BYTES or cs == 0:
        raise ClientLayoutError(f"viser client: implausible sizes ss={ss} cs={cs}")
    raw = zstandard.ZstdDecompressor().decompress(b88decode(attrs["p"]), max_output_size=ss + cs)
    if len(raw) != ss + cs:
        raise ClientLayoutError(f"viser client: {len(raw)} bytes decoded, {ss + cs} expected")
    wasm = gzip.decompress(b88decode(w.group(1).replace("\\\\", "\\")))  # a JS string
    if wasm[:4] != b"\0asm":
        raise ClientLayoutError("viser client: the zstd decoder is not WebAssembly")
    css, js = raw[:ss], raw[ss:]
    tag = hashlib.sha256(raw + wasm).hexdigest()[:12]
    head = html[:m.start()]
    tail = html[m.end():]
    refs = (f'<link rel="stylesheet" href="./{ASSET_DIR}/client.css?v={tag}">\n'
            f'    <script type="module" src="./{ASSET_DIR}/loader.js?v={tag}"></script>')
    page = (head + refs + tail).encode()
    if b"<script>" in page or re.search(rb"<script(?![^>]*\ssrc=)[^>]*>", page):
        raise ClientLayoutError("viser client: an inline <script> is left in the page")
    files = {
        "client.css": (css, "text/css; charset=utf-8"),
        "client.js": (js, "text/javascript; charset=utf-8"),
        "zstd.wasm": (wasm, "application/wasm"),
        "loader.js": ((_LOADER % {"dir": ASSET_DIR, "tag": tag}).encode(),
                      "text/javascript; charset=utf-8"),
    }
    return ClientAssets(page=page, files=files, tag=tag)


_lock = threading.Lock()
_cached: ClientAssets | None = None


def client_assets() -> ClientAssets:
    """:func:`unpack` of the installed viser's page, once per process."""
    global _cached
    with _lock:
        if _cached is None:
            _cached = unpack(viser_index().read_text(encoding="utf-8"))
        return _cached
