"""API keys: ``KEY=SCOPE[+SCOPE...]`` pairs, checked in constant time, never logged.

A request carries ``Authorization: Bearer KEY``. No or unknown key -> 401; a known key
without the route's scope -> 403. Keys are kept only as SHA-256 digests and compared
with :func:`hmac.compare_digest` against *every* configured key, so neither the
position nor the length of a match shows in the timing.
"""

from __future__ import annotations

import hashlib
import hmac
from dataclasses import dataclass

SCOPES = frozenset({"ingest", "read", "admin"})


class AuthError(Exception):
    """Raised by :meth:`KeyRing.check`; ``status`` is 401 or 403."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass(frozen=True)
class _Entry:
    digest: bytes
    scopes: frozenset[str]


def parse_api_keys(spec: str) -> list[tuple[str, frozenset[str]]]:
    """Parse ``"k1=ingest,k2=read+admin"``; errors name the entry by position, not key."""
    out: list[tuple[str, frozenset[str]]] = []
    for i, raw in enumerate(part.strip() for part in spec.split(",")):
        if not raw:
            continue
        key, sep, scopes = raw.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"api_keys entry #{i + 1}: expected KEY=SCOPE[+SCOPE...]")
        if len(key) < 8:
            raise ValueError(f"api_keys entry #{i + 1}: key shorter than 8 characters")
        names = frozenset(s.strip() for s in scopes.split("+") if s.strip())
        bad = names - SCOPES
        if not names or bad:
            raise ValueError(
                f"api_keys entry #{i + 1}: scopes must be among {sorted(SCOPES)}, got {scopes!r}"
            )
        out.append((key, names))
    return out


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).digest()


class KeyRing:
    """The configured keys (digests only) and the scope check."""

    def __init__(self, spec: str):
        self._entries = [_Entry(_digest(k), s) for k, s in parse_api_keys(spec)]

    def __len__(self) -> int:
        return len(self._entries)

    def check(self, authorization: str | None, scope: str) -> None:
        """Raise :class:`AuthError` unless ``authorization`` holds a key with ``scope``."""
        if scope not in self.scopes_of(authorization):
            raise AuthError(403, f"API key lacks the '{scope}' scope")

    def scopes_of(self, authorization: str | None) -> frozenset[str]:
        """The scopes of the key in ``authorization``; :class:`AuthError` (401) if none or unknown."""
        if not authorization:
            raise AuthError(401, "missing Authorization header (expected 'Bearer KEY')")
        kind, _, token = authorization.partition(" ")
        if kind.lower() != "bearer" or not token.strip():
            raise AuthError(401, "Authorization header must be 'Bearer KEY'")
        digest = _digest(token.strip())
        found: frozenset[str] | None = None
        for entry in self._entries:  # no early exit: constant work per request
            if hmac.compare_digest(entry.digest, digest):
                found = entry.scopes
        if found is None:
            raise AuthError(401, "unknown API key")
        return found
