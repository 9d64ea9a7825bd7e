"""The gateway's one base exception."""

from __future__ import annotations

from selfcal.errors import SelfcalError


class GatewayError(SelfcalError):
    """Base class of every error the gateway raises on purpose (spool, config, service)."""
