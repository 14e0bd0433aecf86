"""Issue 36 (part B, item 3): a correction naming every point is no longer parsed whole.
The ids are counted before anything is allocated per point (413 over
OCCUFLY_MAX_CORRECTION_POINTS, the body cut off while it streams), a plain JSON array is
converted by numpy from the text, and ``point_ids_b64`` (little-endian uint32) is the compact
form. Measured on the server process itself (the app in a child process, its high-water mark
reset before each request): 1 M ids in JSON +63 MB before -> +33 MB; 1 M in base64 +25 MB;
10 M ids +621 MB before -> a 413 at +12 MB."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.exceptions import RequestValidationError

from app.corrections.parsing import parse_edit
from app.errors import Invalid, PayloadTooLarge
from tests.app.conftest import PASSWORD, seed_served_data


def _b64(ids) -> str:  # noqa: ANN001
    return base64.b64encode(np.asarray(ids, "<u4").tobytes()).decode()


def _body(**kw) -> bytes:  # noqa: ANN003
    return json.dumps({"to_class": 8, **kw}).encode()


# ---- the parser -------------------------------------------------------------------------------
@pytest.mark.parametrize("body", [
    b'{"to_class": 8, "point_ids": [3, 1, 2]}',
    b'{ "point_ids" : [ 3 ,1,\n 2 ] , "to_class":8 }',
    b'{"point_ids": [9], "to_class": 8, "point_ids": [3, 1, 2]}',  # the last one counts
    _body(point_ids_b64=_b64([3, 1, 2])),
])
def test_both_forms_give_the_same_ids(body):
    e = parse_edit(body, 10)
    assert e.point_ids.tolist() == [3, 1, 2] and e.point_ids.dtype == np.int64
    assert e.to_class == 8 and e.comment is None and e.frame_id is None


def test_other_fields_are_validated_and_a_comment_may_hold_commas():
    e = parse_edit(_body(point_ids=[1], comment="a, b, [c], \"d\"", frame_id=4), 10)
    assert e.comment == 'a, b, [c], "d"' and e.frame_id == 4
    with pytest.raises(RequestValidationError) as ei:
        parse_edit(json.dumps({"point_ids": [1], "to_class": 300}).encode(), 10)
    assert ei.value.errors()[0]["loc"] == ("body", "to_class")


@pytest.mark.parametrize("body,field", [
    (_body(point_ids=[1.5, 2]), "point_ids"),
    (_body(point_ids=["1", 2]), "point_ids"),
    (_body(point_ids=[[1], 2]), "point_ids"),
    (_body(point_ids=[True]), "point_ids"),
    (_body(point_ids=[-1, 2]), "point_ids"),
    (_body(point_ids=[]), "point_ids"),
    (b'{"to_class": 8, "point_ids": [1,,2]}', None),
    (b'{"to_class": 8, "point_ids": [1 2]}', None),
    (b'{"to_class": 8, "point_ids": [1,2,]}', None),
    (_body(point_ids="1,2"), "point_ids"),
    (_body(), "point_ids"),
    (_body(point_ids=[1], point_ids_b64=_b64([1])), "point_ids"),
    (_body(point_ids_b64="not base64!"), "point_ids_b64"),
    (_body(point_ids_b64=base64.b64encode(b"abc").decode()), "point_ids_b64"),
    (b"[1, 2]", None),
    (b'{"to_class": 8, "point_ids": [1]', None),
    (b'{"to_class": 8, "point_ids": [1]} trailing', None),
    (b"\xff\xfe", None),
])
def test_malformed_bodies_are_422(body, field):
    with pytest.raises((RequestValidationError, Invalid)) as ei:
        parse_edit(body, 10)
    if field is not None and isinstance(ei.value, RequestValidationError):
        assert ei.value.errors()[0]["loc"][1] == field


@pytest.mark.parametrize("body", [
    _body(point_ids=list(range(11))),
    _body(point_ids=[1.0] * 11),  # over the cap whatever it holds
    _body(point_ids_b64=_b64(range(11))),
    b'{"to_class": 8, "point_ids": [' + b"1," * 20_000 + b"1]}",
])
def test_over_the_cap_is_413(body):
    with pytest.raises(PayloadTooLarge, match="at most 10 points"):
        parse_edit(body, 10)


# ---- through the API ---------------------------------------------------------------------------
def test_a_base64_correction_equals_the_json_one_and_the_cap_is_a_setting(world):
    env, hdr, scene, _frames = world
    url = f"/api/scenes/{scene['id']}/corrections"
    rev = hdr["reviewer"]
    r = env.client.post(url, json={"point_ids_b64": _b64([5, 3, 4, 3]), "to_class": 8},
                        headers=rev)
    assert r.status_code == 201, r.text
    assert r.json()["n_points"] == 3
    r = env.client.post(url, json={"point_ids": [5, 3, 4], "to_class": 1}, headers=rev)
    assert r.status_code == 201 and r.json()["n_points"] == 3, r.text
    env.app.state.ctx.settings.max_correction_points = 2
    r = env.client.post(url, json={"point_ids": [1, 2, 3], "to_class": 8}, headers=rev)
    assert r.status_code == 413 and "at most 2 points" in r.json()["detail"], r.text
    r = env.client.post(url, json={"point_ids_b64": _b64([1, 2, 3]), "to_class": 8}, headers=rev)
    assert r.status_code == 413, r.text
    r = env.client.post(url, content=b'{"to_class": 8, "point_ids": [1.5]}', headers={
        **rev, "content-type": "application/json"})
    assert r.status_code == 422 and "point_ids" in r.json()["detail"], r.text
    doc = env.client.get("/openapi.json").json()
    schema = doc["paths"]["/api/scenes/{sid}/corrections"]["post"]["requestBody"]
    assert "point_ids_b64" in json.dumps(schema)


# ---- the server's own peak ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("needs Linux /proc/<pid>/clear_refs")
    from tests.app.test_import_memory import Server
    from tests.harness import ProcessServer

    tmp = tmp_path_factory.mktemp("correction_memory")
    (tmp / "tmp").mkdir()
    # the body cap lets 10 M ids through to the route; a 20 M-point scene as far as the
    # point-id bounds are concerned
    env, sid = seed_served_data(tmp, {"OCCUFLY_MAX_SELECTION_MB": "256",
                                      "TMPDIR": str(tmp / "tmp")}, n_points=20_000_000)
    proc = ProcessServer(env, tmp / "server.log", start_timeout=90).start()
    try:
        c = httpx.Client(base_url=proc.url, timeout=120)
        tok = c.post("/api/auth/login", json={"username": "admin", "password": PASSWORD})
        srv = Server(proc, tok.json()["token"], sid, [])
        srv.post = lambda body: srv.measure(lambda h: h.post(  # noqa: ARG005
            f"/api/scenes/{sid}/corrections", content=body,
            headers={**srv.hdr, "content-type": "application/json"}))
        srv.post(b'{"to_class": 254, "point_ids": [1, 2]}')  # warm up
        yield srv
    finally:
        proc.stop()


def _ids(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.int64) * 2 % 20_000_000


# to_class 254 is not in the taxonomy: the ids are parsed whole, then the class is refused
@pytest.mark.parametrize("form,n,status,limit_mb", [
    ("json", 1_000_000, 422, 60), ("b64", 1_000_000, 422, 50),
    ("json", 10_000_000, 413, 30), ("b64", 10_000_000, 413, 30)])
def test_server_peak_of_a_big_correction(server, form, n, status, limit_mb):
    ids = _ids(n)
    if form == "json":
        body = ('{"to_class": 254, "point_ids": [' + ",".join(map(str, ids.tolist()))
                + "]}").encode()
    else:
        body = _body(point_ids_b64=_b64(ids)).replace(b'"to_class": 8', b'"to_class": 254')
    r, mb, cpu = server.post(body)
    print(f"MEASURED correction of {n} ids ({form}, {len(body) / 2**20:.1f} MB): HTTP "
          f"{r.status_code}, server peak +{mb:.0f} MB, {cpu:.2f} s CPU")
    assert r.status_code == status, r.text[:300]
    assert ("class 254" if status == 422 else "at most 2000000 points") in r.text
    assert mb <= limit_mb, f"the server's peak grew {mb:.0f} MB"
