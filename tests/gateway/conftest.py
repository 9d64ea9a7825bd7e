"""Fixtures of the gateway tests."""

from __future__ import annotations

import logging

import pytest


@pytest.fixture(autouse=True)
def _quiet_bumble():
    # bumble logs a warning per unexpected packet during deliberate fault injection.
    logging.getLogger("bumble").setLevel(logging.ERROR)
    yield
