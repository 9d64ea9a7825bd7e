"""BLE gateway: insole protocol codec, bleak-based gateway, SQLite spool, HTTP forwarder.

``import selfcal.gateway`` stays light (numpy only); the classes that need the
``ble`` extra (bleak, bleak-retry-connector, httpx; bumble for the virtual
stack) are imported on first use::

    from selfcal.gateway import Gateway, BleBackend, GatewayConfig
    from selfcal.gateway.virtual import VirtualBleStack

See ``docs/gateway.md``.
"""

from __future__ import annotations

from typing import Any

from selfcal.gateway import codec
from selfcal.gateway.errors import GatewayError

_LAZY = {
    "Gateway": "selfcal.gateway.gateway",
    "BleBackend": "selfcal.gateway.gateway",
    "GatewayConfig": "selfcal.gateway.gateway",
    "Forwarder": "selfcal.gateway.forwarder",
    "Spool": "selfcal.gateway.spool",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'selfcal.gateway' has no attribute {name!r}")


__all__ = ["BleBackend", "Forwarder", "Gateway", "GatewayConfig", "GatewayError", "Spool", "codec"]
