"""Exception hierarchy and typed refit outcomes."""

from __future__ import annotations


class SelfcalError(Exception):
    """Base class of every error selfcal raises on purpose."""


class InputError(SelfcalError, ValueError):
    """Bad input: a file, an array or a parameter that cannot be used.

    The message names what was wrong (file, line, column, field or argument).
    """


class CalibrationError(SelfcalError):
    """A calibration could not be produced; ``reason`` is one of REFIT_REASONS."""

    def __init__(self, reason: str, message: str):
        super().__init__(f"{reason}: {message}")
        self.reason = reason
        self.message = message


#: Typed reasons for a refit that was not published.
REFIT_REASONS = (
    "insufficient_coverage",
    "no_still_poses",
    "not_converged",
    "implausible",
    "worse_than_current",
    "no_significant_change",
)
