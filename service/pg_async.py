"""Reads on the event loop for PostgreSQL: a few psycopg ``AsyncConnection`` s per loop.

A read the routes run in a thread costs two thread hops and GIL hand-overs on a busy
API process; the hottest read (``GET /devices/{id}/calibration``) instead waits on its
socket in the event loop. What a thread read promises holds here too:

* a statement is bounded by the server's ``statement_timeout`` and the connection's TCP
  keepalives (a partitioned server fails a read in seconds; the loop never blocks on it);
* a pooled connection found broken (a restarted server) is replaced once, by a new
  connection (the idle ones are dropped: the restart broke them too); a failed connect,
  a timeout or a deadlock is not retried;
* every database failure is :class:`StorageUnavailable` (the route's 503);
* after a failed connect while the pool has no connection open (the server is not
  reached), the reads that need a new connection fail at once for ``down_s`` instead
  of each waiting out its own connect timeout (with a connection open, the server is
  up: a failed connect, e.g. ``max_connections``, fails that read alone);
* a statement whose pooled connection broke is run again once, on a new connection:
  the statements are idempotent SELECTs, so a connection that died during its
  statement (not only before it) runs it twice.

At most ``limit`` statements of one loop hold a connection at a time; the other reads
wait their turn, so a burst of GETs never opens more connections than that. A read whose
caller is cancelled (a client gone, a shutdown) returns at once; its statement finishes in
the background (within ``statement_timeout``) on its own connection and slot, so no
connection is ever closed under a statement that is still running.
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Callable
from typing import Any


@functools.cache
def storage_errors() -> tuple[type[BaseException], ...]:
    """psycopg's exception classes of a database that cannot answer now (a 503; the others
    are bugs: a 500). Built once: every read checks against it."""
    import psycopg

    return psycopg.OperationalError, psycopg.InterfaceError, psycopg.InternalError


def _finish(conn: Any) -> None:
    """Close ``conn`` without awaiting (no statement of it may be running)."""
    try:
        conn.pgconn.finish()
    except Exception:  # noqa: BLE001 - closing a broken connection
        pass


class AsyncReaders:
    """A small pool of ``AsyncConnection`` s, bound to the event loop that first uses it.

    ``connect_kwargs()`` gives psycopg's keyword arguments (the URL as ``conninfo``, the
    timeouts); ``limit`` bounds the statements in flight and the idle connections kept;
    ``down_s``: how long after a failed connect reads fail fast. Not thread-safe: use it
    from its loop only (:meth:`close` from another thread via ``call_soon_threadsafe``).
    """

    def __init__(self, connect_kwargs: Callable[[], dict[str, Any]], limit: int = 8, down_s: float = 1.0):
        self._connect_kwargs = connect_kwargs
        self.limit = max(1, int(limit))
        self.down_s = down_s
        self._turns = asyncio.Semaphore(self.limit)
        self._idle: list[Any] = []
        self._open: set[Any] = set()
        self._closed = False
        self._down_until = 0.0
        self._down_reason = ""

    @property
    def connections(self) -> int:
        """Connections open now (idle or running a statement)."""
        return len(self._open)

    def _drop(self, conn: Any) -> None:
        if conn is not None:
            self._open.discard(conn)
            _finish(conn)

    async def _connect(self) -> Any:
        import psycopg

        from selfcal_service.storage import StorageUnavailable

        if self._closed:
            raise StorageUnavailable("database reads are closed (the service is stopping)")
        if time.monotonic() < self._down_until and not self._open:
            raise StorageUnavailable(f"database not reached (a connect failed just now: {self._down_reason})")
        try:
            conn = await psycopg.AsyncConnection.connect(**self._connect_kwargs())
        except psycopg.Error as exc:
            reason = f"{type(exc).__name__}: {exc}"
            if not self._open:  # no connection of ours works either: the server is not reached
                self._down_until = time.monotonic() + self.down_s
                self._down_reason = reason
            raise StorageUnavailable(f"database read failed: {reason}") from None
        if self._closed:  # closed while connecting
            _finish(conn)
            raise StorageUnavailable("database reads are closed (the service is stopping)")
        self._open.add(conn)
        return conn

    async def read(self, sql: str, params: tuple | dict = ()) -> list[tuple]:
        """Run one statement and return its rows. Raises :class:`StorageUnavailable` when
        the database cannot answer (see the module's docstring)."""
        from selfcal_service.storage import StorageUnavailable

        if self._closed:
            raise StorageUnavailable("database reads are closed (the service is stopping)")
        await self._turns.acquire()
        try:
            statement = asyncio.ensure_future(self._statement(sql, params))
        except BaseException:
            self._turns.release()
            raise
        statement.add_done_callback(self._statement_done)
        # a cancelled caller leaves at once; the statement ends on its own connection
        return await asyncio.shield(statement)

    def _statement_done(self, task: asyncio.Future) -> None:
        self._turns.release()
        if not task.cancelled():
            task.exception()  # retrieved: a caller that left is not told, nor is the loop

    async def _statement(self, sql: str, params: tuple | dict) -> list[tuple]:
        from selfcal_service.storage import StorageUnavailable

        errors = storage_errors()
        for attempt in (0, 1):
            pooled = bool(self._idle) and not attempt
            conn = self._idle.pop() if pooled else await self._connect()
            try:
                cur = await conn.execute(sql, params)
                rows = await cur.fetchall()
            except errors as exc:
                broken = conn.broken or conn.closed
                self._drop(conn)  # never back into the pool
                if not (pooled and broken) or self._closed:  # a timeout, a deadlock, a fresh connection
                    raise StorageUnavailable(f"database read failed: {type(exc).__name__}: {exc}") from None
                while self._idle:  # a restarted server broke them all: retry on a new one
                    self._drop(self._idle.pop())
                continue
            except BaseException:  # cancelled (the loop is stopping): it was mid-statement
                self._drop(conn)
                raise
            if self._closed or len(self._idle) >= self.limit:
                self._drop(conn)
            else:
                self._idle.append(conn)
            return rows
        raise AssertionError("unreachable")  # pragma: no cover

    def refuse(self) -> None:
        """Refuse new reads from now on (safe from any thread: it sets a flag)."""
        self._closed = True

    def close(self) -> None:
        """Refuse new reads and close the idle connections; a statement still running closes
        its own connection when it ends. The reads waiting for a turn are woken and refused.
        Call it in this pool's loop (or after it ended)."""
        self._closed = True
        while self._idle:
            self._drop(self._idle.pop())
        for _ in range(self.limit):  # each refused waiter passes its turn on to the next
            self._turns.release()

    def close_all(self) -> None:
        """:meth:`close`, and every other connection too: only once this pool's loop has
        ended (nothing can be running a statement on them)."""
        self.close()
        for conn in list(self._open):
            self._drop(conn)
