"""Prometheus text-format metrics without a client library (counters, gauges, histograms).

With several API processes (``selfcal serve --workers N``) a scrape reaches one of them.
Each process then also writes its counters and histograms to ``<shared_dir>/<pid>.json``
about once a second, and :meth:`Metrics.render` adds up every process's file (a dead
process's last file stays, so counters never go backwards; ``serve`` empties the folder
when it starts). Gauges read from the shared database (backlog) are global. The others
(queue depths, leases) are per process: each comes with a ``pid`` label, one line per
live process (a file written in the last ``GAUGE_FRESH_S``; a dead process's gauges go
away, its counters stay). A ``selfcal worker`` given the same folder (``[service]
metrics_dir``) adds its refit counters and its gauges.
"""

from __future__ import annotations

import json
import os
import threading
import time
import uuid
from pathlib import Path
from typing import Callable

#: A process's gauges count when its shared file is at most this old (s): it rewrites it every second.
GAUGE_FRESH_S = 5.0

#: Request-latency histogram buckets (s).
LATENCY_BUCKETS_S = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5)


def _count(h: list[float], value_s: float) -> None:
    """Add one observation (s) to a histogram ``[bucket counts…, count, sum]``."""
    for i, edge in enumerate(LATENCY_BUCKETS_S):
        if value_s <= edge:
            h[i] += 1
            break
    h[-2] += 1
    h[-1] += value_s


def _labels(labels: tuple[tuple[str, str], ...]) -> str:
    if not labels:
        return ""
    inner = ",".join(f'{k}="{v}"' for k, v in labels)
    return "{" + inner + "}"


class Metrics:
    """A small registry; increments are thread-safe (one lock, tiny critical sections)."""

    HELP = {
        "selfcal_ingest_samples_total": ("counter", "samples stored (duplicates excluded)"),
        "selfcal_ingest_batches_total": ("counter", "batches stored (duplicates excluded)"),
        "selfcal_ingest_duplicates_total": ("counter", "resent batches acknowledged, not stored again"),
        "selfcal_ingest_rejected_total": ("counter", "rejected sample batches by HTTP status"),
        "selfcal_worker_samples_total": ("counter", "samples fed to calibrators"),
        "selfcal_worker_cycles_total": ("counter", "refit-worker cycles committed"),
        "selfcal_worker_checkpoints_total": ("counter", "cycles that also wrote the device's calibrator state (a checkpoint)"),
        "selfcal_worker_checkpoint_patches_total": ("counter", "checkpoints written as a patch against the stored base"),
        "selfcal_worker_checkpoint_bytes_total": ("counter", "bytes of calibrator state written as checkpoints (full states and patches)"),
        "selfcal_worker_evictions_total": ("counter", "calibrators dropped from memory beyond cache_max_devices (written first if ahead)"),
        "selfcal_worker_replays_total": ("counter", "calibrators restored from a checkpoint with the batches fed since fed again"),
        "selfcal_worker_replayed_samples_total": ("counter", "samples fed again in restores (not counted in selfcal_worker_samples_total)"),
        "selfcal_refits_total": ("counter", "refit outcomes by outcome (published or typed reason)"),
        "selfcal_worker_errors_total": ("counter", "worker cycles that failed (retried)"),
        "selfcal_rejected_batches_total": ("counter", "stored batches not fed, by reason (late, calibrator)"),
        "selfcal_rejected_samples_total": ("counter", "samples of stored batches not fed, by reason"),
        "selfcal_ingest_conflicts_total": ("counter", "resent seqs with other content (409)"),
        "selfcal_storage_unavailable_total": ("counter", "requests refused because storage could not write (503)"),
        "selfcal_clock_resets_total": ("counter", "device clocks that went backwards between batches"),
        "selfcal_worker_queue_depth": ("gauge", "devices waiting for their worker"),
        "selfcal_worker_leases": ("gauge", "devices leased by this process's refit worker (PostgreSQL)"),
        "selfcal_worker_lease_repairs_total": ("counter", "leases a worker's view disagreed with the database on, "
                                                          "by kind (orphan: held in the database only, released; "
                                                          "lost: another worker's now, forgotten)"),
        "selfcal_worker_conflicts_total": ("counter", "worker cycles dropped: the device changed elsewhere or the lease was lost"),
        "selfcal_backlog_batches": ("gauge", "stored batches not yet fed nor rejected (all devices)"),
        "selfcal_backlog_oldest_age_seconds": ("gauge", "age of the oldest stored batch not yet fed nor rejected"),
        "selfcal_db_write_queue_depth": ("gauge", "writes waiting for the SQLite writer"),
        "selfcal_db_commits_total": ("counter", "SQLite transactions committed (group commits)"),
        "selfcal_db_writes_total": ("counter", "writes committed (batches, worker cycles, versions)"),
        "selfcal_http_timeouts_total": ("counter", "connections closed for a slow request head or body, by kind"),
        "selfcal_http_internal_errors_total": ("counter", "unexpected exceptions answered with 500"),
        "selfcal_http_request_duration_seconds": ("histogram", "request latency by route and status class"),
        "selfcal_gc_pause_seconds": ("histogram", "pauses of the cyclic garbage collector by generation and role "
                                                  "(api: a process that answers requests; worker: selfcal worker): "
                                                  "every thread of the process waits (summed over the processes)"),
    }

    def __init__(self, shared_dir: str | Path | None = None) -> None:
        self._lock = threading.Lock()
        self._counters: dict[tuple[str, tuple[tuple[str, str], ...]], float] = {}
        self._hist: dict[tuple[str, tuple[tuple[str, str], ...]], list[float]] = {}
        self._gauges: dict[str, Callable[[], float]] = {}
        self._local_gauges: dict[str, Callable[[], float]] = {}
        self._counter_fns: dict[str, Callable[[], float]] = {}
        # one file per process life: a later process with the same pid does not overwrite it
        self._file = f"{os.getpid()}-{uuid.uuid4().hex[:8]}.json"
        self.shared_dir = Path(shared_dir) if shared_dir else None
        if self.shared_dir is not None:
            self.shared_dir.mkdir(parents=True, exist_ok=True)
            threading.Thread(target=self._publish_loop, name="selfcal-metrics", daemon=True).start()

    def track_gc(self, role: str = "api") -> None:
        """Time every cyclic garbage collection of this process into ``selfcal_gc_pause_seconds``
        (one histogram per generation, labelled ``role``: ``api`` for a process that answers
        requests, ``worker`` for ``selfcal worker``, whose pauses stall no request). The
        callback runs inside whichever thread triggered the collection, possibly while that
        thread holds this registry's lock, so it takes no lock: under the GIL an update can
        at worst lose a count to a concurrent one."""
        import gc

        started = [0.0]
        hists = {g: [0.0] * (len(LATENCY_BUCKETS_S) + 2) for g in (0, 1, 2)}
        for g, h in hists.items():
            self._hist[("selfcal_gc_pause_seconds", (("generation", str(g)), ("role", role)))] = h

        def on_gc(phase: str, info: dict) -> None:
            if phase == "start":
                started[0] = time.perf_counter()
                return
            h = hists.get(info.get("generation"))
            if h is None:
                return
            _count(h, time.perf_counter() - started[0])

        gc.callbacks.append(on_gc)
        self._gc_callback = on_gc

    def untrack_gc(self) -> None:
        """Remove the callback of :meth:`track_gc` (at shutdown; tests make many apps)."""
        import gc

        cb = getattr(self, "_gc_callback", None)
        if cb is not None and cb in gc.callbacks:
            gc.callbacks.remove(cb)
        self._gc_callback = None

    # ------------------------------------------------------------ several processes
    def counter_from(self, name: str, fn: Callable[[], float]) -> None:
        """A counter whose value this process reads from ``fn`` (e.g. its store's commits);
        summed over processes like the others."""
        self._counter_fns[name] = fn

    def _own_counters(self) -> dict:
        with self._lock:
            counters = dict(self._counters)
        for name, fn in self._counter_fns.items():
            try:
                counters[(name, ())] = float(fn())
            except Exception:  # noqa: BLE001 - a source that fails counts as nothing new
                pass
        return counters

    def _own_gauges(self) -> dict[str, float]:
        """This process's per-process gauges, read now (nan when a source fails)."""
        out = {}
        for name, fn in self._local_gauges.items():
            try:
                out[name] = float(fn())
            except Exception:  # noqa: BLE001 - the scrape still answers
                out[name] = float("nan")
        return out

    def _snapshot(self) -> dict:
        counters = self._own_counters()
        with self._lock:
            hist = [[k[0], list(k[1]), v] for k, v in self._hist.items()]
        return {"counters": [[k[0], list(k[1]), v] for k, v in counters.items()], "hist": hist,
                "pid": os.getpid(), "gauges": self._own_gauges()}

    def publish(self) -> None:
        """Write this process's counters and histograms to the shared folder (atomically)."""
        if self.shared_dir is None:
            return
        path = self.shared_dir / self._file
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self._snapshot()))
        os.replace(tmp, path)

    def _publish_loop(self) -> None:
        stop = threading.Event()
        while not stop.wait(1.0):
            try:
                self.publish()
            except OSError:  # the folder went away (shutdown): nothing to share any more
                return

    def _merged(self) -> tuple[dict, dict, dict]:
        """Counters and histograms of this process plus every other process's last file, and
        the per-process gauges ``{(name, pid): value}`` of this process and the live others."""
        counters = self._own_counters()
        with self._lock:
            hist = {k: list(v) for k, v in self._hist.items()}
        gauges = {(name, str(os.getpid())): v for name, v in self._own_gauges().items()}
        if self.shared_dir is None:
            return counters, hist, gauges
        own = self._file
        now = time.time()
        for f in self.shared_dir.glob("*.json"):
            if f.name == own:
                continue
            try:
                fresh = now - f.stat().st_mtime <= GAUGE_FRESH_S
                other = json.loads(f.read_text())
            except (OSError, ValueError):
                continue  # being replaced right now: its next version counts next time
            if fresh:
                for name, value in (other.get("gauges") or {}).items():
                    gauges[(name, str(other.get("pid", f.name.split("-")[0])))] = value
            for name, labels, value in other["counters"]:
                key = (name, tuple(tuple(x) for x in labels))
                counters[key] = counters.get(key, 0.0) + value
            for name, labels, values in other["hist"]:
                key = (name, tuple(tuple(x) for x in labels))
                mine = hist.setdefault(key, [0.0] * len(values))
                hist[key] = [a + b for a, b in zip(mine, values)]
        return counters, hist, gauges

    def inc(self, name: str, value: float = 1.0, **labels: str) -> None:
        key = (name, tuple(sorted(labels.items())))
        with self._lock:
            self._counters[key] = self._counters.get(key, 0.0) + value

    def get(self, name: str, **labels: str) -> float:
        return self._counters.get((name, tuple(sorted(labels.items()))), 0.0)

    def gauge(self, name: str, fn: Callable[[], float], per_process: bool = True) -> None:
        """A gauge read from ``fn`` at every scrape. ``per_process``: this process's own value
        (shown with a ``pid`` label beside the other live processes'); False: a global value
        (read from the shared database), shown once without a label."""
        (self._local_gauges if per_process else self._gauges)[name] = fn

    def observe(self, name: str, value_s: float, **labels: str) -> None:
        key = (name, tuple(sorted(labels.items())))
        with self._lock:
            h = self._hist.get(key)
            if h is None:
                h = self._hist[key] = [0.0] * (len(LATENCY_BUCKETS_S) + 2)  # buckets, count, sum
            _count(h, value_s)

    def render(self) -> str:
        lines: list[str] = []
        counters, hist, local = self._merged()
        for name, (kind, help_text) in self.HELP.items():
            lines.append(f"# HELP {name} {help_text}")
            lines.append(f"# TYPE {name} {kind}")
            if name in self._gauges:  # value read from a callable (gauge or counter)
                try:
                    value = float(self._gauges[name]())
                except Exception:  # noqa: BLE001 - e.g. the database is down: the scrape still answers
                    value = float("nan")
                lines.append(f"{name} {value:g}")
            elif kind == "counter":
                rows = [(k[1], v) for k, v in counters.items() if k[0] == name] or [((), 0.0)]
                for labels, value in sorted(rows):
                    lines.append(f"{name}{_labels(labels)} {value:g}")
            elif kind == "gauge":
                rows = sorted((pid, v) for (g, pid), v in local.items() if g == name)
                for pid, value in rows:
                    lines.append(f"{name}{_labels((('pid', pid),))} {value:g}")
            else:
                for (hname, labels), h in sorted(hist.items()):
                    if hname != name:
                        continue
                    cum = 0.0
                    for i, edge in enumerate(LATENCY_BUCKETS_S):
                        cum += h[i]
                        lines.append(f"{name}_bucket{_labels(labels + (('le', f'{edge:g}'),))} {cum:g}")
                    lines.append(f"{name}_bucket{_labels(labels + (('le', '+Inf'),))} {h[-2]:g}")
                    lines.append(f"{name}_count{_labels(labels)} {h[-2]:g}")
                    lines.append(f"{name}_sum{_labels(labels)} {h[-1]:.6f}")
        return "\n".join(lines) + "\n"
