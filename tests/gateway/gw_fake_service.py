"""A tiny stand-in for the calibration service's ingest endpoint.

Implements the HTTP batch contract of ``docs/internals.md``: bearer auth,
validation (422), durable-looking dedupe by ``(device_id, seq)`` (200 with
``duplicate: true`` on a resend). Usable without a socket
(:meth:`FakeService.transport`, an ``httpx.MockTransport``) or as a real
uvicorn server on 127.0.0.1 that can be turned down and up (:class:`LiveServer`).
"""

from __future__ import annotations

import asyncio
import json
import socket
from dataclasses import dataclass, field

import httpx


@dataclass
class FakeService:
    """Records accepted batches; ``up=False`` answers 503; ``fail_after_commit`` n times
    commits a batch but answers 500 (a lost acknowledgement); a seq resent with other
    content gets 409 (as the service answers)."""

    key: str = "test-key"
    up: bool = True
    fail_after_commit: int = 0
    batches: dict[tuple[str, int], dict] = field(default_factory=dict)
    order: dict[str, list[int]] = field(default_factory=dict)
    duplicates: int = 0
    requests: int = 0
    fail_devices: set[str] = field(default_factory=set)  # answered 500 whatever they send
    posts: dict[str, int] = field(default_factory=dict)  # POSTs per device

    def conflicting(self, device_id: str, seqs) -> None:
        """Hold ``seqs`` of ``device_id`` with content no gateway sends (a lost spool's)."""
        for seq in seqs:
            self.batches[(device_id, seq)] = {"seq": seq, "t_s": [-1.0], "ax_g": [0.0], "ay_g": [0.0], "az_g": [1.0]}
            self.order.setdefault(device_id, []).append(seq)

    def handle(self, method: str, path: str, headers: dict[str, str], body: bytes) -> tuple[int, dict]:
        self.requests += 1
        if not self.up:
            return 503, {"detail": "service unavailable"}
        if headers.get("authorization") != f"Bearer {self.key}":
            return 401, {"detail": "Authorization: missing or wrong bearer key"}
        parts = path.strip("/").split("/")
        if method != "POST" or len(parts) != 3 or parts[0] != "devices" or parts[2] != "samples":
            return 404, {"detail": f"no route {method} {path}"}
        device_id = parts[1]
        self.posts[device_id] = self.posts.get(device_id, 0) + 1
        try:
            batch = json.loads(body)
            seq = batch["seq"]
            n = len(batch["t_s"])
            for name in ("ax_g", "ay_g", "az_g"):
                if len(batch[name]) != n:
                    return 422, {"detail": f"{name}: length {len(batch[name])} != t_s length {n}"}
            if "pressure_kpa" in batch and len(batch["pressure_kpa"]) != n:
                return 422, {"detail": "pressure_kpa: wrong length"}
        except (ValueError, KeyError, TypeError) as exc:
            return 422, {"detail": f"invalid batch: {exc!r}"}
        key = (device_id, seq)
        duplicate = key in self.batches
        if duplicate and {k: v for k, v in self.batches[key].items() if k != "seq"} != {
                k: v for k, v in batch.items() if k != "seq"}:
            return 409, {"detail": f"seq {seq} of device {device_id!r} is stored with other content"}
        if device_id in self.fail_devices:
            return 500, {"detail": f"device {device_id!r}: always failing"}
        if duplicate:
            self.duplicates += 1
        else:
            self.batches[key] = batch
            self.order.setdefault(device_id, []).append(seq)
        if self.fail_after_commit > 0 and not duplicate:
            self.fail_after_commit -= 1
            return 500, {"detail": "internal error after commit"}
        return 200, {"device_id": device_id, "seq": seq, "accepted": n, "duplicate": duplicate}

    def transport(self) -> httpx.MockTransport:
        """An in-process transport (no socket)."""

        def handler(request: httpx.Request) -> httpx.Response:
            status, payload = self.handle(
                request.method, request.url.path, dict(request.headers), request.content
            )
            return httpx.Response(status, json=payload)

        return httpx.MockTransport(handler)

    # -- views -------------------------------------------------------------
    def samples(self, device_id: str) -> dict[str, list]:
        """All accepted samples of a device, concatenated in seq order."""
        out: dict[str, list] = {"t_s": [], "ax_g": [], "ay_g": [], "az_g": [], "pressure_kpa": [], "temp_c": []}
        for seq in sorted(s for d, s in self.batches if d == device_id):
            batch = self.batches[(device_id, seq)]
            for k in out:
                out[k].extend(batch.get(k, []))
        return out

    def n_samples(self, device_id: str | None = None) -> int:
        return sum(len(b["t_s"]) for (d, _), b in self.batches.items() if device_id in (None, d))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LiveServer:
    """``FakeService`` behind a real uvicorn server on 127.0.0.1; ``stop()`` makes
    the port refuse connections, ``start()`` brings it back on the same port."""

    def __init__(self, service: FakeService):
        self.service = service
        self.port = _free_port()
        self._server = None
        self._task: asyncio.Task | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _app(self):
        service = self.service

        async def app(scope, receive, send):
            if scope["type"] == "lifespan":
                while True:
                    message = await receive()
                    if message["type"] == "lifespan.startup":
                        await send({"type": "lifespan.startup.complete"})
                    elif message["type"] == "lifespan.shutdown":
                        await send({"type": "lifespan.shutdown.complete"})
                        return
            body = b""
            while True:
                message = await receive()
                body += message.get("body", b"")
                if not message.get("more_body"):
                    break
            headers = {k.decode().lower(): v.decode() for k, v in scope["headers"]}
            status, payload = service.handle(scope["method"], scope["path"], headers, body)
            data = json.dumps(payload).encode()
            await send({"type": "http.response.start", "status": status,
                        "headers": [(b"content-type", b"application/json")]})
            await send({"type": "http.response.body", "body": data})

        return app

    async def start(self) -> None:
        import uvicorn

        config = uvicorn.Config(self._app(), host="127.0.0.1", port=self.port, log_level="warning", lifespan="on")
        self._server = uvicorn.Server(config)
        self._task = asyncio.get_running_loop().create_task(self._server.serve())
        while not self._server.started:
            if self._task.done():
                self._task.result()
            await asyncio.sleep(0.01)

    async def stop(self) -> None:
        if self._server is not None:
            self._server.should_exit = True
            await self._task
            self._server = None
