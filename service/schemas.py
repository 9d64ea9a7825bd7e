"""Request/response schemas, the binary batch format and the batch validator.

Units are in every field name. Two encodings of the same sample batch are accepted by
``POST /devices/{device_id}/samples``:

* ``application/json`` — columnar :class:`SampleBatchIn` (``extra="forbid"``, strict
  numbers, ``NaN``/``Infinity`` tokens rejected with the field named);
* ``application/x-selfcal-batch`` — the compact little-endian layout below, decoded
  with ``numpy.frombuffer`` (no per-number parsing). Version 2 (magic ``SCB2``) ends
  with a CRC-32 of everything before it, so a flipped bit is refused (422, field
  ``crc32``) instead of stored; version 1 (``SCB1``, no checksum) is still accepted.
  The service stores every batch in the version-1 layout (its canonical bytes, whose
  SHA-256 tells a resent batch from a different one).

Binary layout (all little-endian, no padding)::

    offset  size   field
    0       4      magic          b"SCB1" (no checksum) or b"SCB2" (CRC-32 at the end)
    4       8      seq            int64, 0 .. 2**53 - 1
    12      4      n              uint32, samples in the batch (>= 1)
    16      2      k              uint16, pressure channels per sample (0 = none)
    18      2      flags          uint16, bit 0 = temp_c present, other bits 0
    20      8n     t_s            float64[n]
            8n     ax_g           float64[n]
            8n     ay_g           float64[n]
            8n     az_g           float64[n]
            8n     temp_c         float64[n]      (only if flags bit 0)
            8nk    pressure_kpa   float64[n*k]    sample-major: p1..pk of sample 0, ...
            4      crc32          uint32, SCB2 only: zlib/IEEE CRC-32 of all bytes before it

The body length must be exactly ``20 + 8n(4 + t + k)`` (SCB1) or that plus 4 (SCB2),
with t = 1 if temp_c present.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

# ---------------------------------------------------------------- plausible ranges
#: |a| above this (g) is not a wearable accelerometer reading (±16 g is the largest
#: common full-scale range).
ACC_LIMIT_G = 16.0
TEMP_MIN_C, TEMP_MAX_C = -40.0, 85.0  # industrial operating range of MEMS parts
PRESSURE_MIN_KPA, PRESSURE_MAX_KPA = 0.0, 2000.0  # 200 N/cm^2: far above body weight
T_ABS_MAX_S = 1e10  # device clock or Unix time; beyond year 2286 is a bug
SEQ_MAX = 2**53 - 1  # exact in every JSON parser
#: Device ids: ASCII letter/digit first, then up to 63 of letters, digits, . _ : -
DEVICE_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,63}$"

BINARY_MEDIA_TYPE = "application/x-selfcal-batch"
BINARY_MAGIC = b"SCB1"
BINARY_MAGIC_CRC = b"SCB2"
_HEADER = struct.Struct("<4sqIHH")
BINARY_HEADER_BYTES = _HEADER.size  # 20
FLAG_TEMP = 1


class FieldError(Exception):
    """A rejected request: ``field`` names the offending field (``ax_g[3]``)."""

    def __init__(self, field: str, message: str, status: int = 422):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message
        self.status = status


# ---------------------------------------------------------------- internal batch
@dataclass
class Batch:
    """A validated batch in arrays: ``acc_g`` (n, 3), ``pressure_kpa`` (n, k) or None."""

    seq: int
    t_s: np.ndarray
    acc_g: np.ndarray
    temp_c: np.ndarray | None = None
    pressure_kpa: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    def to_bytes(self, crc: bool = False) -> bytes:
        """Encode in the binary layout of this module's docstring (``crc``: version 2)."""
        n = self.n
        k = 0 if self.pressure_kpa is None else int(self.pressure_kpa.shape[1])
        flags = FLAG_TEMP if self.temp_c is not None else 0
        parts = [
            _HEADER.pack(BINARY_MAGIC_CRC if crc else BINARY_MAGIC, self.seq, n, k, flags),
            np.ascontiguousarray(self.t_s, dtype="<f8").tobytes(),
            np.ascontiguousarray(self.acc_g.T, dtype="<f8").tobytes(),
        ]
        if self.temp_c is not None:
            parts.append(np.ascontiguousarray(self.temp_c, dtype="<f8").tobytes())
        if self.pressure_kpa is not None:
            parts.append(np.ascontiguousarray(self.pressure_kpa, dtype="<f8").tobytes())
        body = b"".join(parts)
        return body + struct.pack("<I", zlib.crc32(body)) if crc else body


def decode_binary(body: bytes) -> Batch:
    """Decode (not yet range-check) a binary batch; errors name the header field."""
    if len(body) < BINARY_HEADER_BYTES:
        raise FieldError("body", f"binary batch shorter than the {BINARY_HEADER_BYTES}-byte header")
    magic, seq, n, k, flags = _HEADER.unpack_from(body, 0)
    if magic not in (BINARY_MAGIC, BINARY_MAGIC_CRC):
        raise FieldError("magic", f"expected {BINARY_MAGIC_CRC!r} or {BINARY_MAGIC!r}, got {magic!r}")
    if magic == BINARY_MAGIC_CRC:
        if len(body) < BINARY_HEADER_BYTES + 4:
            raise FieldError("body", "binary batch too short for its CRC-32")
        (want,) = struct.unpack_from("<I", body, len(body) - 4)
        got = zlib.crc32(memoryview(body)[:-4])
        if got != want:
            raise FieldError("crc32", f"checksum mismatch (0x{got:08x} computed, 0x{want:08x} sent): "
                             "the batch was corrupted on the way")
        body = body[:-4]
    if not 0 <= seq <= SEQ_MAX:
        raise FieldError("seq", f"must be in 0..{SEQ_MAX}, got {seq}")
    if n < 1:
        raise FieldError("n", "a batch holds at least one sample")
    if flags & ~FLAG_TEMP:
        raise FieldError("flags", f"unknown flag bits 0x{flags & ~FLAG_TEMP:04x}")
    has_temp = bool(flags & FLAG_TEMP)
    expected = BINARY_HEADER_BYTES + 8 * n * (4 + int(has_temp) + k)
    if len(body) != expected:
        raise FieldError(
            "body", f"binary batch of n={n}, k={k}, flags={flags} must be {expected} bytes, got {len(body)}"
        )
    data = np.frombuffer(body, dtype="<f8", offset=BINARY_HEADER_BYTES)
    t_s = data[:n]
    acc_g = data[n : 4 * n].reshape(3, n).T
    pos = 4 * n
    temp_c = None
    if has_temp:
        temp_c = data[pos : pos + n]
        pos += n
    pressure = data[pos : pos + n * k].reshape(n, k) if k else None
    return Batch(int(seq), t_s, acc_g, temp_c, pressure)


def canonical_binary(body: bytes) -> bytes:
    """A decoded binary batch's stored form: the version-1 layout (``SCB1``, no CRC).

    Equal to ``decode_binary(body).to_bytes()`` without decoding again.
    """
    if body[:4] == BINARY_MAGIC_CRC:
        return BINARY_MAGIC + body[4:-4]
    return body


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _check_column(name: str, values: np.ndarray, lo: float, hi: float, unit: str) -> None:
    finite = np.isfinite(values)
    if not finite.all():
        i = _first_bad(~finite)
        raise FieldError(f"{name}[{i}]", f"must be a finite number, got {values.flat[i]!r}")
    bad = (values < lo) | (values > hi)
    if bad.any():
        i = _first_bad(bad)
        raise FieldError(f"{name}[{i}]", f"{values.flat[i]!r} outside the plausible range [{lo:g}, {hi:g}] {unit}")


def check_batch(batch: Batch, *, max_samples: int, max_pressure_channels: int) -> None:
    """Cross-field and range checks shared by both encodings; raises FieldError."""
    n = batch.n
    if n > max_samples:
        raise FieldError("t_s", f"{n} samples exceed the limit of {max_samples} per batch")
    _check_column("t_s", batch.t_s, -T_ABS_MAX_S, T_ABS_MAX_S, "s")
    if n > 1:
        dt = np.diff(batch.t_s)
        if (dt < 0).any():
            i = _first_bad(dt < 0) + 1
            raise FieldError(
                f"t_s[{i}]", f"t_s must be non-decreasing: {float(batch.t_s[i])!r} < previous {float(batch.t_s[i - 1])!r}"
            )
    for j, name in enumerate(("ax_g", "ay_g", "az_g")):
        _check_column(name, batch.acc_g[:, j], -ACC_LIMIT_G, ACC_LIMIT_G, "g")
    if batch.temp_c is not None:
        _check_column("temp_c", batch.temp_c, TEMP_MIN_C, TEMP_MAX_C, "degC")
    if batch.pressure_kpa is not None:
        k = batch.pressure_kpa.shape[1]
        if k > max_pressure_channels:
            raise FieldError("pressure_kpa", f"{k} channels exceed the limit of {max_pressure_channels}")
        finite = np.isfinite(batch.pressure_kpa)
        bad = ~finite | (batch.pressure_kpa < PRESSURE_MIN_KPA) | (batch.pressure_kpa > PRESSURE_MAX_KPA)
        if bad.any():
            i, c = np.argwhere(bad)[0]
            raise FieldError(
                f"pressure_kpa[{i}][{c}]",
                f"{batch.pressure_kpa[i, c]!r} must be finite and within "
                f"[{PRESSURE_MIN_KPA:g}, {PRESSURE_MAX_KPA:g}] kPa",
            )


# ---------------------------------------------------------------- JSON request
Acc = Annotated[float, Field(ge=-ACC_LIMIT_G, le=ACC_LIMIT_G)]
Time = Annotated[float, Field(ge=-T_ABS_MAX_S, le=T_ABS_MAX_S)]
Temp = Annotated[float, Field(ge=TEMP_MIN_C, le=TEMP_MAX_C)]
Pressure = Annotated[float, Field(ge=PRESSURE_MIN_KPA, le=PRESSURE_MAX_KPA)]

_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class SampleBatchIn(BaseModel):
    """One batch of samples from one device (columnar; all arrays of equal length)."""

    model_config = _STRICT

    seq: int = Field(ge=0, le=SEQ_MAX, description="per-device batch sequence number")
    t_s: list[Time] = Field(min_length=1, description="sample times (s), non-decreasing")
    ax_g: list[Acc] = Field(min_length=1, description="specific force x (g)")
    ay_g: list[Acc] = Field(min_length=1, description="specific force y (g)")
    az_g: list[Acc] = Field(min_length=1, description="specific force z (g)")
    temp_c: list[Temp] | None = Field(None, description="sensor temperature (degC), one per sample")
    pressure_kpa: list[Annotated[list[Pressure], Field(min_length=1)]] | None = Field(
        None, description="pressure cells (kPa): one list of channel values per sample"
    )

    def to_batch(self) -> Batch:
        """Arrays from the columns; checks the lengths (errors name the field)."""
        n = len(self.t_s)
        for name in ("ax_g", "ay_g", "az_g", "temp_c", "pressure_kpa"):
            col = getattr(self, name)
            if col is not None and len(col) != n:
                raise FieldError(name, f"length {len(col)} differs from length of t_s ({n})")
        pressure = None
        if self.pressure_kpa is not None:
            k = len(self.pressure_kpa[0])
            for i, row in enumerate(self.pressure_kpa):
                if len(row) != k:
                    raise FieldError(
                        f"pressure_kpa[{i}]", f"{len(row)} channels, but sample 0 has {k}"
                    )
            pressure = np.asarray(self.pressure_kpa, dtype=np.float64)
        return Batch(
            seq=self.seq,
            t_s=np.asarray(self.t_s, dtype=np.float64),
            acc_g=np.column_stack(
                [np.asarray(c, dtype=np.float64) for c in (self.ax_g, self.ay_g, self.az_g)]
            ),
            temp_c=None if self.temp_c is None else np.asarray(self.temp_c, dtype=np.float64),
            pressure_kpa=pressure,
        )


# ---------------------------------------------------------------- responses
class ErrorOut(BaseModel):
    """Every error: ``error`` (kind), ``field`` (what was wrong, if a field), ``message``."""

    error: str
    field: str | None = None
    message: str


class BatchAck(BaseModel):
    device_id: str
    seq: int
    accepted: int = Field(description="samples in the batch (also for a duplicate)")
    duplicate: bool = Field(description="true: this seq was already stored; not counted again")


class RefitOutcome(BaseModel):
    model_config = ConfigDict(extra="allow")

    published: bool
    reason: str | None = None
    message: str = ""
    t_s: float | None = None


Status = Literal["uncalibrated", "provisional", "calibrated"]


class CalibrationOut(BaseModel):
    """The current model of a device (``a_cal_g = matrix @ (raw - offset)``)."""

    device_id: str
    version: int | None = Field(description="model version served; null before the first")
    status: Status
    status_reason: str | None = Field(
        None, description="why a version whose covariance would make it 'calibrated' is 'provisional' (e.g. the "
        "cells since the last version disagree with it: a bias step not yet named)")
    source: Literal["refit", "factory", "rollback"] | None = None
    model: str | None = None
    params: dict[str, float | None] | None = None
    std: dict[str, float | None] | None = None
    matrix: list[list[float]] | None = None
    offset: list[float] | None = None
    n_poses: int | None = None
    residual_rms_mg: float | None = None
    predicted_sphere_rms_mg: float | None = Field(
        None, description="calibrated-norm RMS error over the whole sphere predicted by the covariance, mg, with "
        "what the effects the model lacks could add (unmodelled) and, while status_reason names one, an offset jump")
    predicted_sphere_rms_mg_model: float | None = Field(
        None, description="the same from the model's own covariance alone, mg (versions before 2026-11-27: null)")
    unmodelled: dict[str, Any] | None = Field(
        None, description="{effects: candidate effects the model lacks, sphere_rms_mg: what they could add over the "
        "sphere, mg, the sum in quadrature of undetermined_mg (what the poses leave open, at the effects' datasheet "
        "size) and determined_mg (what the poses say the effects are); older versions lack the two parts}")
    updated_at: str | None = Field(None, description="ISO 8601 UTC time of this version")
    determined: list[str] = Field(default_factory=list, description="parameters the data determined")
    undetermined: list[str] = Field(default_factory=list, description="parameters held at the prior")
    last_refit: RefitOutcome | None = None
    calibrator_status: Status | None = Field(None, description="status the calibrator reports")
    samples_processed: int = 0
    batches_stored: int = 0
    processed_seq: int | None = Field(None, description="highest batch seq fed to the calibrator")
    rejected_batches: int = Field(0, description="stored batches never fed (late, or refused by the calibrator)")
    rejected_samples: int = Field(0, description="samples of those batches")
    last_rejection: dict[str, Any] | None = Field(
        None, description="the last rejected batch: {seq, reason, at (Unix s)}")


class Provenance(BaseModel):
    model_config = ConfigDict(extra="allow")

    n_poses: int | None = None
    coverage: Any = None
    temp_range_c: list[float] | None = None
    time_span_s: list[float] | None = None
    seq_range: list[int] | None = None
    samples: int | None = None


class VersionOut(BaseModel):
    version: int
    status: Status
    source: Literal["refit", "factory", "rollback"]
    created_at: str
    calibration: dict[str, Any]
    provenance: Provenance


class HistoryOut(BaseModel):
    device_id: str
    current_version: int | None
    versions: list[VersionOut]


class DeviceOut(BaseModel):
    device_id: str
    status: Status
    version: int | None
    samples_processed: int
    batches_stored: int
    updated_at: str | None


class DevicesOut(BaseModel):
    devices: list[DeviceOut]
    next_after: str | None = Field(None, description="pass as ?after= for the next page")


class WhoAmIOut(BaseModel):
    """The scopes of the presented key (the dashboard hides what the key may not do)."""

    scopes: list[Literal["ingest", "read", "admin"]]


class RefusalOut(BaseModel):
    """A refit that published nothing, or a stored batch never fed, with its reason."""

    kind: Literal["refit", "batch"] = Field(description="refit: the calibrator kept the served model; batch: not fed")
    reason: str | None = Field(None, description="typed reason: no_significant_change, worse_than_current, "
                               "insufficient_coverage, implausible, late, calibrator, ...")
    message: str = ""
    at: str | None = Field(None, description="ISO 8601 UTC time the service recorded it (the clock of created_at)")
    at_unix_s: float | None = Field(None, description="the same time, Unix seconds")
    t_s: float | None = Field(None, description="device (calibrator) time of a refit, s")
    seq: int | None = Field(None, description="the rejected batch's seq")


class RefusalsOut(BaseModel):
    device_id: str
    refusals: list[RefusalOut] = Field(description="oldest first; the service keeps the last 1000 per device")


class FleetDeviceOut(BaseModel):
    """One device as the fleet dashboard lists it."""

    device_id: str
    status: Status
    version: int | None
    source: Literal["refit", "factory", "rollback"] | None = None
    model: str | None = None
    predicted_sphere_rms_mg: float | None = Field(
        None, description="served version: calibrated-norm RMS error over the sphere its covariance predicts, mg")
    residual_rms_mg: float | None = Field(None, description="served version: fit residual RMS, mg")
    n_poses: int | None = Field(None, description="served version: pose cells it was fitted to")
    backlog_batches: int = Field(description="stored batches of this device neither fed nor rejected yet")
    batches_stored: int
    samples_processed: int
    rejected_batches: int
    last_seen: str | None = Field(None, description="ISO 8601 UTC receipt time of the device's highest-seq batch")
    updated_at: str | None = Field(None, description="ISO 8601 UTC time of its last refit cycle or admin write")
    last_refusal: RefusalOut | None = Field(
        None, description="its newest refusal (GET /devices/{id}/refusals has them all; the last refit's "
        "full outcome is in GET /devices/{id}/calibration)")


class FleetOut(BaseModel):
    devices: list[FleetDeviceOut]
    next_after: str | None = Field(None, description="pass as ?after= for the next page")


class SphereGridOut(BaseModel):
    """Directions spread over the whole sphere and the calibrated-norm error predicted along each."""

    direction: list[list[float]] = Field(description="unit gravity directions, sensor frame")
    sd_mg: list[float | None] = Field(description="sd of the calibrated norm the current fit predicts there, mg")
    prior_sd_mg: list[float | None] = Field(description="the datasheet prior's sd there, mg")
    undetermined: list[bool] = Field(description="sd_mg above undetermined_above_sd_mg")


class PosesOut(BaseModel):
    """The device's stored still poses (pose cells) and the directions they leave undetermined."""

    device_id: str
    available: bool = Field(description="false: this calibrator keeps no pose store, or nothing was fed yet")
    note: str | None = None
    version: int | None = Field(None, description="served version the residuals are computed with")
    model: str | None = None
    residual_basis: Literal["served", "nominal"] | None = Field(
        None, description="served: residuals under the served version; nominal: no calibration yet")
    n_poses: int
    direction: list[list[float | None]] = Field(description="per pose: unit gravity direction, sensor frame")
    temp_c: list[float | None] = Field(description="per pose: mean temperature, degC (null: none measured)")
    residual_mg: list[float | None] = Field(description="per pose: |a_cal| - 1 g under the served version, mg")
    windows: list[int] = Field(description="per pose: still windows merged in the cell")
    t_s: list[float | None] = Field(description="per pose: mean window time, device s")
    residual_rms_mg: float | None = None
    undetermined_above_sd_mg: float | None = Field(
        None, description="a direction is undetermined above this predicted sd, mg ([scheduler] calibrated_max_sphere_mg)")
    sphere: SphereGridOut


class HealthOut(BaseModel):
    """Liveness: the process answers and its threads run (restart it if not)."""

    status: Literal["ok", "degraded"]
    db: bool
    workers_alive: int
    pending_devices: int


class ReadyOut(BaseModel):
    """Readiness: the service can take and process data now."""

    ready: bool
    storage_writable: bool
    storage_problem: str | None = None
    workers_alive: int
    backlog_batches: int = Field(description="stored batches neither fed nor rejected yet")
    max_backlog_batches: int


class RollbackIn(BaseModel):
    """Serve an earlier version again (recorded as a new version with source rollback)."""

    model_config = _STRICT

    to_version: int | None = Field(None, ge=1, le=2**31 - 1, description="default: the version before the current")


Matrix3 = Annotated[list[Annotated[float, Field(ge=-1e3, le=1e3)]], Field(min_length=3, max_length=3)]


class FactoryCalibrationIn(BaseModel):
    """A factory (bench) calibration to seed a device with: ``a_cal_g = matrix @ (raw - offset)``."""

    model_config = _STRICT

    matrix: Annotated[list[Matrix3], Field(min_length=3, max_length=3)]
    offset: Annotated[list[Annotated[float, Field(ge=-ACC_LIMIT_G, le=ACC_LIMIT_G)]], Field(min_length=3, max_length=3)]
    model: str = Field("affine9", max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    params: dict[Annotated[str, Field(max_length=32)], Annotated[float, Field(ge=-1e6, le=1e6)]] | None = Field(
        None, max_length=64
    )
    std: dict[Annotated[str, Field(max_length=32)], Annotated[float, Field(ge=1e-7, le=1e6)]] | None = Field(
        None, max_length=64, description="standard deviations of the parameters (g, or relative for scales), "
                                         ">= 1e-7 (selfcal.calibrator.SEED_STD_MIN)"
    )
    note: str | None = Field(None, max_length=500)


def batch_request_openapi(max_samples: int) -> dict[str, Any]:
    """OpenAPI ``requestBody`` for the samples route: JSON schema + the binary type."""
    schema = SampleBatchIn.model_json_schema(ref_template="#/components/schemas/{model}")
    for name in ("t_s", "ax_g", "ay_g", "az_g"):
        schema["properties"][name]["maxItems"] = max_samples
    return {
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {"schema": schema},
                BINARY_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}},
            },
        }
    }
