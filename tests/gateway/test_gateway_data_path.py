"""The gateway's packet-to-spool path without a radio: a full disk, a temperature the
service would refuse, a restart whose leftover batches are acknowledged first, and ids."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from selfcal.gateway import codec
from selfcal.gateway.gateway import SPOOL_RETRY_MAX_BATCHES, Gateway, _Link
from selfcal.gateway.spool import Spool


def _gateway(path, **config) -> Gateway:
    gw = Gateway("http://service.test", "k", spool_path=path, config={"batch_max_samples": 20, **config})
    gw._spool = Spool(path)  # (what start() opens; no radio, no forwarder here)
    return gw


def _connect(gw: Gateway, device_id: str = "ins-1"):
    info = codec.DeviceInfo(device_id=device_id, firmware="1", sample_rate_hz=20.0, max_samples_per_packet=10)
    return gw._device(info, _Link(address="AA:BB", ble_device=None, last_seen=0.0))


def _feed(gw: Gateway, dev, index: int, n: int = 10, temp_c: float = 25.0) -> None:
    acc = np.tile([0.0, 0.0, 1.0], (n, 1))
    gw._on_packet(dev, bytearray(codec.encode_packet(index, acc, np.full((n, 4), 20.0), temp_c)))


def _bodies(gw: Gateway, device_id: str = "ins-1") -> list[dict]:
    rows = gw._spool._db.execute("SELECT body FROM batches WHERE device_id = ? ORDER BY seq", (device_id,))
    return [json.loads(r[0]) for r in rows]


def test_samples_the_spool_cannot_store_stay_open_and_are_stored_later(tmp_path):
    """A full disk: the batch's buffers were emptied before the write, and its samples
    vanished uncounted. They now stay open, are stored (in batches of the usual size) once
    the spool writes again, and only past a bound are the oldest dropped, counted."""
    gw = _gateway(tmp_path / "s.db")
    dev = _connect(gw)
    real = gw._spool.put_batch

    def full(*a, **k):
        raise sqlite3.OperationalError("database or disk is full")

    gw._spool.put_batch = full
    for k in range(3):
        _feed(gw, dev, 10 * k)
    stats = gw.stats()["devices"]["ins-1"]
    assert stats["spool_errors"] == 2 and stats["open_batch_samples"] == 30 and stats["samples_dropped"] == 0
    gw._spool.put_batch = real
    _feed(gw, dev, 30)
    t = [b["t_s"] for b in _bodies(gw)]
    assert [len(x) for x in t] == [20, 20] and sum(t, [])[0] == 0.0  # every sample, in batches of 20
    assert np.allclose(np.diff(sum(t, [])), 0.05)
    gw._spool.put_batch = full  # a long outage: memory stays bounded
    for k in range(4, 4 + 2 * SPOOL_RETRY_MAX_BATCHES + 4):
        _feed(gw, dev, 10 * k)
    stats = gw.stats()["devices"]["ins-1"]
    assert stats["open_batch_samples"] <= SPOOL_RETRY_MAX_BATCHES * 20 + 10
    assert stats["samples_dropped"] + stats["open_batch_samples"] + 40 == stats["samples_received"]


def test_a_temperature_outside_the_services_range_drops_only_the_temperatures(tmp_path):
    """The packet's temperature field holds -327..327 degC, the service takes -40..85: one
    sentinel reading had the whole batch refused (422), its acceleration with it."""
    gw = _gateway(tmp_path / "s.db")
    dev = _connect(gw)
    _feed(gw, dev, 0)
    _feed(gw, dev, 10, temp_c=90.0)
    _feed(gw, dev, 20)
    _feed(gw, dev, 30)
    first, second = _bodies(gw)
    assert "temp_c" not in first and len(first["t_s"]) == 20  # sent, without its temperatures
    assert second["temp_c"] == [25.0] * 20
    assert gw.stats()["devices"]["ins-1"]["temp_dropped"] == 1


def test_a_restart_keeps_the_devices_timeline_when_its_leftovers_are_acknowledged_first(tmp_path):
    """The insole rebooted in the last run (its sample index restarted; the spool keeps the
    unwrapping offset). After a restart the forwarder acknowledged the leftover batches
    before the insole reconnected, which made the device's state with a fresh tracker:
    its time jumped back to 0."""
    path = tmp_path / "s.db"
    gw = _gateway(path)
    dev = _connect(gw)
    for index in (5000, 5010, 0, 10):  # 20 samples, then the insole restarts its index
        _feed(gw, dev, index)
    gw._spool.close()
    gw = _gateway(path)
    gw._on_ack("ins-1", 20, False)  # a leftover batch acknowledged before the insole is back
    dev = _connect(gw)
    _feed(gw, dev, 20)
    _feed(gw, dev, 30)
    starts = [b["t_s"][0] for b in _bodies(gw)]
    assert starts == [250.0, 251.0, 252.0]  # (5000 / 20 Hz on, never back)


@pytest.mark.parametrize("device_id, ok", [("ins-1", True), ("a:b.c_d-9", True), ("..", False), ("-x", False),
                                            (".hidden", False), ("x" * 64, True), ("x" * 65, False)])
def test_device_ids_follow_the_services_rule(device_id, ok):
    """``..`` was accepted and became another URL path (404, retried for ever)."""
    if ok:
        assert codec.validate_device_id(device_id) == device_id
    else:
        with pytest.raises(codec.CodecError):
            codec.validate_device_id(device_id)


def test_the_gateways_rules_are_the_services():
    service_schemas = pytest.importorskip("selfcal_service.schemas")
    from selfcal.gateway import gateway

    assert codec._DEVICE_ID_RE.pattern == service_schemas.DEVICE_ID_PATTERN
    assert (gateway.TEMP_MIN_C, gateway.TEMP_MAX_C) == (service_schemas.TEMP_MIN_C, service_schemas.TEMP_MAX_C)
    settings = pytest.importorskip("selfcal_service.settings")
    le = [m.le for m in gateway.GatewayConfig.model_fields["batch_max_samples"].metadata if hasattr(m, "le")]
    assert le == [settings.Settings.model_fields["max_batch_samples"].default]  # (a larger batch: 413 for good)


def _times(gw: Gateway, device_id: str = "ins-1") -> list[float]:
    return sum((b["t_s"] for b in _bodies(gw, device_id)), [])


_CRASHING_RUN = """
import os, signal, sys
import numpy as np
from selfcal.gateway import codec
from selfcal.gateway.gateway import Gateway, _Link
from selfcal.gateway.spool import Spool

gw = Gateway("http://service.test", "k", spool_path=sys.argv[1], config={"batch_max_samples": 20})
gw._spool = Spool(sys.argv[1])
info = codec.DeviceInfo(device_id="ins-1", firmware="1", sample_rate_hz=20.0, max_samples_per_packet=10)
dev = gw._device(info, _Link(address="AA:BB", ble_device=None, last_seen=0.0))
def feed(index, n=10):
    gw._on_packet(dev, bytearray(codec.encode_packet(index, np.tile([0.0, 0.0, 1.0], (n, 1)),
                                                      np.full((n, 4), 20.0), 25.0)))
for index in (0, 10, 20, 30, 40):  # 2 batches of 20 spooled, 10 samples open
    feed(index)
gw._journal_open()  # (the batch timer's tick)
feed(50, n=5)  # received after the last journal write: lost in the crash
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_gateway_loses_only_the_samples_received_since_the_last_journal_write(tmp_path):
    """``kill -9`` (or a power cut) lost every insole's open batch: up to
    ``batch_max_samples`` or ``batch_max_age_s`` of samples. The open batches are now
    journalled every ``journal_every_s``; the next start spools what was journalled, once,
    and the insole's timeline goes on where the journal left it."""
    import subprocess
    import sys

    path = tmp_path / "s.db"
    run = subprocess.run([sys.executable, "-c", _CRASHING_RUN, str(path)], capture_output=True, text=True)
    assert run.returncode == -9, run.stderr
    gw = _gateway(path)
    gw._recover_open()
    assert _times(gw) == [i / 20 for i in range(50)]  # the 10 journalled samples too, none twice
    assert gw.stats()["devices"]["ins-1"]["samples_recovered"] == 10
    assert gw._spool._db.execute("SELECT COUNT(*) FROM open_samples").fetchone()[0] == 0
    dev = _connect(gw)
    _feed(gw, dev, 55)  # the insole goes on: samples 50..54 were lost in the crash, counted as a gap
    _feed(gw, dev, 65)
    assert _times(gw)[50:] == [i / 20 for i in range(55, 75)]
    assert gw.stats()["devices"]["ins-1"]["samples_lost"] == 5
    gw._spool.close()
    gw = _gateway(path)
    gw._recover_open()  # a second start recovers nothing more
    assert len(_times(gw)) == 70 and gw.stats()["devices"] == {}


def test_journalled_samples_a_stored_batch_holds_are_not_recovered_again(tmp_path):
    """A batch's commit deletes the journal rows it covers, and a row it covers only in
    part (its samples split into batches after a full disk) gives back only the rest."""
    path = tmp_path / "s.db"
    gw = _gateway(path)
    dev = _connect(gw)
    _feed(gw, dev, 0)
    gw._journal_open()
    _feed(gw, dev, 10)  # a batch of 20: the journal row of 0..9 goes with its commit
    assert gw._spool._db.execute("SELECT COUNT(*) FROM open_samples").fetchone()[0] == 0
    real = gw._spool.put_batch

    def full(*a, **k):
        raise sqlite3.OperationalError("database or disk is full")

    gw._spool.put_batch = full
    for index in (20, 30, 40):  # 30 samples open, journalled in one row
        _feed(gw, dev, index)
    gw._journal_open()
    calls = []

    def once(*a, **k):  # the disk fills again after one batch
        calls.append(1)
        if len(calls) > 1:
            full()
        return real(*a, **k)

    gw._spool.put_batch = once
    _feed(gw, dev, 50)  # 20..39 stored; 40..59 kept open (40..49 journalled)
    assert _times(gw) == [i / 20 for i in range(40)]
    gw._spool.close()  # the crash
    gw = _gateway(path)
    gw._recover_open()
    assert _times(gw) == [i / 20 for i in range(50)]  # 40..49 once; 50..59 were never journalled


def test_a_spool_of_an_earlier_release_is_opened_and_its_batches_kept(tmp_path):
    path = tmp_path / "old.db"
    db = sqlite3.connect(path)
    db.executescript("""
        CREATE TABLE devices (device_id TEXT PRIMARY KEY, next_batch_seq INTEGER NOT NULL, last_count INTEGER,
                              count_offset INTEGER NOT NULL DEFAULT 0);
        CREATE TABLE batches (id INTEGER PRIMARY KEY AUTOINCREMENT, device_id TEXT NOT NULL, seq INTEGER NOT NULL,
                              n_samples INTEGER NOT NULL, body BLOB NOT NULL, created_s REAL NOT NULL,
                              attempts INTEGER NOT NULL DEFAULT 0, UNIQUE (device_id, seq));
        INSERT INTO devices VALUES ('ins-1', 1, 19, 0);
        INSERT INTO batches (device_id, seq, n_samples, body, created_s) VALUES ('ins-1', 0, 20, x'7b7d', 0);
    """)
    db.commit()
    db.close()
    gw = _gateway(path)
    gw._recover_open()
    assert gw._spool.depth() == {"ins-1": (1, 20)}
    dev = _connect(gw)
    _feed(gw, dev, 20)
    _feed(gw, dev, 30)
    assert [b["seq"] for b in _bodies(gw)[1:]] == [1] and _bodies(gw)[1]["t_s"][0] == 1.0
