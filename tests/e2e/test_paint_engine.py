"""The painting engine's pure modules, run in Chromium against truth computed independently in
numpy: PNG encode/decode (all five PNG row filters), capsule brush rasterisation, polygon
fill, flood fill, tile-patch undo/redo and the painted-pixel counter."""

from __future__ import annotations

import base64
import struct
import zlib

import numpy as np
import pytest

from tests.e2e.conftest import png_ids

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def page(browser, live):
    ctx = browser.new_context()
    pg = ctx.new_page()
    errors = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(f"{live.base_url}/#/login")
    pg.wait_for_selector("#username")
    pg.evaluate("""async () => {
        window.png = await import('/js/core/png.js');
        window.mk = await import('/js/paint/mask.js');
        window.hist = await import('/js/paint/history.js');
        window.b64 = (a) => { let s = ''; for (let i = 0; i < a.length; i += 0x8000)
                                s += String.fromCharCode.apply(null, a.subarray(i, i + 0x8000));
                              return btoa(s); };
        window.unb64 = (s) => Uint8Array.from(atob(s), (c) => c.charCodeAt(0));
    }""")
    yield pg
    ctx.close()
    assert not errors, errors


def ids_from(page, expr: str, *args) -> np.ndarray:
    b64, w, h = page.evaluate(expr, *args) if args else page.evaluate(expr)
    return np.frombuffer(base64.b64decode(b64), np.uint8).reshape(h, w)


def png_with_filters(ids: np.ndarray, filters: list[int]) -> bytes:
    """An 8-bit greyscale PNG whose row y uses PNG filter filters[y % len(filters)]."""
    h, w = ids.shape
    a = ids.astype(np.int32)
    rows = []
    for y in range(h):
        f = filters[y % len(filters)]
        cur = a[y]
        up = a[y - 1] if y else np.zeros(w, np.int32)
        left = np.r_[0, cur[:-1]]
        ul = np.r_[0, up[:-1]]
        if f == 0:
            r = cur
        elif f == 1:
            r = cur - left
        elif f == 2:
            r = cur - up
        elif f == 3:
            r = cur - (left + up) // 2
        else:
            p = left + up - ul
            pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - ul)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, ul))
            r = cur - pred
        rows.append(bytes([f]) + (r & 255).astype(np.uint8).tobytes())

    from occufly.io.masks import png_chunk as chunk

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(b"".join(rows))) + chunk(b"IEND", b""))


def test_png_encoder_roundtrip_is_single_channel_and_exact(page):
    rng = np.random.default_rng(1)
    ids = rng.choice(np.array([0, 1, 6, 16, 17, 255], np.uint8), size=(37, 53))
    ids[5:30, 10:40] = 16
    out = page.evaluate("""async ([s, w, h]) => { const blob = await png.encodeGreyPng(unb64(s), w, h);
                           return b64(new Uint8Array(await blob.arrayBuffer())); }""",
                        [base64.b64encode(ids.tobytes()).decode(), 53, 37])
    data = base64.b64decode(out)
    assert np.array_equal(png_ids(data), ids)  # PIL checks the CRCs and says mode "L"
    # a large, mostly uniform mask compresses by orders of magnitude (not raw pixels)
    n = page.evaluate("""async () => { const w = 2000, h = 1500, a = new Uint8Array(w * h);
                         a.fill(6, 0, w * 500); for (let y = 600; y < 900; y++) a.fill(16, y * w + 300, y * w + 1700);
                         return (await png.encodeGreyPng(a, w, h)).size; }""")
    assert n < 2000 * 1500 / 100


@pytest.mark.parametrize("filters", [[0], [1], [2], [3], [4], [0, 1, 2, 3, 4]])
def test_png_decoder_handles_every_row_filter(page, filters):
    rng = np.random.default_rng(len(filters) * 7 + filters[0])
    ids = rng.integers(0, 256, size=(23, 41), dtype=np.uint8)
    ids[3:15, 5:30] = 33
    data = png_with_filters(ids, filters)
    got = ids_from(page, """async (s) => { const d = await png.decodeIdPng(new Blob([unb64(s)]));
                            return [b64(d.ids), d.width, d.height]; }""", base64.b64encode(data).decode())
    assert np.array_equal(got, ids)


def test_brush_capsule_matches_pixel_centre_geometry(page):
    W, H = 200, 120
    segs = [(10.3, 20.7, 150.9, 60.2, 7.5), (150.9, 60.2, 150.9, 60.2, 12.0), (190.0, 5.0, 230.0, 140.0, 20.0)]
    got = ids_from(page, """(segs) => { const m = new mk.MaskModel(200, 120, [{id: 8, name: 't', rgb: [1, 2, 3]}]);
        const p = new mk.TilePatch(m);
        for (const [ax, ay, bx, by, r] of segs) mk.stampSegment(m, p, ax, ay, bx, by, r, 8);
        window._m = m; return [b64(m.ids), 200, 120]; }""", segs)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    truth = np.zeros((H, W), bool)
    for ax, ay, bx, by, r in segs:
        d = np.array([bx - ax, by - ay])
        L2 = d @ d
        t = np.clip(((xx - ax) * d[0] + (yy - ay) * d[1]) / L2, 0, 1) if L2 else np.zeros_like(xx)
        truth |= (ax + t * d[0] - xx) ** 2 + (ay + t * d[1] - yy) ** 2 <= r * r
    assert np.array_equal(got == 8, truth)
    assert page.evaluate("() => window._m.painted") == int(truth.sum())


def test_polygon_fill_exact_area_and_triangle(page):
    got = ids_from(page, """() => { const m = new mk.MaskModel(100, 80, [{id: 3, name: 't', rgb: [1, 2, 3]}]);
        const p = new mk.TilePatch(m);
        mk.fillPolygon(m, p, [[10, 10], [50, 10], [50, 30], [10, 30]], 3);
        mk.fillPolygon(m, p, [[60, 5], [95, 40], [62, 75]], 3);
        return [b64(m.ids), 100, 80]; }""")
    assert (got[:, :55] == 3).sum() == 40 * 20  # the rectangle: exactly its area
    assert np.array_equal(np.argwhere(got[:, :55] == 3).min(0), [10, 10])
    yy, xx = np.mgrid[0:80, 0:100] + 0.5
    (x1, y1), (x2, y2), (x3, y3) = (60, 5), (95, 40), (62, 75)
    def side(ax, ay, bx, by):
        return (bx - ax) * (yy - ay) - (by - ay) * (xx - ax)
    s1, s2, s3 = side(x1, y1, x2, y2), side(x2, y2, x3, y3), side(x3, y3, x1, y1)
    inside = ((s1 > 0) & (s2 > 0) & (s3 > 0)) | ((s1 < 0) & (s2 < 0) & (s3 < 0))
    tri = got == 3
    tri[:, :55] = False
    # identical except possibly pixel centres lying exactly on an edge
    assert (tri != inside).sum() <= 2


def test_flood_fill_takes_the_similar_region_only(page):
    rng = np.random.default_rng(3)
    W, H = 90, 60
    rgb = np.zeros((H, W, 4), np.uint8)
    rgb[..., 3] = 255
    rgb[:, :40, :3] = 100 + rng.integers(-10, 11, (H, 40, 1))  # region A, +-10 grain
    rgb[:, 40:, :3] = 180  # region B
    rgb[20:30, 10:20, :3] = 180  # an island of B colour inside A (not connected to B)
    got = ids_from(page, """([s, w, h]) => { const m = new mk.MaskModel(w, h, [{id: 9, name: 't', rgb: [1, 2, 3]}]);
        const p = new mk.TilePatch(m);
        const r = mk.floodFill(m, p, unb64(s), new Uint8Array(w * h), 5, 5, 24, 9);
        window._cnt = r.count; return [b64(m.ids), w, h]; }""", [base64.b64encode(rgb.tobytes()).decode(), W, H])
    truth = np.zeros((H, W), bool)
    truth[:, :40] = True
    truth[20:30, 10:20] = False
    assert np.array_equal(got == 9, truth)
    assert page.evaluate("() => window._cnt") == truth.sum()


def test_tile_patch_undo_redo_restore_exact_bytes_and_store_only_touched_tiles(page):
    r = page.evaluate("""() => {
        const W = 1500, H = 1100, m = new mk.MaskModel(W, H, [{id: 1, name: 'a', rgb: [1, 2, 3]}, {id: 2, name: 'b', rgb: [3, 2, 1]}]);
        const h = new hist.History();
        let seed = 7; const rnd = () => (seed = (seed * 16807) % 2147483647) / 2147483647;
        const snaps = [m.ids.slice()];
        let x = W / 2, y = H / 2;  // each stroke starts where the previous ended (erasers overlap paint)
        for (let k = 0; k < 6; k++) {   // strokes of 30 samples each, classes 1/2 and the eraser
          const s = new hist.StrokeCommand(m, k % 3 === 2 ? 0 : 1 + (k % 2), 10 + 20 * rnd());
          for (let i = 0; i < 30; i++) { x += (rnd() - 0.5) * 80; y += (rnd() - 0.5) * 80; s.addSample(x, y, mk.stampSegment); }
          s.end(); h.push(s); snaps.push(m.ids.slice());
        }
        const eq = (a, b) => a.length === b.length && a.every((v, i) => v === b[i]);
        const count = () => m.ids.reduce((n, v) => n + (v !== 0), 0);
        const res = {steps: h.undos.length, ok: [], counts: [], maxPatch: 0};
        for (const c of h.undos) res.maxPatch = Math.max(res.maxPatch, c.patch.bytes);
        for (let k = 6; k > 0; k--) { h.undo(); res.ok.push(eq(m.ids, snaps[k - 1])); res.counts.push(m.painted === count()); }
        for (let k = 1; k <= 6; k++) { h.redo(); res.ok.push(eq(m.ids, snaps[k])); res.counts.push(m.painted === count()); }
        // a stroke that changes nothing (erasing empty pixels) is not an undo step
        const noop = new hist.StrokeCommand(m, 0, 5); noop.addSample(1, 1, mk.stampSegment); noop.addSample(3, 1, mk.stampSegment);
        noop.end(); const before = h.undos.length; if (!m.ids[W + 2]) h.push(noop); res.noopSkipped = h.undos.length === before;
        res.full = W * H; return res; }""")
    assert r["steps"] == 6  # each multi-sample stroke is one command
    assert all(r["ok"]) and all(r["counts"])
    assert r["maxPatch"] < r["full"]  # patches hold touched tiles, never the whole mask
    assert r["noopSkipped"]
