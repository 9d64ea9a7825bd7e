"""``selfcal demo``: the whole system end to end on one machine.

What runs (``docs/demo.md``):

* the **service** as a real subprocess (``python -m selfcal.cli serve``) on 127.0.0.1,
  a free port, a SQLite database in a temporary folder and freshly generated API keys
  (``SELFCAL_API_KEYS`` in its environment, never on a command line);
* N **virtual insoles** (bumble BLE peripherals, :mod:`selfcal.gateway.virtual`), each
  streaming its own simulated wearer (:class:`selfcal.sim.Simulation`, distinct seeds)
  from the moment the shoe goes on, with device time accelerated (``speed``);
* the unchanged **gateway** (:class:`selfcal.gateway.Gateway`) in the same process,
  over the virtual BLE stack, spooling to SQLite and posting to the service.

Optionally the service is killed with SIGKILL at a fraction of the planned run and
restarted on the same database and port: the gateway's spool holds the batches
meanwhile. At the end the demo waits until every acknowledged sample has gone through
the service's refit worker, reads each device's calibration and measures it against
that device's simulation truth (the sphere metric of :mod:`selfcal.replay`).
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from selfcal.config import load_config, section
from selfcal.errors import InputError, SelfcalError
from selfcal.replay import sphere_directions
from selfcal.sim import SimConfig, Simulation, sensor_mean
from selfcal.sim.sensor import SensorTruth

log = logging.getLogger(__name__)

#: Samples per second (all insoles together, wall clock) the demo streams by default.
#: Measured on a 2-core machine: the whole path (bumble BLE, gateway, HTTP with
#: synchronous=FULL commits, the service's refit worker) carries ~36-40 k/s; 28.8 k/s
#: leaves headroom to drain the spool after a service restart while streaming.
DEFAULT_STREAM_RATE = 28_800.0
#: Upper bound of the automatic time acceleration (one or two insoles).
MAX_AUTO_SPEED = 720.0
#: Hours of wear per insole by default (the calibrator needs 0.5-2.8 h on the demo wearer).
DEFAULT_HOURS = 6.0
#: Samples per BLE notification: what a 247-byte ATT MTU carries ((247 - 11) // 12).
SAMPLES_PER_PACKET = 19
#: Gateway batch size: a multiple of the packet size, below the service's 2000 limit
#: (a batch closes when it reaches the limit, so it may overshoot by a packet).
BATCH_SAMPLES = 100 * SAMPLES_PER_PACKET
#: The stream starts this long before the shoe first goes on (the insole is switched on).
LEAD_S = 300.0

#: The demo wearer: the default simulated wearer except a crossed-legs foot that rests
#: (4 mg sway) instead of swinging (25 mg), so rolled still poses reach the calibrator,
#: and no simulated radio loss (the BLE link is the virtual stack's, which loses nothing).
DEMO_SIM_OVERRIDES: dict[str, dict[str, Any]] = {
    "posture": {"sit_crossed_sway_sd_mg": 4.0},
    "ble": {"packet_loss_rate": 0.0},
}

#: Gateway settings of the demo (over the config's [gateway] section): big batches
#: because time runs ``speed`` times faster, and short retry delays so a restarted
#: service is found again within a second.
DEMO_GATEWAY = {
    "batch_max_samples": BATCH_SAMPLES,
    "batch_max_age_s": 1.0,
    "backoff_initial_s": 0.2,
    "backoff_max_s": 1.0,
    "reconnect_initial_s": 0.2,
    "flush_timeout_s": 5.0,
}


# --------------------------------------------------------------------------- options
@dataclass
class DemoOptions:
    """What to run.

    Attributes
    ----------
    devices : int
        Virtual insoles (one simulated wearer each, seeds ``seed .. seed + devices - 1``).
    hours : float
        Hours of wear streamed per insole (from 5 min before the shoe goes on).
    speed : float or None
        Device time per wall time; None = ``DEFAULT_STREAM_RATE / (devices * 20 Hz)``,
        at most ``MAX_AUTO_SPEED``.
    kill_service_at : float or None
        Fraction (0, 1) of the planned run at which the service gets SIGKILL and is
        restarted on the same database and port.
    seed : int
    config : str or None
        TOML file overriding ``selfcal/configs/default.toml`` (passed to the service too).
    progress : bool
        Live status on stderr.
    verbose : bool
        Show the gateway's and bumble's warnings.
    timeout_s : float
        Give up (error) if the run takes longer than this.
    """

    devices: int = 4
    hours: float = DEFAULT_HOURS
    speed: float | None = None
    kill_service_at: float | None = None
    seed: int = 0
    config: str | None = None
    progress: bool = True
    verbose: bool = False
    timeout_s: float = 900.0
    rate_hz: float = 20.0

    def validate(self) -> None:
        if not 1 <= self.devices <= 256:
            raise InputError(f"--devices must be in 1..256, got {self.devices}")
        if not (self.hours > 0 and math.isfinite(self.hours)):
            raise InputError(f"--hours must be > 0, got {self.hours}")
        if self.speed is not None and not (self.speed > 0 and math.isfinite(self.speed)):
            raise InputError(f"--speed must be > 0, got {self.speed}")
        if self.kill_service_at is not None and not 0 < self.kill_service_at < 1:
            raise InputError(f"--kill-service-at must be a fraction in (0, 1), got {self.kill_service_at}")

    def effective_speed(self) -> float:
        if self.speed is not None:
            return float(self.speed)
        return float(min(MAX_AUTO_SPEED, DEFAULT_STREAM_RATE / (self.devices * self.rate_hz)))


# --------------------------------------------------------------------------- truth metric
def norm_rms_mg(
    truth: SensorTruth,
    directions: np.ndarray,
    matrix: Any,
    offset: Any,
    *,
    model: str | None = None,
    params: dict[str, float] | None = None,
    t_s: float = 0.0,
) -> float:
    """RMS of ``|a_cal| - 1 g`` (mg) for unit gravity along each of ``directions``.

    As :class:`selfcal.replay.TruthMetrics`: the true sensor's noise-free output
    (:func:`selfcal.sim.sensor_mean`) at the reference temperature, calibrated with the
    published ``a_cal = matrix @ (raw - offset)``. For a model with effects
    (``affine9+...``) the named ``params`` are applied with :class:`selfcal.models.ErrorModel`.
    """
    dirs = np.asarray(directions, dtype=float)
    n = len(dirs)
    temp = np.full(n, truth.temp_ref_c)
    tt = np.full(n, float(t_s))
    raw = sensor_mean(truth, dirs, temp, tt)
    if model and "+" in model and params:
        from selfcal.models import ErrorModel

        em = ErrorModel(model, temp_ref_c=truth.temp_ref_c)
        a = em.apply(em.from_dict(params), raw, temp, tt)
    else:
        a = (raw - np.asarray(offset, dtype=float)) @ np.asarray(matrix, dtype=float).T
    return float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1.0) ** 2)) * 1e3)


def sphere_norm_rms_mg(
    truth: SensorTruth,
    matrix: Any,
    offset: Any,
    *,
    model: str | None = None,
    params: dict[str, float] | None = None,
    t_s: float = 0.0,
    n: int = 2000,
) -> float:
    """:func:`norm_rms_mg` over ``n`` directions spread on the whole sphere (replay's metric)."""
    return norm_rms_mg(truth, sphere_directions(n), matrix, offset, model=model, params=params, t_s=t_s)


# --------------------------------------------------------------------------- sample source
class SimSource:
    """The sample source of one virtual insole: a simulated wearer, from shoe-on.

    A callable source (:mod:`selfcal.gateway.virtual.insole`): each call returns the
    next chunk ``(t_s, acc_g, pressure_kpa, temp_c)`` or None at the end. Until the
    insole first has a subscriber (the gateway connected and enabled notifications) it
    returns one placeholder sample per call: the insole consumes device time while
    nobody listens and drops those samples (firmware without a buffer), so the
    simulation starts exactly with the first sample that goes over the air. After that,
    samples are never held back (a link loss would lose samples, and the gateway would
    count the gap).

    Parameters
    ----------
    sim : Simulation
    hours : float
        Hours of the simulation to stream, from ``LEAD_S`` before the shoe first goes on.
    packet : int
        The planned total is rounded down to a multiple of this (whole packets only).
    piece : int
        Samples per returned chunk.
    """

    def __init__(self, sim: Simulation, hours: float, *, packet: int = SAMPLES_PER_PACKET, piece: int = 380):
        self.sim = sim
        self.rate_hz = float(sim.rate_hz)
        sch = sim.schedule
        on = np.flatnonzero(sch.on_foot)
        t_on = float(sch.start[on[0]]) / sch.rate_hz if len(on) else 0.0
        self.t_start_s = max(0.0, t_on - LEAD_S)
        n = int(round(hours * 3600.0 * self.rate_hz))
        self.planned = max(packet, n - n % packet)
        self.piece = int(piece)
        self.insole: Any = None
        self.started = False
        self.emitted = 0
        self.first_t_s: float | None = None
        self.last_t_s: float | None = None
        self._chunks = sim.iter_samples(chunk_s=600.0)
        self._buf: tuple[np.ndarray, ...] | None = None
        self._pos = 0
        self._preroll = (np.zeros(1), np.array([[0.0, 0.0, 1.0]]), np.zeros((1, 4)), np.full(1, 25.0))
        self._worn: list[np.ndarray] = []
        self._skip_to_start()

    WORN_EVERY = 10

    def worn_directions(self) -> np.ndarray:
        """Unit gravity directions (foot frame) of the still samples streamed so far (every 10th)."""
        if not self._worn:
            return np.zeros((0, 3))
        a = np.concatenate(self._worn)
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    def _load(self) -> bool:
        chunk = next(self._chunks, None)
        if chunk is None:
            self._buf = None
            return False
        self._buf = (chunk.t_s, chunk.acc_g, chunk.pressure_kpa, chunk.temp_c, chunk.a_true_g, chunk.still)
        self._pos = 0
        return True

    def _skip_to_start(self) -> None:
        while self._load():
            t = self._buf[0]
            if t[-1] >= self.t_start_s:
                self._pos = int(np.searchsorted(t, self.t_start_s))
                return

    @property
    def done(self) -> bool:
        """Every planned sample has been handed to the insole."""
        return self.emitted >= self.planned

    def __call__(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        if not self.started:
            if self.insole is None or not self.insole.subscribed:
                return self._preroll
            self.started = True
        if self.done:
            return None
        while self._buf is None or self._pos >= len(self._buf[0]):
            if not self._load():
                self.planned = self.emitted  # the simulation ran out (too few days)
                return None
        a = self._pos
        b = min(len(self._buf[0]), a + self.piece, a + self.planned - self.emitted)
        self._pos = b
        t, acc, prs, temp, a_true, still = (x[a:b] for x in self._buf)
        if still.any():  # truth: orientations of the still moments streamed (every 10th sample)
            self._worn.append(a_true[still][:: self.WORN_EVERY])
        if self.first_t_s is None:
            self.first_t_s = float(t[0])
        self.last_t_s = float(t[-1])
        self.emitted += b - a
        return t, acc, prs, temp


def demo_sim_config(cfg: dict[str, Any]) -> SimConfig:
    """The config's ``[sim]`` section with :data:`DEMO_SIM_OVERRIDES` applied."""
    return SimConfig.from_section(section(cfg, "sim")).updated(**DEMO_SIM_OVERRIDES)


def make_simulation(sim_cfg: SimConfig, seed: int, hours: float) -> Simulation:
    """One simulated wearer with enough days for ``hours`` of wear after shoe-on."""
    days = (11.0 + hours + 1.0) / 24.0  # the shoe goes on before ~10 h (7.5 h +- 0.5 h)
    return Simulation(sim_cfg, np.random.default_rng(seed), days=days, seed=seed)


# --------------------------------------------------------------------------- service process
def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pdeathsig_preexec() -> Callable[[], None] | None:
    """Linux: a ``preexec_fn`` giving the child SIGKILL when the demo process dies.

    ``prctl`` is resolved here, in the parent, so the child only makes one C call
    between fork and exec.
    """
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None

    def preexec() -> None:  # pragma: no cover - runs in the child
        prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG

    return preexec


class ServiceProcess:
    """``python -m selfcal.cli serve`` on 127.0.0.1 with a fixed port and database."""

    def __init__(self, db: Path, port: int, api_keys: str, log_path: Path, config: str | None = None):
        self.db = Path(db)
        self.port = int(port)
        self.api_keys = api_keys
        self.log_path = Path(log_path)
        self.config = config
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        env = dict(os.environ)
        env["SELFCAL_API_KEYS"] = self.api_keys
        cmd = [sys.executable, "-m", "selfcal.cli", "serve", "--db", str(self.db), "--host", "127.0.0.1",
               "--port", str(self.port), "--log-level", "warning"]
        if self.config:
            cmd += ["--config", str(Path(self.config).resolve())]
        with open(self.log_path, "ab") as fh:
            fh.write(f"--- start {self.starts + 1} at {time.strftime('%H:%M:%S')}\n".encode())
            fh.flush()
            self.proc = subprocess.Popen(
                cmd, env=env, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                cwd=str(self.db.parent), start_new_session=True, preexec_fn=_pdeathsig_preexec(),
            )
        self.starts += 1

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill9(self) -> None:
        """SIGKILL, no goodbye (what a crash or an OOM kill does)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        if self.proc is not None:
            self.proc.wait()

    def stop(self, grace_s: float = 10.0) -> None:
        """SIGTERM (uvicorn finishes and closes the database), SIGKILL after ``grace_s``."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def log_tail(self, n: int = 20) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    async def wait_healthy(self, client: Any, timeout_s: float = 60.0) -> float:
        """Poll ``GET /healthz`` until 200; returns the seconds waited."""
        import httpx

        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if self.proc is not None and self.proc.poll() is not None:
                raise SelfcalError(f"the service exited with code {self.proc.returncode}:\n{self.log_tail()}")
            try:
                r = await client.get("/healthz", timeout=2.0)
                if r.status_code == 200:
                    return time.monotonic() - t0
            except httpx.HTTPError:
                pass
            await asyncio.sleep(0.05)
        raise SelfcalError(f"the service did not answer /healthz within {timeout_s:.0f} s:\n{self.log_tail()}")


# --------------------------------------------------------------------------- status line
class Status:
    """Live progress on stderr: one rewritten line on a terminal, else a line per 10 %."""

    def __init__(self, enabled: bool, stream: Any = None):
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_decile = -1
        self._open = False

    def update(self, line: str, fraction: float) -> None:
        if not self.enabled:
            return
        if self.tty:
            self.stream.write("\r" + line[:160].ljust(min(160, max(len(line), 100))))
            self.stream.flush()
            self._open = True
            return
        decile = int(fraction * 10 + 1e-9)
        if decile > self._last_decile:
            self._last_decile = decile
            self.stream.write(line + "\n")
            self.stream.flush()

    def event(self, message: str) -> None:
        if not self.enabled:
            return
        if self._open:
            self.stream.write("\n")
            self._open = False
        self.stream.write(f"demo: {message}\n")
        self.stream.flush()

    def close(self) -> None:
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False


# --------------------------------------------------------------------------- the run
async def _stop_gateway(gw: Any, timeout_s: float = 30.0) -> None:
    """``gw.stop()``, tolerating a lost cancellation of the forwarder's task.

    On Python 3.11 ``asyncio.wait_for`` swallows a cancellation that arrives in the
    same loop iteration as the awaited event (CPython gh-86296, fixed in 3.12): when
    ``Forwarder.stop()`` cancels its drain loop right after a ``wake()``, the loop keeps
    running and ``stop()`` waits forever. The demo makes that unlikely (it stops the
    gateway only once nothing is left to forward) and, if it happens, cancels again.
    """
    task = asyncio.ensure_future(gw.stop())
    deadline = time.monotonic() + timeout_s
    while not task.done():
        await asyncio.wait({task}, timeout=1.0)
        if task.done():
            break
        fwd_task = getattr(getattr(gw, "_forwarder", None), "_task", None)
        if fwd_task is not None and not fwd_task.done():
            fwd_task.cancel()
        if time.monotonic() > deadline:
            task.cancel()
            log.warning("gateway did not stop within %.0f s", timeout_s)
            break
    if task.done() and not task.cancelled() and task.exception() is not None:
        log.warning("gateway stop: %r", task.exception())


def _fmt_int(n: int) -> str:
    return f"{n:,}"


class _Demo:
    def __init__(self, opts: DemoOptions, workdir: Path, status: Status):
        self.opts = opts
        self.workdir = workdir
        self.status = status
        self.cfg = load_config(opts.config)
        self.ingest_key = "gw-" + secrets.token_hex(12)
        self.read_key = "demo-" + secrets.token_hex(12)
        self.service = ServiceProcess(
            workdir / "selfcal.db", free_port(), f"{self.ingest_key}=ingest,{self.read_key}=read",
            workdir / "service.log", opts.config,
        )
        self.speed = opts.effective_speed()
        self.restarts = 0
        self.kill_events: list[dict[str, Any]] = []
        self.service_state = "starting"
        self.max_spool_batches = 0
        self.calibrated_count = 0

    # -- helpers -------------------------------------------------------------
    def _gateway_config(self) -> dict[str, Any]:
        gw = dict(section(self.cfg, "gateway"))
        gw.update(DEMO_GATEWAY)
        gw["http_concurrency"] = max(int(gw.get("http_concurrency", 8)), self.opts.devices)
        return gw

    async def _poll_devices(self, client: Any) -> None:
        """Status counts from ``GET /devices`` (for the progress line only)."""
        import httpx

        try:
            r = await client.get("/devices", params={"limit": 1000}, timeout=2.0)
            if r.status_code == 200:
                devs = r.json()["devices"]
                self.calibrated_count = sum(d["status"] == "calibrated" for d in devs)
        except (httpx.HTTPError, ValueError, KeyError):
            pass

    async def _restart(self, client: Any, event: dict[str, Any]) -> None:
        self.service.start()
        self.service_state = "restarting"
        await self.service.wait_healthy(client)
        event["down_s"] = round(time.monotonic() - event["_t_kill"], 3)
        self.restarts += 1
        self.service_state = "up"
        self.status.event(f"service restarted on the same database and port after {event['down_s']:.1f} s down")

    def _line(self, sources: list[SimSource], stats: dict[str, Any], t0: float) -> tuple[str, float]:
        planned = sum(s.planned for s in sources)
        emitted = sum(s.emitted for s in sources)
        frac = emitted / planned if planned else 1.0
        hours = frac * self.opts.hours
        tot = stats["totals"]
        line = (
            f"demo {hours:4.1f}/{self.opts.hours:g} h worn x{self.opts.devices} | "
            f"received {_fmt_int(tot['samples_received'])} | acked {_fmt_int(tot['samples_forwarded'])} | "
            f"spool {stats['spool_batches']} | service {self.service_state} | "
            f"calibrated {self.calibrated_count}/{self.opts.devices} | {time.monotonic() - t0:4.0f} s"
        )
        return line, frac

    # -- main ----------------------------------------------------------------
    async def run(self) -> dict[str, Any]:
        import httpx

        from selfcal.gateway import Gateway
        from selfcal.gateway.virtual import VirtualBleStack

        opts = self.opts
        t0 = time.monotonic()
        self.service.start()
        sim_cfg = demo_sim_config(self.cfg)
        sims = [make_simulation(sim_cfg, opts.seed + i, opts.hours) for i in range(opts.devices)]
        sources = [SimSource(sim, opts.hours) for sim in sims]
        device_ids = [f"insole-{i + 1:02d}" for i in range(opts.devices)]
        headers = {"Authorization": f"Bearer {self.read_key}"}
        async with httpx.AsyncClient(base_url=self.service.url, headers=headers, timeout=10.0) as client:
            startup_s = await self.service.wait_healthy(client)
            self.service_state = "up"
            self.status.event(
                f"service up at {self.service.url} in {startup_s:.1f} s (db in {self.workdir}); "
                f"{opts.devices} insoles x {opts.hours:g} h of wear at {self.speed:g}x "
                f"({opts.devices * opts.rate_hz * self.speed:,.0f} samples/s)"
            )
            async with VirtualBleStack() as stack:
                gw = Gateway(self.service.url, self.ingest_key, spool_path=self.workdir / "spool.db",
                             config=self._gateway_config(), ble=stack.backend())
                await gw.start()
                try:
                    insoles = []
                    for dev_id, src in zip(device_ids, sources):
                        ins = await stack.add_insole(
                            device_id=dev_id, source=src, speed=self.speed, sample_rate_hz=opts.rate_hz,
                            max_samples_per_packet=SAMPLES_PER_PACKET, advertising_interval_ms=100.0,
                        )
                        src.insole = ins
                        insoles.append(ins)
                    t_stream = time.monotonic()
                    await self._stream(client, gw, sources, insoles, t0)
                    stream_s = time.monotonic() - t_stream
                    stats = await self._drain(client, gw, insoles, t0)
                    result = await self._collect(client, stats, sources, insoles, device_ids)
                finally:
                    await _stop_gateway(gw)
        self.service.stop()
        result["wall_s"] = round(time.monotonic() - t0, 2)
        result["stream_s"] = round(stream_s, 2)
        return result

    async def _stream(self, client: Any, gw: Any, sources: list[SimSource], insoles: list[Any], t0: float) -> None:
        opts = self.opts
        planned = sum(s.planned for s in sources)
        restart_task: asyncio.Task[None] | None = None
        last_poll = 0.0
        while True:
            await asyncio.sleep(0.2)
            if time.monotonic() - t0 > opts.timeout_s:
                raise SelfcalError(f"the demo did not finish within {opts.timeout_s:.0f} s")
            stats = gw.stats()
            self.max_spool_batches = max(self.max_spool_batches, stats["spool_batches"])
            emitted = sum(s.emitted for s in sources)
            frac = emitted / planned if planned else 1.0
            if (opts.kill_service_at is not None and not self.kill_events
                    and frac >= opts.kill_service_at):
                self.service.kill9()
                self.service_state = "DOWN (SIGKILL)"
                event = {"at_fraction": round(frac, 4), "_t_kill": time.monotonic()}
                self.kill_events.append(event)
                self.status.event(f"service killed with SIGKILL at {100 * frac:.0f} % of the run; restarting it")
                restart_task = asyncio.ensure_future(self._restart(client, event))
            if restart_task is not None and restart_task.done():
                restart_task.result()  # raises if the restart failed
                restart_task = None
            if time.monotonic() - last_poll > 1.0 and self.service_state == "up":
                last_poll = time.monotonic()
                await self._poll_devices(client)
            line, frac = self._line(sources, stats, t0)
            self.status.update(line, frac)
            if all(s.done for s in sources) and all(i.exhausted for i in insoles) and restart_task is None:
                return

    async def _drain(self, client: Any, gw: Any, insoles: list[Any], t0: float) -> dict[str, Any]:
        """Wait until the gateway has forwarded everything and the service has fed it all."""
        ids = [i.device_id for i in insoles]
        sent = {i.device_id: i.samples_sent for i in insoles}

        def gateway_done(s: dict[str, Any]) -> bool:
            devs = s["devices"]
            return (all(i in devs for i in ids)
                    and all(devs[i]["samples_received"] + devs[i]["samples_lost"] >= sent[i] for i in ids)
                    and all(devs[i]["open_batch_samples"] == 0 for i in ids)
                    and s["spool_batches"] == 0)

        deadline = t0 + self.opts.timeout_s
        while True:
            stats = gw.stats()
            line, _ = self._line_drain(stats, "forwarding the last batches", t0)
            self.status.update(line, 1.0)
            if gateway_done(stats):
                break
            if time.monotonic() > deadline:  # (they are not lost: the spool keeps them)
                waiting = sum(max(sent[i] - stats["devices"].get(i, {}).get("samples_forwarded", 0), 0) for i in ids)
                raise SelfcalError(
                    f"the demo did not finish within {self.opts.timeout_s:.0f} s: {waiting:,} samples not yet "
                    f"forwarded ({stats['spool_batches']} batches in the gateway's spool); this machine or the "
                    "service is too slow for this --speed: lower it, or raise --timeout")
            await asyncio.sleep(0.2)
        await asyncio.sleep(0.3)  # let the forwarder's loop go idle before stopping it
        stats = gw.stats()
        forwarded = {i: stats["devices"].get(i, {}).get("samples_forwarded", 0) for i in ids}
        while True:
            processed: dict[str, int] = {}
            pending = None
            for i in ids:
                r = await client.get(f"/devices/{i}/calibration")
                processed[i] = r.json().get("samples_processed", 0) if r.status_code == 200 else 0
            h = await client.get("/healthz")
            if h.status_code in (200, 503):
                pending = h.json().get("pending_devices")
            done = all(processed[i] >= forwarded[i] for i in ids) and pending == 0
            line, _ = self._line_drain(stats, f"service refits: {_fmt_int(sum(processed.values()))} "
                                              f"of {_fmt_int(sum(forwarded.values()))} samples fed", t0)
            self.status.update(line, 1.0)
            if done:
                break
            if time.monotonic() > deadline:
                behind = sum(max(forwarded[i] - processed[i], 0) for i in ids)
                raise SelfcalError(
                    f"the demo did not finish within {self.opts.timeout_s:.0f} s: the service has {behind:,} stored "
                    "samples still to feed to its calibrators; lower --speed, or raise --timeout")
            await asyncio.sleep(0.25)
        self.status.close()
        return stats

    def _line_drain(self, stats: dict[str, Any], what: str, t0: float) -> tuple[str, float]:
        return (f"demo {self.opts.hours:g}/{self.opts.hours:g} h worn x{self.opts.devices} | {what} | "
                f"spool {stats['spool_batches']} | {time.monotonic() - t0:4.0f} s"), 1.0

    async def _collect(self, client: Any, stats: dict[str, Any], sources: list[SimSource],
                       insoles: list[Any], device_ids: list[str]) -> dict[str, Any]:
        devices = []
        lost_total = 0
        for dev_id, src, ins in zip(device_ids, sources, insoles):
            gdev = stats["devices"].get(dev_id, {})
            r = await client.get(f"/devices/{dev_id}/calibration")
            cal = r.json() if r.status_code == 200 else {}
            h = await client.get(f"/devices/{dev_id}/calibration/history")
            versions = h.json().get("versions", []) if h.status_code == 200 else []
            truth = src.sim.truth.sensor
            t_eval = float(src.last_t_s or 0.0)
            sphere = None
            if cal.get("matrix") is not None and cal.get("offset") is not None:
                sphere = round(sphere_norm_rms_mg(truth, cal["matrix"], cal["offset"], model=cal.get("model"),
                                                  params=cal.get("params"), t_s=t_eval), 4)
            raw_sphere = round(sphere_norm_rms_mg(truth, np.eye(3), np.zeros(3), t_s=t_eval), 2)
            worn_dirs = src.worn_directions()
            worn = raw_worn = None
            if len(worn_dirs):
                raw_worn = round(norm_rms_mg(truth, worn_dirs, np.eye(3), np.zeros(3), t_s=t_eval), 2)
                if sphere is not None:
                    worn = round(norm_rms_mg(truth, worn_dirs, cal["matrix"], cal["offset"], model=cal.get("model"),
                                             params=cal.get("params"), t_s=t_eval), 4)
            calibrated_after_h = None
            for v in versions:
                if v.get("status") == "calibrated":
                    span = (v.get("provenance") or {}).get("time_span_s") or [None, None]
                    if span[0] is not None and span[1] is not None:
                        calibrated_after_h = round((span[1] - span[0]) / 3600.0, 2)
                    break
            sent = int(ins.samples_sent)
            stored = int(cal.get("samples_processed", 0))
            gaps_lost = int(gdev.get("samples_lost", 0))
            lost_total += max(sent - stored, 0) + gaps_lost
            devices.append({
                "device_id": dev_id,
                "samples_sent": sent,
                "samples_stored": stored,
                "status": cal.get("status", "unknown"),
                "sphere_norm_rms_mg": sphere,
                "predicted_sphere_rms_mg": (None if cal.get("predicted_sphere_rms_mg") is None
                                            else round(float(cal["predicted_sphere_rms_mg"]), 4)),
                "promise_kept": (None if sphere is None or cal.get("predicted_sphere_rms_mg") is None
                                 else bool(sphere <= 2.5 * cal["predicted_sphere_rms_mg"] + 0.05)),
                "uncalibrated_sphere_norm_rms_mg": raw_sphere,
                "worn_norm_rms_mg": worn,
                "uncalibrated_worn_norm_rms_mg": raw_worn,
                "calibrated_after_h": calibrated_after_h,
                "versions": len(versions),
                "n_poses": cal.get("n_poses"),
                "batches_stored": cal.get("batches_stored"),
                "seed": self.opts.seed + device_ids.index(dev_id),
                "hours_worn": round(src.emitted / self.opts.rate_hz / 3600.0, 3),
            })
        tot = stats["totals"]
        return {
            "devices": devices,
            "lost_samples": int(lost_total),
            "service_restarts": int(self.restarts),
            "service_kills": [{k: v for k, v in e.items() if not k.startswith("_")} for e in self.kill_events],
            "hours_per_device": self.opts.hours,
            "speed": self.speed,
            "gateway": {
                "samples_received": tot["samples_received"],
                "samples_forwarded": tot["samples_forwarded"],
                "gaps": tot["gaps"],
                "malformed_packets": tot["malformed_packets"],
                "batches_forwarded": tot["batches_forwarded"],
                "duplicates": tot["duplicates"],
                "retries": stats["service"]["retries"],
                "rejected_batches": stats["rejected_batches"],
                "max_spool_batches": self.max_spool_batches,
            },
        }


#: The whole run is cancelled this long (s) after ``--timeout`` if no loop of it noticed first.
DEADLINE_MARGIN_S = 30.0


def run_demo(opts: DemoOptions, stream: Any = None) -> dict[str, Any]:
    """Run the demo; returns the summary dict (the ``--json`` output).

    The service subprocess is always stopped (SIGKILL on error or Ctrl-C) and the
    temporary folder removed.
    """
    opts.validate()
    status = Status(opts.progress, stream)
    quiet = {"bumble": logging.ERROR, "selfcal.gateway": logging.ERROR}
    saved = {name: logging.getLogger(name).level for name in quiet}
    if not opts.verbose:
        for name, level in quiet.items():
            logging.getLogger(name).setLevel(level)
    bumble_noise = _BumbleCallbackErrors()
    if not opts.verbose:
        logging.getLogger("asyncio").addFilter(bumble_noise)
    workdir = Path(tempfile.mkdtemp(prefix="selfcal-demo-"))
    demo: _Demo | None = None
    old_term = _terminate_as_interrupt()
    try:
        demo = _Demo(opts, workdir, status)
        # (a margin past the loops' own checks, whose messages say more: where it is behind)
        return asyncio.run(within(demo.run(), opts.timeout_s + DEADLINE_MARGIN_S,
                                  f"the demo did not finish within {opts.timeout_s:.0f} s (raise --timeout)"))
    finally:
        status.close()
        if demo is not None:
            demo.service.kill9()
        shutil.rmtree(workdir, ignore_errors=True)
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)
        logging.getLogger("asyncio").removeFilter(bumble_noise)
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


async def within(coro: Any, timeout_s: float, message: str) -> Any:
    """Await ``coro``; SelfcalError(``message``) if it takes longer than ``timeout_s`` (s)
    (it is cancelled): a stall anywhere in the run, not only where a loop checks the clock."""
    try:
        return await asyncio.wait_for(coro, timeout=timeout_s)
    except asyncio.TimeoutError:
        raise SelfcalError(message) from None


def _terminate_as_interrupt() -> Any:
    """SIGTERM handled as Ctrl-C (KeyboardInterrupt: the service stopped, the temporary folder
    removed, exit 130); the previous handler, or None off the main thread."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, interrupt)


class _BumbleCallbackErrors(logging.Filter):
    """Drops asyncio's "Exception in callback" records raised inside bumble (its host's
    packet handler sets results on futures its own timeouts cancelled: InvalidStateError),
    which the virtual stack survives; shown with ``-v``."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        tb = exc.__traceback__ if exc is not None else None
        while tb is not None:
            if "/bumble/" in tb.tb_frame.f_code.co_filename.replace("\\", "/"):
                return False
            tb = tb.tb_next
        return True


def format_table(result: dict[str, Any]) -> str:
    """The human summary printed without ``--json``."""

    def mg(raw: float | None, cal: float | None) -> str:
        left = "-" if raw is None else f"{raw:.1f}"
        right = "-" if cal is None else f"{cal:.2f}"
        return f"{left} -> {right} mg"

    rows = [("device", "sent", "stored", "status", "calibrated after", "versions",
             "|a|-1g worn poses", "|a|-1g whole sphere", "predicted sphere")]
    for d in result["devices"]:
        after = "-" if d["calibrated_after_h"] is None else f"{d['calibrated_after_h']:.1f} h"
        rows.append((d["device_id"], _fmt_int(d["samples_sent"]), _fmt_int(d["samples_stored"]), d["status"],
                     after, str(d["versions"]),
                     mg(d["uncalibrated_worn_norm_rms_mg"], d["worn_norm_rms_mg"]),
                     mg(d["uncalibrated_sphere_norm_rms_mg"], d["sphere_norm_rms_mg"]),
                     "-" if d.get("predicted_sphere_rms_mg") is None else f"{d['predicted_sphere_rms_mg']:.2f} mg"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) if i in (0, 3) else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
             for r in rows]
    g = result["gateway"]
    lines.append("(RMS of |a_cal| - 1 g against the simulation truth, uncalibrated -> calibrated: over the still "
                 "orientations the wearer's foot took, and over 2000 directions on the whole sphere; 'predicted "
                 "sphere' is what the published covariance promises)")
    lines.append("")
    lines.append(f"lost samples: {result['lost_samples']}   service restarts: {result['service_restarts']}")
    for k in result["service_kills"]:
        lines.append(f"  SIGKILL at {100 * k['at_fraction']:.0f} % of the run, {k.get('down_s', float('nan')):.1f} s "
                     f"down; the gateway spool held up to {g['max_spool_batches']} batches, "
                     f"{g['retries']} retried posts, {g['duplicates']} duplicate acks")
    lines.append(f"{result['hours_per_device']:g} h of wear per insole at {result['speed']:g}x in "
                 f"{result['stream_s']:.0f} s of streaming ({result['wall_s']:.0f} s in all)")
    return "\n".join(lines)


__all__ = ["DemoOptions", "SimSource", "format_table", "norm_rms_mg", "run_demo", "sphere_norm_rms_mg"]
