"""A throw-away PostgreSQL cluster for tests and benchmarks: initdb + pg_ctl on a temp dir.

    with PgCluster() as pg:            # or pg = PgCluster(); pg.start(); ...; pg.stop()
        url = pg.create_database("t1")  # postgresql://selfcal@127.0.0.1:PORT/t1

The server binaries come from ``PATH`` or ``/usr/lib/postgresql/*/bin`` (Debian's
``postgresql`` package; ``scripts/postgres.sh`` installs it). PostgreSQL refuses to run
as root, so as root the cluster runs as the ``postgres`` user that package creates.
:func:`unavailable` says why a cluster cannot be had here (None if it can).
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

USER = "selfcal"


def pg_bin_dir() -> Path | None:
    """The folder holding ``initdb`` and ``pg_ctl`` (newest version), or None."""
    found = shutil.which("pg_ctl")
    if found and shutil.which("initdb"):
        return Path(os.path.realpath(found)).parent
    dirs = sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda d: int(Path(d).parent.name.split(".")[0]))
    for d in reversed(dirs):
        if (Path(d) / "pg_ctl").exists() and (Path(d) / "initdb").exists():
            return Path(d)
    return None


def _run_as() -> list[str]:
    """Command prefix to run the server as a non-root user (PostgreSQL refuses root)."""
    if os.geteuid() != 0:
        return []
    return ["runuser", "-u", "postgres", "--"]


def unavailable() -> str | None:
    """Why no cluster can be started here, or None."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "psycopg is not installed (pip install -e '.[dev]')"
    if pg_bin_dir() is None:
        return "no PostgreSQL server binaries (initdb, pg_ctl): run scripts/postgres.sh (apt-get install postgresql)"
    if os.geteuid() == 0:
        if shutil.which("runuser") is None:
            return "running as root without runuser: cannot start PostgreSQL as another user"
        try:
            import pwd

            pwd.getpwnam("postgres")
        except KeyError:
            return "running as root and there is no 'postgres' user to run the server as"
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PgCluster:
    """One PostgreSQL server on 127.0.0.1 and a free port, its data in a temp dir."""

    def __init__(self, max_connections: int = 300) -> None:
        self.max_connections = max_connections
        self.dir: Path | None = None
        self.port = 0
        self.bin: Path | None = None

    @property
    def base_url(self) -> str:
        return f"postgresql://{USER}@127.0.0.1:{self.port}"

    def start(self) -> "PgCluster":
        why = unavailable()
        if why:
            raise RuntimeError(why)
        self.bin = pg_bin_dir()
        self.dir = Path(tempfile.mkdtemp(prefix="selfcal-pg-"))
        data, sock = self.dir / "data", self.dir / "sock"
        sock.mkdir()
        prefix = _run_as()
        if prefix:  # the server's user must own its folder
            shutil.chown(self.dir, "postgres")
            shutil.chown(sock, "postgres")
        subprocess.run(prefix + [str(self.bin / "initdb"), "-D", str(data), "-U", USER, "-A", "trust",
                                 "--no-sync", "-E", "UTF8"], check=True, capture_output=True)
        self.port = _free_port()
        opts = (f"-p {self.port} -c listen_addresses=127.0.0.1 -c unix_socket_directories={sock} "
                f"-c max_connections={self.max_connections} -c shared_buffers=64MB")
        subprocess.run(prefix + [str(self.bin / "pg_ctl"), "-D", str(data), "-l", str(self.dir / "server.log"),
                                 "-o", opts, "-w", "-t", "60", "start"], check=True, capture_output=True)
        return self

    def create_database(self, name: str) -> str:
        """Create database ``name`` (if missing); return its URL."""
        import psycopg

        with psycopg.connect(self.base_url + "/postgres", autocommit=True) as conn:
            if conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (name,)).fetchone() is None:
                conn.execute(f'CREATE DATABASE "{name}"')
        return f"{self.base_url}/{name}"

    def stop(self) -> None:
        if self.dir is None:
            return
        subprocess.run(_run_as() + [str(self.bin / "pg_ctl"), "-D", str(self.dir / "data"), "-m", "immediate",
                                    "-w", "stop"], capture_output=True)
        shutil.rmtree(self.dir, ignore_errors=True)
        self.dir = None

    def __enter__(self) -> "PgCluster":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
