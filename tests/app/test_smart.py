"""Server-side smart tools: intelligent scissors (and GrabCut with scribbles) on a frame whose
photo has a known edge: a bright rectangle on a dark, noisy background."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from app.annotations.smart import grabcut, scissors
from tests.app.conftest import H, W, write_tiny_workspace

RECT = (16, 12, 44, 36)  # x0, y0, x1, y1 (exclusive) of the bright rectangle


def edge_photo(w: int = W, h: int = H, rect=RECT, seed: int = 0) -> np.ndarray:  # noqa: ANN001
    rng = np.random.default_rng(seed)
    img = rng.integers(20, 50, (h, w, 3)).astype(np.uint8)
    x0, y0, x1, y1 = rect
    img[y0:y1, x0:x1] = rng.integers(200, 230, (y1 - y0, x1 - x0, 3)).astype(np.uint8)
    return img


def border_distance(path: np.ndarray, rect=RECT) -> np.ndarray:  # noqa: ANN001
    """Distance of each (x, y) to the rectangle's border (its outermost pixel ring)."""
    x0, y0, x1, y1 = rect
    x, y = path[:, 0].astype(float), path[:, 1].astype(float)
    inside = (x >= x0) & (x <= x1 - 1) & (y >= y0) & (y <= y1 - 1)
    din = np.minimum.reduce([x - x0, x1 - 1 - x, y - y0, y1 - 1 - y])
    dx = np.maximum.reduce([x0 - x, np.zeros_like(x), x - (x1 - 1)])
    dy = np.maximum.reduce([y0 - y, np.zeros_like(y), y - (y1 - 1)])
    return np.where(inside, din, np.hypot(dx, dy))


def densify(path: np.ndarray) -> np.ndarray:
    out = [path[0].astype(float)]
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(1, int(np.ceil(np.abs(b - a).max())))
        out.extend(a + (b - a) * t for t in np.arange(1, n + 1) / n)
    return np.array(out)


@pytest.fixture
def edge_world(env):
    hdr = {r: env.bearer(r) for r in ("admin", "reviewer", "annotator", "annotator2")}
    src = env.import_root / "tiny_src"
    write_tiny_workspace(src)
    for p in (src / "images").iterdir():
        Image.fromarray(edge_photo()).save(p)
    scene = env.import_tiny(hdr["admin"], members=("annotator", "reviewer"))
    env.select_all(scene["id"])
    fid = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr["annotator"]).json()["id"]
    return env, hdr, fid


def test_scissors_path_follows_the_edge_around_a_corner(edge_world):
    env, hdr, fid = edge_world
    # from the left side to the bottom side: the straight line cuts the corner at (16, 35)
    start, end = [16, 20], [30, 35]
    r = env.client.post(f"/api/frames/{fid}/scissors", json={"start": start, "end": end},
                        headers=hdr["annotator"])
    assert r.status_code == 200, r.text
    body = r.json()
    path = np.array(body["path"])
    assert path[0].tolist() == start and path[-1].tolist() == end
    assert body["scale"] == 1.0 and body["crop"][0] <= 16 and body["crop"][3] >= 36
    dense = densify(path)
    assert border_distance(dense).max() <= 1.0, path.tolist()  # on the edge all the way
    assert np.hypot(dense[:, 0] - 16, dense[:, 1] - 35).min() <= 1.5  # through the corner
    straight = densify(np.array([start, end]))
    assert border_distance(straight).max() > 5  # the straight line would not be
    # the same request answers the same path (deterministic), reviewer / admin rules below
    again = env.client.post(f"/api/frames/{fid}/scissors", json={"start": start, "end": end},
                            headers=hdr["annotator"]).json()
    assert again["path"] == body["path"]
    same = env.client.post(f"/api/frames/{fid}/scissors", json={"start": start, "end": start},
                           headers=hdr["annotator"])
    assert same.status_code == 200 and same.json()["path"] == [start]


BAD = [
    ({"start": [16, 20], "end": [W, 10]}, "end"),
    ({"start": [-1, 20], "end": [30, 35]}, "start"),
    ({"start": [16, H + 5], "end": [30, 35]}, "start"),
    ({"start": [16, 20, 3], "end": [30, 35]}, "start"),
    ({"start": [16], "end": [30, 35]}, "start"),
    ({"start": [16, 20]}, "end"),
    ({"start": ["a", 20], "end": [30, 35]}, "start"),
    ({"start": [16.5, 20], "end": [30, 35]}, "start"),
]


def test_scissors_rejects_bad_points_with_422_naming_the_field(edge_world):
    env, hdr, fid = edge_world
    for body, field in BAD:
        r = env.client.post(f"/api/frames/{fid}/scissors", json=body, headers=hdr["annotator"])
        assert r.status_code == 422, (body, r.text)
        assert field in r.text, (body, r.text)
    r = env.client.post(f"/api/frames/{fid}/scissors", content=b"not json",
                        headers={**hdr["annotator"], "Content-Type": "application/json"})
    assert r.status_code == 422


def test_scissors_roles(edge_world):
    env, hdr, fid = edge_world
    ok = {"start": [16, 20], "end": [30, 35]}
    assert env.client.post(f"/api/frames/{fid}/scissors", json=ok).status_code == 401
    assert env.client.post(f"/api/frames/{fid}/scissors", json=ok,
                           headers=hdr["reviewer"]).status_code == 403
    # an annotator who is not a member of the scene, and one who does not hold the frame
    assert env.client.post(f"/api/frames/{fid}/scissors", json=ok,
                           headers=hdr["annotator2"]).status_code == 403
    env.add_members(env.client.get("/api/scenes", headers=hdr["admin"]).json()[-1]["id"],
                    ("annotator2",), hdr["admin"])
    r = env.client.post(f"/api/frames/{fid}/scissors", json=ok, headers=hdr["annotator2"])
    assert r.status_code == 403 and "not assigned to you" in r.text
    assert env.client.post(f"/api/frames/{fid}/scissors", json=ok,
                           headers=hdr["admin"]).status_code == 200
    assert env.client.post("/api/frames/99999/scissors", json=ok,
                           headers=hdr["admin"]).status_code == 404


def test_scissors_on_a_20_megapixel_photo_works_on_a_downscaled_crop():
    import time

    h, w = 3648, 5472
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.where(((xx - 2700) / 1500.0) ** 2 + ((yy - 1800) / 1000.0) ** 2 <= 1, 210, 35)
    img = np.repeat(img[:, :, None], 3, axis=2).astype(np.uint8)
    t0 = time.process_time()
    path, crop, s = scissors(img, (1200, 1800), (2700, 800))  # a quarter of the ellipse
    cpu = time.process_time() - t0
    assert s < 0.5 and max(crop[2] - crop[0], crop[3] - crop[1]) * s <= 513
    assert cpu < 2.0
    d = densify(path)
    r = np.hypot((d[:, 0] - 2700) / 1500.0, (d[:, 1] - 1800) / 1000.0)
    assert np.abs(r - 1).max() < 0.02  # on the ellipse (within ~1 working pixel) all the way


def test_grabcut_scribbles_change_the_cut():
    # two bright blocks in the box; a background scribble on the right one removes it
    img = edge_photo(rect=(10, 10, 30, 38))
    img[10:38, 34:54] = img[10:38, 10:30]
    box = (6, 6, 58, 42)
    plain = grabcut(img, box)
    assert plain[20 - 6, 40 - 6] and plain[20 - 6, 20 - 6]
    bg = [[x, y] for x in range(36, 52, 2) for y in range(12, 36, 2)]
    refined = grabcut(img, box, fg=[[20, 24]], bg=bg)
    assert refined[20 - 6, 20 - 6] and not refined[20 - 6:30 - 6, 36 - 6:52 - 6].any()


def test_grabcut_strokes_in_painting_order_the_later_wins():
    img = edge_photo(rect=(10, 10, 30, 38))
    img[10:38, 34:54] = img[10:38, 10:30]
    box = (6, 6, 58, 42)
    bg = ("bg", [[38, 14], [50, 34], [38, 34]])
    fg = ("fg", [[36, 24], [52, 24]])  # crosses the background stroke
    cut = grabcut(img, box, strokes=[bg, fg])
    assert cut[24 - 6, 36 - 6:53 - 6].all()  # the later (foreground) line wins where they cross
    cut = grabcut(img, box, strokes=[fg, bg])
    assert not cut[24 - 6, 44 - 6]  # ... and the other way round


def test_grabcut_route_takes_strokes_and_checks_them(edge_world):
    env, hdr, fid = edge_world
    url = f"/api/frames/{fid}/grabcut"
    ok = {"rect": [4, 4, 60, 44], "strokes": [{"kind": "bg", "points": [[20, 20], [30, 30]]}]}
    r = env.client.post(url, json=ok, headers=hdr["annotator"])
    assert r.status_code == 200 and r.headers["x-box"] == "4,4,60,44"
    for bad, field in (({"kind": "bg", "points": [[20, 20], [W, 30]]}, "strokes[0]"),
                       ({"kind": "maybe", "points": [[20, 20]]}, "kind"),
                       ({"kind": "fg", "points": []}, "points")):
        r = env.client.post(url, json={"rect": [4, 4, 60, 44], "strokes": [bad]},
                            headers=hdr["annotator"])
        assert r.status_code == 422 and field in r.text, r.text
    many = [{"kind": "fg", "points": [[1, 1]] * 15_000}] * 2
    r = env.client.post(url, json={"rect": [4, 4, 60, 44], "strokes": many}, headers=hdr["annotator"])
    assert r.status_code == 422 and "at most 20000" in r.text
    assert env.client.post(url, json=ok, headers=hdr["reviewer"]).status_code == 403
