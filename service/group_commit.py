"""A writer thread that applies queued writes in *group commits* (SQLite and PostgreSQL).

Every write is a function ``op(conn) -> value`` queued with :meth:`GroupCommitStore._submit`,
which returns a ``Future``. The writer thread owns one writing connection. It takes
every write queued so far (up to ``group_commit_max_ops``), runs each inside its own
SAVEPOINT (a failing write, e.g. a 409 conflict, does not sink its neighbours; an op
marked ``one_statement`` that refuses in Python, not by a database error, needs none), then
COMMITs once and only then resolves the futures: an acknowledgement always follows a
durable commit.

A *storage* error (read-only, disk full, connection lost, deadlock) fails the whole
group with :class:`StorageUnavailable` (HTTP 503); the connection is dropped and opened
again for the next group, so the service recovers without a restart. The dialects
differ only in the hooks: how to connect, how to begin, which errors are storage
errors, and whether the database is still the one opened.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from concurrent.futures import Future
from typing import Any, Callable

from selfcal_service.storage import Storage, StorageUnavailable

log = logging.getLogger("selfcal.service.store")

_STOP = object()


def _resolve(fut: Future, ok: bool, value: Any) -> None:
    """Deliver a write's outcome; never raises (the writer thread must outlive any caller)."""
    if fut.done():
        return
    try:
        if ok:
            fut.set_result(value)
        else:
            fut.set_exception(value)
    except Exception:  # noqa: BLE001 - InvalidStateError: resolved meanwhile
        log.debug("a write's outcome was not delivered (its future was already resolved)")


class GroupCommitStore(Storage):
    """Base of the stores: the group-committing writer thread and its bookkeeping."""

    begin_sql = "BEGIN"

    def __init__(self, group_commit_max_ops: int = 512) -> None:
        self.group_commit_max_ops = group_commit_max_ops
        self._queue: "queue.SimpleQueue[Any]" = queue.SimpleQueue()
        self._writer: threading.Thread | None = None
        self.commits = 0  # transactions committed (for metrics)
        self.ops_committed = 0
        self.last_write_error: tuple[float, str] | None = None

    # ------------------------------------------------------------ dialect hooks
    def _writer_connect(self) -> Any:
        """A new writing connection (raises if the database cannot be reached)."""
        raise NotImplementedError

    def _close_writer(self, conn: Any) -> None:
        """Close a writing connection that failed (errors ignored)."""
        raise NotImplementedError

    def _is_storage_error(self, exc: BaseException) -> bool:
        """True if ``exc`` means the database cannot write (the whole group fails)."""
        raise NotImplementedError

    def _transaction_aborted(self, conn: Any) -> bool:
        """Whether the writer's transaction can no longer commit, after an op without its
        own savepoint raised (a dialect that runs such ops tells; otherwise assume so)."""
        return True

    def identity_problem(self) -> str | None:
        """Why the database is no longer the one opened, or None (SQLite checks its file)."""
        return None

    # ------------------------------------------------------------ lifecycle
    def _start_writer(self, name: str) -> None:
        self._writer = threading.Thread(target=self._write_loop, name=name, daemon=True)
        self._writer.start()

    def _stop_writer(self) -> None:
        if self._writer is not None:
            self._queue.put(_STOP)
            self._writer.join(timeout=30)
            self._writer = None

    def writer_alive(self) -> bool:
        return self._writer is not None and self._writer.is_alive()

    def _submit(self, fn: Callable[[Any], Any]) -> Future:
        fut: Future = Future()
        if self._writer is None:
            fut.set_exception(RuntimeError("storage is closed"))
            return fut
        self._queue.put((fn, fut))
        return fut

    def queue_depth(self) -> int:
        return self._queue.qsize()

    # ------------------------------------------------------------ the loop
    def _take_group(self, first: Any) -> tuple[list, bool]:
        ops = [first]
        stop = False
        while len(ops) < self.group_commit_max_ops:
            try:
                nxt = self._queue.get_nowait()
            except queue.Empty:
                break
            if nxt is _STOP:
                stop = True
                break
            ops.append(nxt)
        return ops, stop

    def _write_loop(self) -> None:
        conn = self._try_connect()  # None: connect again before the next group
        stop = False
        while not stop:
            item = self._queue.get()
            if item is _STOP:
                break
            ops, stop = self._take_group(item)
            # a write whose caller gave up while it was queued (a request's timeout cancels
            # the future) is dropped unwritten; the others can no longer be cancelled, so
            # their results are always delivered (a cancelled future refuses set_result:
            # that exception had killed this thread, and every later write hung)
            ops = [(fn, fut) for fn, fut in ops if fut.set_running_or_notify_cancel()]
            if not ops:
                continue
            results: list[tuple[Future, bool, Any]] = []
            try:
                problem = self.identity_problem()
                if problem:  # never acknowledge into an unlinked or foreign database
                    raise StorageUnavailable(problem)
                if conn is None:
                    conn = self._writer_connect()
                try:
                    conn.execute(self.begin_sql)
                except Exception as exc:  # noqa: BLE001 - nothing ran yet: a stale connection?
                    if not self._is_storage_error(exc):
                        raise
                    # the server restarted or dropped an idle connection: one fresh try
                    self._close_writer(conn)
                    conn = None
                    conn = self._writer_connect()
                    conn.execute(self.begin_sql)
                for fn, fut in ops:
                    if getattr(fn, "one_statement", False):
                        # one statement that refuses by its result, never by a database
                        # error: no savepoint (two round trips fewer); a database error
                        # would leave the transaction aborted, so it fails the group
                        try:
                            value = fn(conn)
                        except Exception as exc:
                            if self._is_storage_error(exc) or self._transaction_aborted(conn):
                                raise
                            results.append((fut, False, exc))  # refused in Python or by the driver: nothing to undo
                        else:
                            results.append((fut, True, value))
                        continue
                    conn.execute("SAVEPOINT op")
                    try:
                        value = fn(conn)
                    except Exception as exc:
                        if self._is_storage_error(exc):
                            raise  # read-only, full, I/O, connection: the whole group fails below
                        conn.execute("ROLLBACK TO SAVEPOINT op")  # one bad write must not sink the group
                        conn.execute("RELEASE SAVEPOINT op")
                        results.append((fut, False, exc))
                    else:
                        conn.execute("RELEASE SAVEPOINT op")
                        results.append((fut, True, value))
                conn.execute("COMMIT")
            except Exception as exc:
                reason = exc if isinstance(exc, StorageUnavailable) else StorageUnavailable(
                    f"database write failed: {type(exc).__name__}: {exc}")
                if self.last_write_error is None:  # log once per outage, not per request
                    log.error("storage unavailable: %s", reason)
                self.last_write_error = (time.time(), str(reason))
                if conn is not None:
                    try:
                        conn.execute("ROLLBACK")
                    except Exception:  # noqa: BLE001 - the connection may be gone
                        pass
                    # a fresh connection next time: the old one may keep a read-only or
                    # I/O error state (SQLite) or be broken (PostgreSQL)
                    self._close_writer(conn)
                conn = None  # connect again with the next group (lazily: no wait during an outage)
                for _, fut in ops:
                    _resolve(fut, False, reason)
                continue
            if self.last_write_error is not None:
                log.warning("storage writable again")
            self.last_write_error = None
            self.commits += 1
            self.ops_committed += len(ops)
            for fut, ok, value in results:  # only now: the commit is durable
                _resolve(fut, ok, value)
        if conn is not None:
            self._close_writer(conn)

    def _try_connect(self) -> Any:
        try:
            return self._writer_connect()
        except Exception:  # noqa: BLE001 - unreachable now; try again with the next write
            return None

    def probe_write(self, timeout_s: float = 2.0) -> str | None:
        """None if a write commits within ``timeout_s``, else why not (for /readyz)."""
        try:
            self._submit(self._probe_op).result(timeout=timeout_s)
        except Exception as exc:  # noqa: BLE001 - any failure is the answer
            return str(exc) or type(exc).__name__
        return None

    def _probe_op(self, conn: Any) -> None:
        raise NotImplementedError
