"""The hot routes (``[service] hot_routes``): a binary batch POST and a calibration GET
answered without FastAPI's routing layers give the same answers as the routes.

Two apps in this process, one with the hot routes and one without, each on its own
database (SQLite, or PostgreSQL in the ``SELFCAL_TEST_BACKEND=postgresql`` pass), get the
same requests: plain ones, which the hot path must answer itself (the route's endpoint
is not called), and every kind of refusal, which it must hand to the app. Statuses,
bodies, the headers a client reads and the metrics must be equal.
"""

from __future__ import annotations

import re
import struct
import time

import numpy as np
import pytest
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient

from service_helpers import KEY_SPEC, auth, backend_db, batch_json

from selfcal_service.main import create_app
from selfcal_service.schemas import Batch
from selfcal_service.settings import load_settings

BINARY = "application/x-selfcal-batch"
HOT = ("/devices/{device_id}/samples", "/devices/{device_id}/calibration")


def _binary(seq: int, n: int = 20, acc=None, magic: bytes | None = None) -> bytes:
    rng = np.random.default_rng(seq)
    t = seq * n / 20.0 + np.arange(n) / 20.0
    a = np.column_stack([0.01 + 0.002 * rng.standard_normal(n), -0.02 + 0.002 * rng.standard_normal(n),
                         1.0 + 0.002 * rng.standard_normal(n)]) if acc is None else acc
    body = Batch(seq=seq, t_s=t, acc_g=a, temp_c=25.0 + 0.1 * rng.standard_normal(n)).to_bytes()
    return body if magic is None else magic + body[4:]


def _requests() -> list[tuple[str, str, dict, bytes | dict | None, bool]]:
    """(method, path, headers, body (bytes, or a dict sent as JSON), whether the route's
    endpoint is reached with the hot routes on: False for what the hot path answers)."""
    ing, rd = auth("ingest"), auth("read")
    bin_h = {**ing, "Content-Type": BINARY}
    nan = np.full((20, 3), 0.5)
    nan[3, 1] = np.nan
    out = [
        ("POST", "/devices/h1/samples", bin_h, _binary(0), False),
        ("POST", "/devices/h1/samples", bin_h, _binary(0), False),  # a resend: duplicate
        ("POST", "/devices/h1/samples", bin_h, _binary(0, acc=np.full((20, 3), 0.3)), False),  # 409
        ("POST", "/devices/h1/samples", bin_h, _binary(1), False),
        ("POST", "/devices/h1/samples", {**ing, "Content-Type": BINARY + "; v=1"}, _binary(2), False),
        ("POST", "/devices/h1/samples", bin_h, _binary(10**9), False),  # a seq jump: 422
        ("POST", "/devices/h1/samples", bin_h, _binary(3, acc=nan), False),  # checked after decoding: 422
        ("POST", "/devices/h1/samples", bin_h, _binary(4, n=2500), True),  # over the body limit: 413
        ("POST", "/devices/h1/samples", bin_h, _binary(4, magic=b"XXXX"), True),  # does not decode
        ("POST", "/devices/h1/samples", bin_h, _binary(4)[:-5], True),  # truncated
        ("POST", "/devices/h1/samples", bin_h, struct.pack("<4sqIHH", b"SCB1", 4, 0, 0, 0), True),  # n = 0
        ("POST", "/devices/h1/samples", {**ing, "Content-Type": "text/plain"}, _binary(4), True),  # 415
        ("POST", "/devices/h1/samples", {"Content-Type": BINARY}, _binary(4), True),  # 401
        ("POST", "/devices/h1/samples", {**rd, "Content-Type": BINARY}, _binary(4), True),  # 403
        ("POST", "/devices/-h1/samples", bin_h, _binary(4), True),  # the id's pattern: 422
        ("POST", "/devices/h2/samples", ing, batch_json(0), True),  # JSON: the route
        ("POST", "/devices/h1/samples/", bin_h, _binary(4), False),
        ("GET", "/devices/h1/calibration", rd, None, False),
        ("GET", "/devices/h1/calibration?x=1", rd, None, False),
        ("GET", "/devices/h2/calibration", auth("all"), None, False),
        ("GET", "/devices/nobody/calibration", rd, None, False),  # 404, the app's handler's
        ("GET", "/devices/h1/calibration", {}, None, True),  # 401
        ("GET", "/devices/h1/calibration", {"Authorization": "Basic abcdefghijkl"}, None, True),
        ("GET", "/devices/h1/calibration", ing, None, True),  # 403
        ("GET", "/devices/" + "x" * 80 + "/calibration", rd, None, True),  # 422
        ("GET", "/devices/h1/calibration/history", rd, None, False),  # another route
        ("POST", "/devices/h1/calibration", rd, None, False),  # 405
    ]
    return out


def _app(tmp_path, name: str, hot: bool):
    settings = load_settings(None, environ={}, overrides={
        "db_path": backend_db(tmp_path / f"{name}.db"), "api_keys": KEY_SPEC, "hot_routes": hot,
        "calibrator": "service_fakes:FakeCalibrator", "max_body_bytes": 65536, "max_batch_samples": 2000})
    app = create_app(settings, config={"fake": {"publish_after_samples": 30}})
    calls = {path: 0 for path in HOT}
    for route in app.routes:  # count the requests that reach the route's endpoint
        if isinstance(route, APIRoute) and route.path in HOT:
            inner = route.app

            async def counted(scope, receive, send, inner=inner, path=route.path):
                calls[path] += 1
                await inner(scope, receive, send)

            route.app = counted
    return app, calls


def _untimed(x):
    """``x`` without the times of the run (keys ending in ``_at``), at any depth."""
    if isinstance(x, dict):
        return {k: _untimed(v) for k, v in x.items() if not k.endswith("_at")}
    if isinstance(x, list):
        return [_untimed(v) for v in x]
    return x


def _settled(*apps) -> None:
    """Wait until every app's refit worker has fed and committed what it was given (reads
    then agree): no batch left unfed in its store, and its worker idle."""
    deadline = time.monotonic() + 30
    while not all(a.state.store.backlog() == 0 and a.state.worker.idle() for a in apps):
        assert time.monotonic() < deadline, "the refit workers did not settle"
        time.sleep(0.01)


def _seen(r) -> tuple:
    body = r.json() if r.headers.get("content-type", "").startswith("application/json") else r.text
    body = _untimed(body)
    return (r.status_code, r.headers.get("content-type"), r.headers.get("www-authenticate"),
            r.headers.get("allow"), r.headers.get("retry-after"), "x-request-id" in r.headers, body)


def _metric_lines(client) -> list[str]:
    text = client.get("/metrics", headers=auth("read")).text
    keep = ("selfcal_http_request_duration_seconds_count", "selfcal_ingest_")
    return sorted(ln for ln in text.splitlines() if ln.startswith(keep))


def test_the_hot_routes_answer_as_the_routes_do(tmp_path):
    hot_app, hot_calls = _app(tmp_path, "hot", True)
    app, calls = _app(tmp_path, "plain", False)
    with TestClient(hot_app, follow_redirects=False) as hot_client, \
            TestClient(app, follow_redirects=False) as client:
        for method, path, headers, body, reaches_route in _requests():
            kw = {"json": body} if isinstance(body, dict) else {"content": body}
            before = dict(hot_calls)
            if method == "GET":
                _settled(hot_app, app)
            got = hot_client.request(method, path, headers=headers, **kw)
            want = client.request(method, path, headers=headers, **kw)
            assert _seen(got) == _seen(want), (method, path, got.text, want.text)
            assert sum(hot_calls.values()) - sum(before.values()) == int(reaches_route), (method, path)
        assert sum(calls.values()) > sum(hot_calls.values()) > 0
        assert _metric_lines(hot_client) == _metric_lines(client)
        assert any('route="/devices/{device_id}/samples"' in ln for ln in _metric_lines(hot_client))


@pytest.mark.parametrize("hot", [True, False])
def test_a_store_failure_on_the_hot_path_is_the_routes_503(tmp_path, hot):
    from selfcal_service.storage import StorageUnavailable

    app, calls = _app(tmp_path, f"down-{hot}", hot)
    with TestClient(app) as client:
        assert client.post("/devices/d1/samples", content=_binary(0),
                           headers={**auth("ingest"), "Content-Type": BINARY}).status_code == 200
        store = app.state.store

        def down(*a, **k):
            raise StorageUnavailable("the database is down (test)")

        async def down_async(*a, **k):
            down()

        store.submit_batch, store.current, store.current_async = down, down, down_async  # current_async: PostgreSQL's
        r = client.post("/devices/d1/samples", content=_binary(1), headers={**auth("ingest"), "Content-Type": BINARY})
        assert (r.status_code, r.json()["error"], r.headers["retry-after"]) == (503, "storage_unavailable", "5")
        r = client.get("/devices/d1/calibration", headers=auth("read"))
        assert (r.status_code, r.json()["error"]) == (503, "storage_unavailable")
    assert sum(calls.values()) == (0 if hot else 3)  # hot: the store's error answered by the app's handler


def _raw(client, app, path: str, headers: dict, messages: list[dict]) -> tuple:
    """One request straight through the ASGI interface, its body as ``messages`` (so in
    as many pieces as a trickling client's TCP segments): (status, headers, body)."""
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
             "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "headers": [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in headers.items()],
             "client": ("127.0.0.1", 5000), "server": ("testserver", 80)}
    pending = list(reversed(messages))
    out: dict = {"body": b""}

    async def receive():
        return pending.pop() if pending else {"type": "http.disconnect"}

    async def send(message):
        if message["type"] == "http.response.start":
            out["status"] = message["status"]
            out["headers"] = {k.decode(): v.decode() for k, v in message["headers"] if k != b"x-request-id"}
        elif message["type"] == "http.response.body":
            out["body"] += message.get("body", b"")

    client.portal.call(app, scope, receive, send)
    body = re.sub(rb"request id [0-9a-f]+", b"request id R", out["body"])  # each request's own
    return out.get("status"), out.get("headers"), body


def _pieces(body: bytes, size: int) -> list[dict]:
    parts = [body[i:i + size] for i in range(0, len(body), size)] or [b""]
    return [{"type": "http.request", "body": p, "more_body": i < len(parts) - 1} for i, p in enumerate(parts)]


def test_bodies_in_many_pieces_and_clients_gone_are_answered_as_the_routes_do(tmp_path):
    """A body read in many pieces: a batch is taken by the hot path; one that does not
    decode, one over the limit (with and without a Content-Length) and one whose client
    left mid-body go to the route with what was read replayed, and get its answers."""
    hot_app, hot_calls = _app(tmp_path, "hot", True)
    app, _ = _app(tmp_path, "plain", False)
    head = {**auth("ingest"), "Content-Type": BINARY}
    good, bad = _binary(0), _binary(1, magic=b"XXXX")
    big = _binary(2, n=2500)  # 2500 x 5 x 8 bytes: over the 64-KiB limit
    cases = [  # (headers, messages, the route's endpoint reached)
        ({**head, "Content-Length": str(len(good))}, _pieces(good, 7), False),
        (head, _pieces(_binary(1), 3), False),  # no Content-Length (chunked)
        (head, _pieces(bad, 5), True),
        (head, _pieces(big, 1000), True),
        (head, _pieces(big, len(big)), True),  # over the limit in its last piece
        (head, _pieces(_binary(3), 50)[:4] + [{"type": "http.disconnect"}], True),
    ]
    with TestClient(hot_app) as hot_client, TestClient(app) as client:
        for headers, messages, reaches_route in cases:
            before = sum(hot_calls.values())
            got = _raw(hot_client, hot_app, "/devices/p1/samples", headers, [dict(m) for m in messages])
            want = _raw(client, app, "/devices/p1/samples", headers, [dict(m) for m in messages])
            assert got == want, (len(messages), got, want)
            assert sum(hot_calls.values()) - before == int(reaches_route)
        assert _metric_lines(hot_client) == _metric_lines(client)
