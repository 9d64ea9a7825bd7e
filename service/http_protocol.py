"""uvicorn's HTTP protocols with deadlines for slow clients (header and body timeouts).

uvicorn closes an *idle* keep-alive connection (``timeout_keep_alive``), but once a
client has sent one byte it waits for the rest of the request head, and for the body,
for ever. A few hundred clients that send half a request (slowloris) then hold
sockets, memory and, for a body, a request task each. :class:`TimedHttpToolsProtocol`
(uvicorn's httptools parser, C, the default when ``httptools`` is installed) and
:class:`TimedH11Protocol` (the pure-Python h11 parser) add two deadlines per request:

* **head**: the request line and headers must be complete within ``header_timeout_s``
  of the connection being opened, or of the first byte of a request on a kept-alive
  connection;
* **body**: the body must be complete within ``body_timeout_s`` of its head.

A client that misses a deadline is disconnected (the request task sees
``http.disconnect``; nothing is stored, as a body that never completed is never
parsed), and ``on_timeout(kind)`` is called with kind ``header`` or ``body``.

The classes are module-level so that uvicorn can hand them to worker processes (they
are spawned, and their configuration is pickled); :func:`configure` sets the deadlines
in each process (the app factory calls it). :func:`protocol_class` picks the parser.
httptools costs a fraction of h11's CPU a request, which is what a GET waits for
behind a queue of ingests in the same event loop.
"""

from __future__ import annotations

import asyncio
import socket
from typing import Any, Callable

from uvicorn.protocols.http.h11_impl import H11Protocol


class _Deadlines:
    """The deadlines, for either of uvicorn's protocols (a mixin placed before it)."""

    header_timeout_s: float = 10.0
    body_timeout_s: float = 30.0
    on_timeout: Callable[[str], None] | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        # asyncio sets TCP_NODELAY only on sockets whose proto is IPPROTO_TCP; the listening
        # socket uvicorn hands to its worker processes comes back with proto 0, so without
        # this each response's body waited ~40 ms for the client's delayed ACK (Nagle)
        sock = transport.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass
        self._deadline: asyncio.TimerHandle | None = None
        self._deadline_kind = ""
        self._timed_cycle: Any = None
        self._arm("header", self.header_timeout_s, None)  # a connection that never sends is closed too

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        # the first byte of a new request on a kept-alive connection starts its head deadline
        if self._deadline is None and (self.cycle is None or self.cycle.response_complete):
            self._arm("header", self.header_timeout_s, self.cycle)
        super().data_received(data)

    def on_response_complete(self) -> None:
        self._disarm()  # idle from here on: uvicorn's keep-alive timeout applies
        super().on_response_complete()  # may start a pipelined request (handle_events)

    # ------------------------------------------------------------------ deadlines
    def _arm(self, kind: str, delay_s: float, cycle: Any) -> None:
        self._disarm()
        self._deadline_kind = kind
        self._deadline = self.loop.call_later(delay_s, self._late, kind, cycle)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        self._deadline_kind = ""

    def _late(self, kind: str, cycle: Any) -> None:
        self._deadline, self._deadline_kind = None, ""
        if self.transport.is_closing() or self.cycle is not cycle:
            return
        if kind == "body" and not cycle.more_body:
            return
        callback = type(self).on_timeout
        if callback is not None:
            callback(kind)
        self.transport.close()


class TimedH11Protocol(_Deadlines, H11Protocol):
    """uvicorn's ``H11Protocol`` with a request-head and a request-body deadline."""

    def handle_events(self) -> None:
        super().handle_events()
        cycle = self.cycle
        if cycle is None:
            return
        if cycle is not self._timed_cycle:  # a new request head is complete
            self._timed_cycle = cycle
            if cycle.more_body:
                self._arm("body", self.body_timeout_s, cycle)
            else:
                self._disarm()
        elif self._deadline_kind == "body" and not cycle.more_body:
            self._disarm()  # its body is complete


try:  # the C parser (uvicorn's own default when it is installed)
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:  # pragma: no cover - httptools is part of the 'service' extra
    HttpToolsProtocol = None  # type: ignore[assignment,misc]

if HttpToolsProtocol is not None:

    class TimedHttpToolsProtocol(_Deadlines, HttpToolsProtocol):  # type: ignore[misc,valid-type]
        """uvicorn's ``HttpToolsProtocol`` with a request-head and a request-body deadline."""

        def on_headers_complete(self) -> None:
            super().on_headers_complete()
            cycle = self.cycle  # the new request (queued behind the current one if pipelined)
            self._timed_cycle = cycle
            self._arm("body", self.body_timeout_s, cycle)  # disarmed when its message completes

        def on_message_complete(self) -> None:
            super().on_message_complete()
            if self._deadline_kind == "body":
                self._disarm()


def protocol_class(parser: str = "auto") -> type:
    """The timed protocol for ``parser``: ``httptools``, ``h11`` or ``auto`` (httptools
    when installed, else h11). Raises ``ValueError`` for httptools when it is missing."""
    if parser == "h11" or (parser == "auto" and HttpToolsProtocol is None):
        return TimedH11Protocol
    if HttpToolsProtocol is None:
        raise ValueError("http_parser = httptools, but httptools is not installed (pip install httptools)")
    if parser not in ("auto", "httptools"):
        raise ValueError(f"http_parser must be auto, httptools or h11, got {parser!r}")
    return TimedHttpToolsProtocol


def configure(header_timeout_s: float, body_timeout_s: float, on_timeout: Callable[[str], None] | None) -> None:
    """Set the deadlines (seconds) and the timeout callback for this process."""
    _Deadlines.header_timeout_s = float(header_timeout_s)
    _Deadlines.body_timeout_s = float(body_timeout_s)
    _Deadlines.on_timeout = staticmethod(on_timeout) if on_timeout is not None else None  # type: ignore[assignment]
