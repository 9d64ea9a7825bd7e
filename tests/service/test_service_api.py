"""HTTP contract over a real uvicorn server (``selfcal serve`` subprocess, fake calibrator)."""

from __future__ import annotations

import math
import struct

import httpx
import numpy as np
import pytest

from service_helpers import auth, batch_json, t_ms_sum

pytestmark = pytest.mark.service

BINARY = "application/x-selfcal-batch"


def post(srv, device_id, body, scope="ingest", **kw):
    with srv.client(scope) as c:
        return c.post(f"/devices/{device_id}/samples", json=body, **kw) if body is not None else c.post(
            f"/devices/{device_id}/samples", **kw
        )


def stored(srv, device_id) -> int | None:
    """batches stored for a device (None if the device does not exist)."""
    with srv.client("read") as c:
        r = c.get(f"/devices/{device_id}/calibration")
    return None if r.status_code == 404 else r.json()["batches_stored"]


# ----------------------------------------------------------------- auth
@pytest.mark.parametrize(
    "method,path,scope",
    [
        ("POST", "/devices/a1/samples", "ingest"),
        ("GET", "/devices/a1/calibration", "read"),
        ("GET", "/devices/a1/calibration/history", "read"),
        ("GET", "/devices", "read"),
        ("GET", "/metrics", "read"),
        ("PUT", "/devices/a1/calibration", "admin"),
        ("POST", "/devices/a1/calibration/rollback", "admin"),
    ],
)
def test_missing_unknown_key_401_wrong_scope_403(fake_server, method, path, scope):
    url = fake_server.url + path
    body = batch_json(0) if path.endswith("samples") else {}
    r = httpx.request(method, url, json=body)
    assert r.status_code == 401 and r.json()["field"] == "Authorization"
    assert r.headers["www-authenticate"] == "Bearer"
    r = httpx.request(method, url, json=body, headers={"Authorization": "Bearer not-a-key-at-all"})
    assert r.status_code == 401
    r = httpx.request(method, url, json=body, headers={"Authorization": "Basic " + "x" * 12})
    assert r.status_code == 401
    wrong = next(s for s in ("ingest", "read", "admin") if s != scope)
    r = httpx.request(method, url, json=body, headers=auth(wrong))
    assert r.status_code == 403, r.text
    assert scope in r.json()["message"]
    # the key itself never appears in what the server says or logs
    assert "ingest-key-0001" not in r.text


def test_keys_are_never_logged(fake_server):
    httpx.get(fake_server.url + "/devices", headers={"Authorization": "Bearer secret-probe-key-123"})
    httpx.get(fake_server.url + "/devices", headers=auth("read"))
    text = fake_server.log.read_text()
    assert "secret-probe-key-123" not in text and "read-key-0001" not in text


def test_healthz_needs_no_key(fake_server):
    r = httpx.get(fake_server.url + "/healthz")
    assert r.status_code == 200 and r.json()["status"] == "ok"


# ----------------------------------------------------------------- ingest
def test_ingest_refit_get_vertical_slice(fake_server):
    dev = "slice-01"
    bodies = [batch_json(seq, n=50, temp=True, pressure_channels=4) for seq in range(10)]
    for b in bodies:
        r = post(fake_server, dev, b)
        assert r.status_code == 200, r.text
        assert r.json() == {"device_id": dev, "seq": b["seq"], "accepted": 50, "duplicate": False}
    cal = fake_server.wait_processed(dev, 9)
    assert cal["samples_processed"] == 500 and cal["batches_stored"] == 10
    assert cal["status"] == "calibrated" and cal["version"] == 2 and cal["source"] == "refit"
    assert cal["matrix"][0][0] == pytest.approx(1.01) and len(cal["offset"]) == 3
    assert cal["undetermined"] == ["nxz"] and "bx" in cal["determined"]
    assert cal["last_refit"]["t_ms_sum"] == sum(t_ms_sum(b) for b in bodies)
    with fake_server.client("read") as c:
        hist = c.get(f"/devices/{dev}/calibration/history").json()
        devices = c.get("/devices", params={"limit": 1000}).json()["devices"]
    assert [v["version"] for v in hist["versions"]] == [1, 2]
    assert [v["status"] for v in hist["versions"]] == ["provisional", "calibrated"]
    prov = hist["versions"][0]["provenance"]
    assert prov["seq_range"] == [0, 3] and prov["samples"] == 200
    lo, hi = prov["temp_range_c"]
    assert 24 < lo <= hi < 26
    assert prov["time_span_s"][0] == 0.0 and prov["time_span_s"][1] == pytest.approx(199 / 20)
    assert any(d["device_id"] == dev and d["status"] == "calibrated" for d in devices)


def test_resent_batch_is_acknowledged_not_counted_twice(fake_server):
    dev = "dup-01"
    bodies = [batch_json(seq) for seq in range(5)]
    for b in bodies:
        assert post(fake_server, dev, b).json()["duplicate"] is False
    for b in (bodies[1], bodies[4], bodies[4]):
        r = post(fake_server, dev, b)
        assert r.status_code == 200 and r.json()["duplicate"] is True and r.json()["accepted"] == 20
    cal = fake_server.wait_processed(dev, 4)
    assert cal["batches_stored"] == 5 and cal["samples_processed"] == 100
    assert cal["last_refit"]["n_samples"] == 100
    assert cal["last_refit"]["t_ms_sum"] == sum(t_ms_sum(b) for b in bodies)


def test_binary_batch_equals_json_batch(fake_server):
    from selfcal_service.schemas import Batch

    rng = np.random.default_rng(7)
    body = batch_json(0, n=40, temp=True, pressure_channels=3, rng=rng)
    batch = Batch(
        seq=0,
        t_s=np.asarray(body["t_s"]),
        acc_g=np.column_stack([body["ax_g"], body["ay_g"], body["az_g"]]),
        temp_c=np.asarray(body["temp_c"]),
        pressure_kpa=np.asarray(body["pressure_kpa"]),
    )
    r = post(fake_server, "bin-01", None, content=batch.to_bytes(), headers={"Content-Type": BINARY})
    assert r.status_code == 200, r.text
    assert r.json()["accepted"] == 40
    r2 = post(fake_server, "json-01", body)
    assert r2.status_code == 200
    a = fake_server.wait_processed("bin-01", 0)["last_refit"]
    b = fake_server.wait_processed("json-01", 0)["last_refit"]
    assert a["t_ms_sum"] == b["t_ms_sum"] == t_ms_sum(body)
    # resending the binary form of a JSON-stored seq is a duplicate too
    r3 = post(fake_server, "json-01", None, content=batch.to_bytes(), headers={"Content-Type": BINARY})
    assert r3.json()["duplicate"] is True


# ----------------------------------------------------------------- validation
def _bad(**changes):
    body = batch_json(0, n=5, temp=True, pressure_channels=2)
    for k, v in changes.items():
        if v is None:
            body.pop(k)
        else:
            body[k] = v
    return body


BAD_JSON = [
    (_bad(ay_g=[0.0] * 4), "ay_g"),
    (_bad(temp_c=[20.0] * 6), "temp_c"),
    (_bad(pressure_kpa=[[1.0, 2.0]] * 4), "pressure_kpa"),
    (_bad(pressure_kpa=[[1.0, 2.0]] * 4 + [[1.0]]), "pressure_kpa[4]"),
    (_bad(ax_g=[0.0, 0.0, 17.0, 0.0, 0.0]), "ax_g[2]"),
    (_bad(az_g=[0.0, 0.0, 0.0, -16.5, 0.0]), "az_g[3]"),
    (_bad(temp_c=[20.0, 20.0, 20.0, 20.0, 90.0]), "temp_c[4]"),
    (_bad(pressure_kpa=[[1.0, 2.0]] * 4 + [[1.0, -3.0]]), "pressure_kpa[4][1]"),
    (_bad(pressure_kpa=[[1.0, 2.0]] * 4 + [[1.0, 2500.0]]), "pressure_kpa[4][1]"),
    (_bad(t_s=[0.0, 0.05, 0.04, 0.1, 0.2]), "t_s[2]"),
    (_bad(seq=-1), "seq"),
    (_bad(seq=1.5), "seq"),
    (_bad(seq="3"), "seq"),
    (_bad(ax_g=[0.0, "0.1", 0.0, 0.0, 0.0]), "ax_g[1]"),
    (_bad(ax_g=[0.0, True, 0.0, 0.0, 0.0]), "ax_g[1]"),
    (_bad(t_s=None), "t_s"),
    (_bad(t_s=[], ax_g=[], ay_g=[], az_g=[], temp_c=None, pressure_kpa=None), "t_s"),
    (_bad(gyro_dps=[0.0] * 5), "gyro_dps"),
    (_bad(ax_mps2=[0.0] * 5), "ax_mps2"),
]


@pytest.mark.parametrize("body,field", BAD_JSON, ids=[f for _, f in BAD_JSON])
def test_bad_json_batch_names_field_and_stores_nothing(fake_server, body, field):
    dev = "bad-" + field.replace("[", "_").replace("]", "")
    r = post(fake_server, dev, body)
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field, r.json()
    assert field in r.json()["message"]
    assert stored(fake_server, dev) is None  # not even the device was created


@pytest.mark.parametrize(
    "raw,field",
    [
        (b'{"seq":0,"t_s":[0,0.05],"ax_g":[0,NaN],"ay_g":[0,0],"az_g":[1,1]}', "ax_g[1]"),
        (b'{"seq":0,"t_s":[0,Infinity],"ax_g":[0,0],"ay_g":[0,0],"az_g":[1,1]}', "t_s[1]"),
        (b'{"seq":0,"t_s":[0,0.05],"ax_g":[0,0],"ay_g":[-Infinity,0],"az_g":[1,1]}', "ay_g[0]"),
        (b'{"seq":0,"t_s":[0,0.05],"ax_g":[0,0],"ay_g":[0,0],"az_g":[1,1e999]}', "az_g[1]"),
        (b'{"seq":0,"t_s":[0,0.05],"ax_g":[0,0],"ay_g":[0,0],"az_g":[1,1],"temp_c":[NaN,20]}', "temp_c[0]"),
        (b'{"seq":0,"t_s":[0,0.05],"ax_g":[0,0],', "body"),
        (b"[1, 2, 3]", "body"),
        (b"", "body"),
    ],
)
def test_nan_infinity_tokens_and_broken_json_rejected(fake_server, raw, field):
    dev = "nan-" + field.replace("[", "_").replace("]", "")
    r = post(fake_server, dev, None, content=raw, headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field
    assert stored(fake_server, dev) is None


@pytest.mark.parametrize(
    "device_id", ["-leading-dash", "a" * 65, "sp ace", "sl%2Fash", "uni\u00e9", "semi;colon"]
)
def test_unsafe_device_id_rejected(fake_server, device_id):
    r = post(fake_server, device_id, batch_json(0))
    assert r.status_code in (404, 422), r.text
    if r.status_code == 422:
        assert r.json()["field"] == "device_id"


def test_safe_device_id_pattern_accepted(fake_server):
    assert post(fake_server, "L-01.left:A_b", batch_json(0)).status_code == 200


def test_oversized_body_413_and_too_many_samples(fake_server):
    big = batch_json(0, n=5000)  # ~ 300 kB > max_body_bytes = 256 kiB
    r = post(fake_server, "big-01", big)
    assert r.status_code == 413 and r.json()["field"] == "body"
    many = batch_json(0, n=2001)
    many = {k: (v if k == "seq" else [round(x, 3) for x in v]) for k, v in many.items()}
    r = post(fake_server, "big-02", many)
    assert r.status_code == 422 and r.json()["field"] == "t_s" and "2000" in r.json()["message"]
    # a chunked body without Content-Length is cut off too
    payload = b'{"seq":0,"t_s":[' + b"0.0," * 80000 + b"0.0]}"

    def gen():
        for i in range(0, len(payload), 65536):
            yield payload[i : i + 65536]

    r = post(fake_server, "big-03", None, content=gen(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413
    assert stored(fake_server, "big-01") is None and stored(fake_server, "big-03") is None


def test_unsupported_content_type_415(fake_server):
    r = post(fake_server, "ct-01", None, content=b"seq=1", headers={"Content-Type": "text/plain"})
    assert r.status_code == 415 and r.json()["field"] == "Content-Type"


@pytest.mark.parametrize(
    "mutate,field",
    [
        (lambda b: b"XXXX" + b[4:], "magic"),
        (lambda b: b[:-8], "body"),
        (lambda b: b[:10], "body"),
        (lambda b: b[:18] + struct.pack("<H", 6) + b[20:], "flags"),
        (lambda b: b[:20 + 8 * 40] + struct.pack("<d", math.nan) + b[20 + 8 * 41 :], "ax_g[0]"),
        (lambda b: b[:20 + 8 * 3] + struct.pack("<d", -1.0) + b[20 + 8 * 4 :], "t_s[3]"),
        (lambda b: b[:20 + 8 * 120] + struct.pack("<d", 20.0) + b[20 + 8 * 121 :], "az_g[0]"),
    ],
)
def test_bad_binary_batch(fake_server, mutate, field):
    from selfcal_service.schemas import Batch

    body = batch_json(0, n=40)
    raw = Batch(0, np.asarray(body["t_s"]), np.column_stack([body["ax_g"], body["ay_g"], body["az_g"]])).to_bytes()
    dev = "binbad-" + field.replace("[", "_").replace("]", "")
    r = post(fake_server, dev, None, content=mutate(raw), headers={"Content-Type": BINARY})
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field
    assert stored(fake_server, dev) is None


# ----------------------------------------------------------------- admin
def test_seed_factory_calibration_and_rollback(fake_server):
    dev = "admin-01"
    with fake_server.client("admin") as c:
        r = c.put(f"/devices/{dev}/calibration", json={"matrix": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]],
                                                         "offset": [0.0, 0.0, 0.0], "note": "bench"})
        assert r.status_code == 200, r.text
        assert r.json()["version"] == 1 and r.json()["source"] == "factory" and r.json()["status"] == "calibrated"
        r = c.put(f"/devices/{dev}/calibration", json={"matrix": [[1.0, 0, 0], [0, 1.0, 0]], "offset": [0, 0, 0]})
        assert r.status_code == 422 and r.json()["field"] == "matrix"
        r = c.put(f"/devices/{dev}/calibration", json={"matrix": [[1.0, 0, 0]] * 3, "offset": [0, 0, 0], "x": 1})
        assert r.status_code == 422 and r.json()["field"] == "x"
        r = c.post(f"/devices/{dev}/calibration/rollback", json={})
        assert r.status_code == 422 and r.json()["field"] == "to_version"
        r = c.post(f"/devices/{dev}/calibration/rollback", json={"to_version": 7})
        assert r.status_code == 404 and r.json()["field"] == "to_version"
    for b in (batch_json(s, n=100) for s in range(5)):
        assert post(fake_server, dev, b).status_code == 200
    cal = fake_server.wait_processed(dev, 4)
    assert cal["version"] == 3 and cal["source"] == "refit"  # fake published twice after the seed
    with fake_server.client("admin") as c:
        r = c.post(f"/devices/{dev}/calibration/rollback", json={"to_version": 1})
        assert r.status_code == 200, r.text
        assert r.json()["version"] == 4 and r.json()["source"] == "rollback"
        assert r.json()["matrix"] == [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]
        hist = c.get(f"/devices/{dev}/calibration/history", headers=auth("read")).json()
    assert hist["current_version"] == 4
    assert hist["versions"][-1]["provenance"]["rollback_of"] == 1


def test_unknown_device_404(fake_server):
    with fake_server.client("read") as c:
        r = c.get("/devices/never-seen/calibration")
        assert r.status_code == 404 and r.json()["field"] == "device_id"


def test_metrics_prometheus_text(fake_server):
    post(fake_server, "metrics-01", batch_json(0))
    post(fake_server, "metrics-01", batch_json(0))
    with fake_server.client("read") as c:
        r = c.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    values = {}
    for line in r.text.splitlines():
        if line and not line.startswith("#"):
            name, _, value = line.rpartition(" ")
            values[name] = float(value)
    assert values["selfcal_ingest_duplicates_total"] >= 1
    assert values["selfcal_ingest_samples_total"] >= 20
    assert any(k.startswith("selfcal_http_request_duration_seconds_bucket") for k in values)
    assert any(k.startswith('selfcal_worker_queue_depth{pid="') for k in values)  # this process's own
    assert values['selfcal_gc_pause_seconds_count{generation="0",role="api"}'] >= 1  # the collector's pauses are timed


# ----------------------------------------------------------------- found by a review (2026-11-28)
def test_a_compressed_body_is_a_415_on_both_paths_and_stores_nothing(fake_server):
    """A body with a Content-Encoding was decoded as if plain: stored as is when its bytes
    happened to parse, a confusing 422 when not."""
    from selfcal_service.schemas import Batch

    body = batch_json(0, n=20)
    raw = Batch(0, np.asarray(body["t_s"]), np.column_stack([body["ax_g"], body["ay_g"], body["az_g"]])).to_bytes()
    import json as _json

    for dev, content, ctype in (("enc-json", _json.dumps(body).encode(), "application/json"),
                                ("enc-bin", raw, BINARY)):  # (the binary one takes the hot path)
        r = post(fake_server, dev, None, content=content, headers={"Content-Type": ctype, "Content-Encoding": "gzip"})
        assert r.status_code == 415 and r.json()["field"] == "Content-Encoding", r.text
        assert stored(fake_server, dev) is None
        r = post(fake_server, dev, None, content=content, headers={"Content-Type": ctype, "Content-Encoding": "identity"})
        assert r.status_code == 200, r.text


def test_an_admin_seed_with_a_std_too_small_or_unknown_or_params_unlike_its_matrix_is_refused(fake_server):
    """A std of 1e-200 was served, and its prior's covariance made every later refit raise:
    the device's batches were all rejected. Unknown std names were dropped silently, and
    params that disagree with the matrix replaced it silently."""
    eye = [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]
    params = {"bx": 0, "by": 0, "bz": 0, "sx": 1, "sy": 1, "sz": 1, "nxy": 0, "nxz": 0, "nyz": 0}
    with fake_server.client("admin") as c:
        r = c.put("/devices/seed-std/calibration", json={"matrix": eye, "offset": [0, 0, 0], "std": {"bx": 1e-200}})
        assert r.status_code == 422 and r.json()["field"].startswith("std"), r.text
        r = c.put("/devices/seed-std/calibration", json={"matrix": [[1.2, 0, 0], [0, 1, 0], [0, 0, 1]],
                                                         "offset": [0.3, 0, 0], "params": params})
        assert r.status_code == 422 and r.json()["field"] == "params" and "different" in r.text, r.text
        r = c.put("/devices/seed-std/calibration", json={"matrix": eye, "offset": [0, 0, 0], "params": params})
        assert r.status_code == 200, r.text  # the same calibration both ways
        assert c.get("/devices/seed-std/calibration/history", headers=auth("read")).json()["current_version"] == 1


def test_a_client_gone_mid_body_is_not_an_internal_error(fake_server):
    import socket
    import time

    def internal_errors():
        with fake_server.client("read") as c:
            text = c.get("/metrics").text
        return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                   if line.startswith("selfcal_http_internal_errors_total"))

    before = internal_errors()
    head = (f"POST /devices/gone-1/samples HTTP/1.1\r\nHost: x\r\n{_auth_line()}"
            "Content-Type: application/json\r\nContent-Length: 400\r\n\r\n{\"seq\": 0, \"t_s\": [")
    with socket.create_connection(("127.0.0.1", fake_server.port)) as s:
        s.sendall(head.encode())
        time.sleep(0.3)
    time.sleep(0.5)
    assert internal_errors() == before
    with fake_server.client("read") as c:
        r = c.request("HEAD", "/healthz")
    assert r.status_code == 405 and "HEAD" not in r.headers.get("allow", "")  # not offered, as not served


def _auth_line() -> str:
    return "".join(f"{k}: {v}\r\n" for k, v in auth("ingest").items())


def test_gzip_is_sent_only_to_a_client_that_accepts_it():
    from selfcal_service.main import _accepts_gzip

    assert _accepts_gzip("gzip") and _accepts_gzip("br, gzip;q=0.5") and _accepts_gzip("*")
    assert not _accepts_gzip("gzip;q=0") and not _accepts_gzip("identity") and not _accepts_gzip("")
    assert not _accepts_gzip("*, gzip;q=0") and not _accepts_gzip("gzip;q=zero")
