"""Reads on the event loop for PostgreSQL: a few psycopg ``AsyncConnection`` s per loop.

A read the routes run in a thread costs two thread hops and GIL hand-overs on a busy
API process; the hottest read (``GET /devices/{id}/calibration``) instead waits on its
socket in the event loop. What a thread read promises holds here too: a statement is
bounded by the server's ``statement_timeout`` and the connection's TCP keepalives (a
partitioned server fails a read in seconds, the loop never blocks on it), a broken
connection is replaced once (by a new one: a restarted server broke the idle ones
too), and a failure is :class:`StorageUnavailable` (the route's
503). At most ``limit`` reads of one loop hold a connection at a time; the others wait
their turn, so a burst of GETs never opens more connections than that.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any


def _finish(conn: Any) -> None:
    """Close ``conn`` without awaiting (safe after a cancellation, or with its loop gone)."""
    try:
        conn.pgconn.finish()
    except Exception:  # noqa: BLE001 - closing a broken connection
        pass


class AsyncReaders:
    """A small pool of ``AsyncConnection`` s, bound to the event loop that first uses it.

    ``connect_kwargs()`` gives psycopg's keyword arguments (the URL as ``conninfo``, the
    timeouts); ``limit`` bounds the reads in flight and the idle connections kept.
    """

    def __init__(self, connect_kwargs: Callable[[], dict[str, Any]], limit: int = 8):
        if limit < 1:
            raise ValueError(f"limit must be >= 1, got {limit}")
        self._connect_kwargs = connect_kwargs
        self.limit = limit
        self._turns = asyncio.Semaphore(limit)
        self._idle: list[Any] = []
        self._open: set[Any] = set()
        self._closed = False

    @property
    def connections(self) -> int:
        """Connections open now (idle or in a read)."""
        return len(self._open)

    async def _connect(self) -> Any:
        import psycopg

        conn = await psycopg.AsyncConnection.connect(**self._connect_kwargs())
        self._open.add(conn)
        return conn

    def _drop(self, conn: Any) -> None:
        if conn is not None:
            self._open.discard(conn)
            _finish(conn)

    async def read(self, sql: str, params: tuple | dict = ()) -> list[tuple]:
        """Run one statement and return its rows; a broken connection is replaced once.
        Raises :class:`StorageUnavailable` when the database cannot answer."""
        import psycopg

        from selfcal_service.storage import StorageUnavailable

        if self._closed:
            raise StorageUnavailable("database reads are closed (the service is stopping)")
        async with self._turns:
            for attempt in (0, 1):
                conn = self._idle.pop() if self._idle and not attempt else None
                try:
                    if conn is None:
                        conn = await self._connect()
                    cur = await conn.execute(sql, params)
                    rows = await cur.fetchall()
                except (psycopg.OperationalError, psycopg.InterfaceError) as exc:
                    broken = conn is None or conn.broken or conn.closed
                    self._drop(conn)  # never back into the pool
                    if attempt or not broken:  # a timeout or deadlock is not retried
                        raise StorageUnavailable(f"database read failed: {type(exc).__name__}: {exc}") from None
                    while self._idle:  # a restarted server broke them all: retry on a new one
                        self._drop(self._idle.pop())
                    continue
                except BaseException:  # a cancelled read leaves its connection mid-statement
                    self._drop(conn)
                    raise
                if self._closed or len(self._idle) >= self.limit:
                    self._drop(conn)
                else:
                    self._idle.append(conn)
                return rows
        return []  # pragma: no cover

    def close(self) -> None:
        """Close every connection (idle or not); later reads raise :class:`StorageUnavailable`."""
        self._closed = True
        for conn in list(self._open):
            self._drop(conn)
        self._idle.clear()
