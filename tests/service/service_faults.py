"""Storage faults and corrupt bodies for the service tests (root-only parts probe first).

* read-only database: ``chattr +i`` on the database and its WAL (not ``-shm``: it is
  mmap-ed, and an immutable mapping raises SIGBUS);
* full disk: a small tmpfs, filled by one file;
* a bit flipped in a binary batch.
"""

from __future__ import annotations

import os
import random
import shutil
import subprocess
from pathlib import Path


def chattr(paths, flag: str) -> bool:
    """``chattr flag`` on every existing path; True if all succeeded."""
    if shutil.which("chattr") is None:
        return False
    return all(subprocess.run(["chattr", flag, str(p)], capture_output=True).returncode == 0
               for p in paths if Path(p).exists())


def database_files(db: Path) -> list[Path]:
    """The files to make immutable for a read-only database."""
    return [Path(db), Path(str(db) + "-wal")]


def can_chattr() -> bool:
    """Root, and a filesystem under TMPDIR with the immutable flag."""
    if os.geteuid() != 0:
        return False
    probe = Path(os.environ.get("TMPDIR", "/tmp")) / f"selfcal-chattr-probe-{os.getpid()}"
    probe.write_text("x")
    ok = chattr([probe], "+i")
    chattr([probe], "-i")
    probe.unlink()
    return ok


def mount_tmpfs(path: Path, size: str) -> bool:
    """Mount a tmpfs of ``size`` (e.g. ``"4m"``) at ``path``; True if it worked."""
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                          capture_output=True).returncode == 0


def unmount(path: Path) -> None:
    subprocess.run(["umount", "-l", str(path)], check=False)


def can_mount() -> bool:
    """Root, and tmpfs mounts allowed here."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    probe = Path("/tmp") / f"selfcal-mount-probe-{os.getpid()}"
    probe.mkdir(exist_ok=True)
    ok = mount_tmpfs(probe, "1m")
    if ok:
        unmount(probe)
    probe.rmdir()
    return ok


def fill_disk(folder: Path) -> Path:
    """Write one file in ``folder`` until its filesystem is full; return the file."""
    filler = Path(folder) / "filler"
    # unbuffered: a buffered file re-raised ENOSPC from its final flush in close(), outside
    # the loop's handler, and the chaos test failed now and then on that
    with open(filler, "wb", buffering=0) as fh:
        for size in (65536, 4096, 512, 1):  # fill to the last byte the filesystem gives
            try:
                while True:
                    fh.write(b"\0" * size)
            except OSError:
                pass
    return filler


def flip_bit(raw: bytes, rng: random.Random) -> bytes:
    """``raw`` with one random bit flipped."""
    buf = bytearray(raw)
    bit = rng.randrange(len(buf) * 8)
    buf[bit // 8] ^= 1 << (bit % 8)
    return bytes(buf)
