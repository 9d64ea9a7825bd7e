"""Delta checkpoints of a calibrator's state: a full *base*, then small *patches* against it.

A worn calibrator's state is ~97 % pose store (one row of sums per pose cell), and between
two checkpoints only the cells that got windows change. A patch holds every field of the
state but the store's rows, the row order (the base row each row is, or -1) and the rows
that are not in the base. Applied to its base, it gives the full state, byte for byte
(``tests/test_checkpoint.py``).

* A row is recognised by a 64-bit digest of its bytes (key, statistics, first and last
  time): the writer keeps only the base's digests (8 bytes a cell), not its rows. Equal
  rows have equal digests; a changed row keeps its old digest with probability ~2^-64.
* A patch names its base by the CRC-32 and length of the base's text, and applying it to
  any other base raises :class:`~selfcal.errors.InputError`.
* The row order is stored as the zlib-compressed differences of consecutive entries: a
  store keeps its rows in order and appends new cells, so they are nearly all 1 (a week-
  worn store's ~5 600 entries take a few hundred bytes instead of ~30 KB).
* A field of the state (but the pose store) whose JSON is the base's, byte for byte, is
  not repeated: the patch names it (``same``) and holds null in its place (format 2; the
  configuration, ~4 KB, always; the published calibration and the selection history while
  no refit changed them). Fields are compared by a 128-bit BLAKE2b digest of their JSON,
  which the writer keeps with the base's row digests.
* Nothing here knows the storage: the refit worker decides when a patch is small enough
  (``patch_fraction`` of the base) and the stores keep the base and the latest patch.
"""

from __future__ import annotations

import base64
import hashlib
import json
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from selfcal.errors import InputError
from selfcal.poses import N_STATS, _dec, _enc

PATCH_FORMAT = "selfcal-calibrator-patch"
PATCH_FORMAT_VERSION = 2  # 2: fields equal to the base's are named, not repeated (1 still read)

# A field whose JSON is shorter than this is repeated even when it is the base's (naming it
# would not save bytes).
_SAME_MIN_BYTES = 64

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@dataclass(frozen=True)
class CheckpointBase:
    """What a writer keeps of a stored base: ``crc32`` and ``n_bytes`` of its text (UTF-8),
    ``digests (m,) uint64``, one per pose-store row in the base's order, and ``fields``,
    the digest of each other top-level field's JSON (:func:`field_digests`)."""

    crc32: int
    n_bytes: int
    digests: np.ndarray
    fields: dict[str, str] = field(default_factory=dict)


def _json(value: Any) -> str:
    """A value's JSON as the calibrator's ``to_json`` writes it (compact, NaN allowed)."""
    return json.dumps(value, allow_nan=True, separators=(",", ":"))


def _digest(text: str) -> str:
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def field_digests(state: dict[str, Any]) -> dict[str, str]:
    """The 128-bit digest (hex) of the JSON of each top-level field of a state dict but
    ``store``, for fields of at least ``_SAME_MIN_BYTES`` (the same for a state and for
    its JSON parsed again: floats, key order and NaN survive the round trip)."""
    out = {}
    for k, v in state.items():
        if k != "store":
            text = _json(v)
            if len(text) >= _SAME_MIN_BYTES:
                out[k] = _digest(text)
    return out


def _mix(z: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser, elementwise on uint64 (wrapping arithmetic)."""
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def row_digests(key: np.ndarray, stats: np.ndarray, t_first: np.ndarray, t_last: np.ndarray) -> np.ndarray:
    """A 64-bit digest of each pose-store row: ``key (m,) int64``, ``stats (m, 20)``,
    ``t_first``/``t_last (m,)`` in s, as float64 bits (-0.0 and 0.0 differ). Returns (m,) uint64."""
    m = int(np.shape(key)[0])
    words = np.empty((m, N_STATS + 3), dtype=np.uint64)
    words[:, 0] = np.asarray(key, dtype="<i8").view(np.uint64)
    words[:, 1:N_STATS + 1] = np.ascontiguousarray(stats, dtype="<f8").reshape(m, N_STATS).view(np.uint64)
    words[:, N_STATS + 1] = np.ascontiguousarray(t_first, dtype="<f8").view(np.uint64)
    words[:, N_STATS + 2] = np.ascontiguousarray(t_last, dtype="<f8").view(np.uint64)
    column = np.arange(1, N_STATS + 4, dtype=np.uint64) * _GOLDEN  # each column its own offset
    return _mix(_mix(words + column).sum(axis=1, dtype=np.uint64))


def _store_rows(store_json: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return (np.asarray(store_json["key"], dtype=np.int64).reshape(-1), _dec(store_json["stats"], (N_STATS,)),
            _dec(store_json["t_first"]), _dec(store_json["t_last"]))


def base_of(text: str, store, fields: dict[str, str]) -> CheckpointBase:
    """The :class:`CheckpointBase` of a full state ``text`` whose pose store is ``store``
    (a :class:`~selfcal.poses.PoseStore`) and whose other fields have the digests
    ``fields`` (:func:`field_digests` of the dict ``text`` serialises: the writer has it,
    so nothing parses the text again)."""
    raw = text.encode()
    return CheckpointBase(zlib.crc32(raw), len(raw), row_digests(store.key, store.stats, store.t_first, store.t_last),
                          fields)


def _encode_order(from_base: np.ndarray) -> str:
    """Row order (base row or -1, (m,) int) -> text: zlib'd differences of consecutive
    entries (the first from -1), little-endian int32, base64."""
    steps = np.diff(from_base, prepend=-1).astype("<i4")
    return base64.b64encode(zlib.compress(steps.tobytes(), 6)).decode("ascii")


def _decode_order(text: str) -> np.ndarray:
    """Inverse of :func:`_encode_order`, (m,) int64."""
    steps = np.frombuffer(zlib.decompress(base64.b64decode(text)), dtype="<i4").astype(np.int64)
    return np.cumsum(steps) - 1


def make_patch(state: dict[str, Any], store, base: CheckpointBase) -> str:
    """The patch text that turns ``base`` into ``state`` (a calibrator's ``state()`` dict
    whose ``"store"`` entry serialises ``store``)."""
    digests = row_digests(store.key, store.stats, store.t_first, store.t_last)
    from_base = np.full(len(digests), -1, dtype=np.int64)
    if len(base.digests):
        order = np.argsort(base.digests, kind="stable")
        pos = np.minimum(np.searchsorted(base.digests[order], digests), len(order) - 1)
        hit = base.digests[order[pos]] == digests
        from_base[hit] = order[pos[hit]]
    new = from_base < 0
    store_patch = dict(state["store"])
    store_patch.update(key=store.key[new].tolist(), stats=_enc(store.stats[new]), t_first=_enc(store.t_first[new]),
                       t_last=_enc(store.t_last[new]),
                       from_base=_encode_order(from_base))
    # each field's JSON once: digested, then written (or null: the base's, its place kept so
    # that the applied state has the same key order)
    texts = {k: _json(v) for k, v in dict(state, store=store_patch).items()}
    same = [k for k, text in texts.items()
            if k != "store" and len(text) >= _SAME_MIN_BYTES and base.fields.get(k) == _digest(text)]
    for k in same:
        texts[k] = "null"
    head = {"format": PATCH_FORMAT, "format_version": PATCH_FORMAT_VERSION, "base_crc32": base.crc32,
            "base_bytes": base.n_bytes, "same": same}
    body = ",".join(f"{_json(str(k))}:{text}" for k, text in texts.items())
    return f"{_json(head)[:-1]},\"state\":{{{body}}}}}"


def apply_patch(base_text: str, patch_text: str, encode: bool = True) -> tuple[dict[str, Any], CheckpointBase]:
    """The full state dict that ``patch_text`` makes of ``base_text``, and the base's
    :class:`CheckpointBase` (for the next patch against the same base). ``encode=False``:
    the pose store's per-cell fields are left as arrays (``PoseStore.from_json`` takes
    them; the dict is then not JSON), which saves encoding them to decode them again.

    Raises :class:`InputError` if the patch is not a patch or was made against another base."""
    raw = base_text.encode()
    crc = zlib.crc32(raw)  # (once: the base is up to megabytes)
    try:
        patch = json.loads(patch_text)
    except (ValueError, RecursionError) as exc:
        raise InputError(f"checkpoint patch: not JSON ({type(exc).__name__}: {exc})") from None
    if not isinstance(patch, dict) or patch.get("format") != PATCH_FORMAT \
            or type(patch.get("format_version")) is not int or patch["format_version"] not in (1, PATCH_FORMAT_VERSION):
        raise InputError("checkpoint patch: unknown format or version")
    if patch.get("base_crc32") != crc or patch.get("base_bytes") != len(raw):
        raise InputError(f"checkpoint patch: made against another base (CRC-32 {patch.get('base_crc32')}, "
                         f"{patch.get('base_bytes')} bytes; the stored base has {crc}, {len(raw)} bytes)")
    try:
        base_state = json.loads(base_text)
        rows = _store_rows(base_state["store"])
    except (ValueError, KeyError, TypeError, OverflowError, RecursionError) as exc:
        raise InputError(f"checkpoint patch: its base has no pose store rows ({type(exc).__name__}: {exc})") from None
    base = CheckpointBase(crc, len(raw), row_digests(*rows), field_digests(base_state))
    same = patch.get("same", [])
    if not isinstance(same, list) or not isinstance(patch.get("state"), dict) or not isinstance(base_state, dict) \
            or any(not isinstance(k, str) or k == "store" or k not in patch["state"] or k not in base_state
                   for k in same):
        raise InputError("checkpoint patch: its fields named as the base's are not fields of both")
    state = dict(patch["state"])
    for k in same:  # format 2: the base's fields, in their places
        state[k] = base_state[k]
    try:
        store_patch = dict(state["store"])
        from_base = _decode_order(store_patch.pop("from_base"))
        changed = _store_rows(store_patch)
    except (ValueError, KeyError, TypeError, OverflowError, zlib.error) as exc:
        raise InputError(f"checkpoint patch: no pose store rows ({type(exc).__name__}: {exc})") from None
    new = from_base < 0
    if int(new.sum()) != len(changed[0]) or (len(from_base) and (from_base.max(initial=-1) >= len(rows[0])
                                                                 or from_base.min(initial=-1) < -1)):
        raise InputError("checkpoint patch: its rows do not match its row order")
    merged = []
    for old, fresh in zip(rows, changed):
        out = np.empty((len(from_base),) + old.shape[1:], dtype=old.dtype)
        out[~new] = old[from_base[~new]]
        out[new] = fresh
        merged.append(out)
    key, stats, t_first, t_last = merged
    if encode:
        store_patch.update(key=key.tolist(), stats=_enc(stats), t_first=_enc(t_first), t_last=_enc(t_last))
    else:
        store_patch.update(key=key, stats=stats, t_first=t_first, t_last=t_last)
    return dict(state, store=store_patch), base


__all__ = ["CheckpointBase", "row_digests", "field_digests", "base_of", "make_patch", "apply_patch", "PATCH_FORMAT"]
