"""Test helpers: start/kill a ``selfcal serve`` subprocess, make sample batches."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent

KEYS = {
    "ingest": "ingest-key-0001",
    "read": "read-key-0001",
    "admin": "admin-key-0001",
    "all": "all-scopes-key-01",
}
KEY_SPEC = ",".join(
    [
        f"{KEYS['ingest']}=ingest",
        f"{KEYS['read']}=read",
        f"{KEYS['admin']}=admin",
        f"{KEYS['all']}=ingest+read+admin",
    ]
)


def backend() -> str:
    """The database the service tests run against: ``sqlite`` (default) or ``postgresql``
    (``SELFCAL_TEST_BACKEND=postgresql``; the session fixture starts a throw-away cluster)."""
    return os.environ.get("SELFCAL_TEST_BACKEND", "sqlite")


def backend_db(path: Path) -> str:
    """The ``--db`` argument for a test's database file: the path itself on SQLite, or a
    PostgreSQL database of its own (named from the path, created once) on PostgreSQL."""
    if backend() != "postgresql":
        return str(path)
    import hashlib

    import psycopg

    base = os.environ["SELFCAL_TEST_PG_URL"]
    name = "t_" + hashlib.sha1(str(Path(path).resolve()).encode()).hexdigest()[:16]
    with psycopg.connect(base + "/postgres", autocommit=True) as conn:
        if conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (name,)).fetchone() is None:
            conn.execute(f'CREATE DATABASE "{name}"')
    return f"{base}/{name}"


only_sqlite = __import__("pytest").mark.skipif(
    backend() == "postgresql", reason="SQLite-specific (its file, WAL, schema migration or filesystem faults)")
only_postgres = __import__("pytest").mark.skipif(
    backend() != "postgresql", reason="PostgreSQL scale-out (runs in the SELFCAL_TEST_BACKEND=postgresql pass)")


def auth(scope: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {KEYS[scope]}"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``python -m selfcal.cli serve --db DB --port P`` with a given calibrator."""

    def __init__(self, db: Path, tmp: Path, calibrator: str | None = None, extra_config: str = "", env: dict | None = None,
                 args: list[str] | None = None):
        self.db = Path(db)
        self.args = list(args or [])
        self.tmp = Path(tmp)
        self.calibrator = calibrator
        self.config = self.tmp / "test.toml"
        self.config.write_text(
            "[service]\nmax_body_bytes = 262144\nmax_batch_samples = 2000\n\n"
            "[fake]\npublish_after_samples = 200\n" + extra_config
        )
        self.env = dict(env or {})
        self.port = 0
        self.proc: subprocess.Popen | None = None
        self.log = self.tmp / "server.log"

    def child_env(self) -> dict[str, str]:
        """The environment of this server's processes (and of its ``selfcal worker`` processes)."""
        env = dict(os.environ)
        env["SELFCAL_API_KEYS"] = KEY_SPEC
        env["PYTHONPATH"] = os.pathsep.join([str(HERE), str(REPO), env.get("PYTHONPATH", "")])
        if self.calibrator:
            env["SELFCAL_CALIBRATOR"] = self.calibrator
        env.update(self.env)
        return env

    @property
    def db_arg(self) -> str:
        """What ``--db`` gets: the SQLite path, or (PostgreSQL run) that path's own database."""
        return backend_db(self.db)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 30.0) -> None:
        self.port = free_port()
        env = self.child_env()
        cmd = [sys.executable, "-m", "selfcal.cli", "serve", "--db", self.db_arg, "--port", str(self.port),
               "--config", str(self.config), "--log-level", "warning", *self.args]
        self._logfh = open(self.log, "ab")
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._logfh, stderr=subprocess.STDOUT, cwd=str(self.tmp))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}: {self.log.read_text()[-2000:]}")
            try:
                if httpx.get(self.url + "/healthz", timeout=1.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        self.kill9()
        raise RuntimeError(f"server did not come up: {self.log.read_text()[-2000:]}")

    def kill9(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=10)
        self.proc = None

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.kill9()
        self.proc = None

    def client(self, scope: str = "all", timeout_s: float = 10.0) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=auth(scope), timeout=timeout_s)

    def wait_settled(self, device_id: str, batches: int, samples_per_batch: int = 20,
                     timeout_s: float = 30.0) -> dict:
        """Poll GET calibration until the device has ``batches`` stored and every sample of
        them fed or rejected (``samples_processed + rejected_samples``); return the body."""
        with self.client("read") as c:
            deadline = time.monotonic() + timeout_s
            body: dict = {}
            while time.monotonic() < deadline:
                r = c.get(f"/devices/{device_id}/calibration")
                if r.status_code == 200:
                    body = r.json()
                    done = body["samples_processed"] + body["rejected_samples"]
                    if body["batches_stored"] == batches and done == batches * samples_per_batch:
                        return body
                time.sleep(0.05)
        raise AssertionError(f"{device_id} not settled: {body}")

    def wait_processed(self, device_id: str, seq: int, timeout_s: float = 60.0) -> dict:
        """Poll GET calibration until the worker has processed up to ``seq``."""
        with self.client("read") as c:
            deadline = time.monotonic() + timeout_s
            body = None
            while time.monotonic() < deadline:
                r = c.get(f"/devices/{device_id}/calibration")
                if r.status_code == 200:
                    body = r.json()
                    if body["processed_seq"] is not None and body["processed_seq"] >= seq:
                        return body
                time.sleep(0.05)
        raise AssertionError(f"{device_id}: not processed up to seq {seq} in {timeout_s} s; last {body}")


class WorkerProcess:
    """``python -m selfcal.cli worker --db URL`` with the server's config and calibrator."""

    def __init__(self, server: ServerProcess, name: str):
        self.server = server
        self.log = server.tmp / f"worker-{name}.log"
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        env = self.server.child_env()
        cmd = [sys.executable, "-m", "selfcal.cli", "worker", "--db", self.server.db_arg,
               "--config", str(self.server.config), "--log-level", "warning", "--status-every-s", "2"]
        self._logfh = open(self.log, "ab")
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._logfh, stderr=subprocess.STDOUT,
                                     cwd=str(self.server.tmp))

    def kill9(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.kill9()


def child_pids(pid: int, cmdline_has: str = "") -> list[int]:
    """The direct children of a process (Linux /proc) whose command line contains ``cmdline_has``."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            pass
    if cmdline_has:
        def cmdline(p: int) -> str:
            try:
                return Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                return ""
        out = [p for p in out if cmdline_has in cmdline(p)]
    return out


def batch_json(seq: int, n: int = 20, t0_s: float | None = None, rate_hz: float = 20.0, temp: bool = False,
               pressure_channels: int = 0, rng: np.random.Generator | None = None) -> dict:
    """A plausible batch: device lying flat, 20 Hz, times continuing from seq."""
    rng = rng or np.random.default_rng(seq)
    t0 = seq * n / rate_hz if t0_s is None else t0_s
    t = t0 + np.arange(n) / rate_hz
    body = {
        "seq": seq,
        "t_s": t.round(6).tolist(),
        "ax_g": (0.01 + 0.002 * rng.standard_normal(n)).tolist(),
        "ay_g": (-0.02 + 0.002 * rng.standard_normal(n)).tolist(),
        "az_g": (1.0 + 0.002 * rng.standard_normal(n)).tolist(),
    }
    if temp:
        body["temp_c"] = (25.0 + 0.1 * rng.standard_normal(n)).tolist()
    if pressure_channels:
        body["pressure_kpa"] = (20.0 + rng.random((n, pressure_channels))).tolist()
    return body


def t_ms_sum(body: dict) -> int:
    return int(np.round(np.asarray(body["t_s"]) * 1000.0).astype(np.int64).sum())
