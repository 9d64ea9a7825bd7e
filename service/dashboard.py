"""The fleet dashboard (``/ui``): static pages and assets shipped in the package.

* ``GET /ui`` (or ``/ui/``): the fleet page; ``GET /ui/devices/{device_id}``: one device.
  Both are static HTML shells that hold no data and need no key: their JavaScript
  reads the JSON API (``/fleet``, ``/devices/...``, ``/whoami``) with
  ``Authorization: Bearer KEY``, so every figure on them needs the ``read`` scope and
  every action the ``admin`` scope, exactly as with ``curl``.
* The key is typed into the page once and kept in the tab's ``sessionStorage``, or
  handed over in the URL fragment (``/ui#key=...``): a fragment never reaches the
  server, and the page stores the key and removes it from the address bar and the
  history entry (``history.replaceState``) before anything else. A key is never put in
  a query string, so it cannot reach an access log.
* ``GET /ui/static/{name}``: the pages' scripts and styles and the vendored plotting
  library (uPlot, MIT, ``ui/static/vendor/uplot/PROVENANCE``). Only files shipped in
  the package are served, read once when the app is built; text assets are gzipped
  once too (sent when the browser accepts gzip) and carry an ETag.

Every response has a Content-Security-Policy allowing only this origin's scripts,
styles and API (no inline script, no CDN, no framing), ``Referrer-Policy: no-referrer``
and ``X-Content-Type-Options: nosniff``.
"""

from __future__ import annotations

import gzip
import hashlib
from dataclasses import dataclass
from importlib import resources
from typing import Annotated

from fastapi import FastAPI, Path, Request
from starlette.responses import RedirectResponse, Response

from selfcal_service.schemas import DEVICE_ID_PATTERN, FieldError

#: Media types of the files the dashboard ships (anything else is not served).
MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".txt": "text/plain; charset=utf-8",
}
#: Extension-less files (licence texts) are served as plain text.
PLAIN_TEXT = "text/plain; charset=utf-8"

SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
        "connect-src 'self'; form-action 'none'; frame-ancestors 'none'; base-uri 'none'"
    ),
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
}

#: Below this many bytes an asset is sent as is (gzip would gain little).
GZIP_MIN_BYTES = 1024


@dataclass(frozen=True)
class Asset:
    """One shipped file: its bytes, gzipped bytes (or None), media type and ETag."""

    body: bytes
    gzipped: bytes | None
    media_type: str
    etag: str


def _asset(body: bytes, media_type: str) -> Asset:
    gz = gzip.compress(body, compresslevel=9, mtime=0) if len(body) >= GZIP_MIN_BYTES else None
    return Asset(body, gz, media_type, '"' + hashlib.sha256(body).hexdigest()[:20] + '"')


def load_assets() -> tuple[dict[str, Asset], dict[str, Asset]]:
    """(pages by name, static files by path under ``static/``) from the package's ``ui`` folder."""
    root = resources.files("selfcal_service").joinpath("ui")
    pages = {name: _asset(root.joinpath(name).read_bytes(), MEDIA_TYPES[".html"])
             for name in ("fleet.html", "device.html")}
    static: dict[str, Asset] = {}

    def walk(folder, prefix: str) -> None:
        for entry in folder.iterdir():
            if entry.is_dir():
                walk(entry, f"{prefix}{entry.name}/")
                continue
            suffix = "." + entry.name.rsplit(".", 1)[1] if "." in entry.name else ""
            if suffix and suffix not in MEDIA_TYPES:
                continue
            static[prefix + entry.name] = _asset(entry.read_bytes(), MEDIA_TYPES.get(suffix, PLAIN_TEXT))

    walk(root.joinpath("static"), "")
    return pages, static


def _send(asset: Asset, request: Request, cache: str) -> Response:
    """The asset, gzipped if the client accepts it; 304 when its ETag matches."""
    headers = {**SECURITY_HEADERS, "ETag": asset.etag, "Cache-Control": cache, "Vary": "Accept-Encoding"}
    if request.headers.get("if-none-match") == asset.etag:
        return Response(status_code=304, headers=headers)
    body = asset.body
    if asset.gzipped is not None and "gzip" in request.headers.get("accept-encoding", ""):
        body = asset.gzipped
        headers["Content-Encoding"] = "gzip"
    return Response(body, media_type=asset.media_type, headers=headers)


def add_dashboard_routes(app: FastAPI) -> None:
    """Register ``/ui``, ``/ui/devices/{device_id}`` and ``/ui/static/{path}`` (not in the OpenAPI schema)."""
    pages, static = load_assets()
    page_cache = "no-cache"  # revalidate (ETag): a new release is picked up at once

    @app.get("/ui", include_in_schema=False)
    async def ui_fleet(request: Request) -> Response:
        return _send(pages["fleet.html"], request, page_cache)

    @app.get("/ui/", include_in_schema=False)
    async def ui_fleet_slash() -> Response:
        return RedirectResponse("/ui", status_code=308, headers=SECURITY_HEADERS)

    @app.get("/ui/devices/{device_id}", include_in_schema=False)
    async def ui_device(
        request: Request, device_id: Annotated[str, Path(pattern=DEVICE_ID_PATTERN)]
    ) -> Response:
        return _send(pages["device.html"], request, page_cache)

    @app.get("/ui/static/{path:path}", include_in_schema=False)
    async def ui_static(request: Request, path: str) -> Response:
        asset = static.get(path)
        if asset is None:
            raise FieldError("path", f"no dashboard file {path!r}", 404)
        return _send(asset, request, page_cache)
