"""Configuration files (TOML).

Each module owns the pydantic model of its own section (``[detector]`` is validated by
``selfcal.detect.DetectorConfig``, ``[fit]`` by ``selfcal.fit.FitConfig`` and so on);
this module only finds, reads and merges the files.

The defaults live in ``selfcal/configs/default.toml`` (every threshold named and commented);
a user file passed with ``--config FILE`` overrides any subset of keys.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from selfcal.errors import InputError

#: Where the default configuration ships: inside the package (``selfcal/configs/default.toml``).
DEFAULT_CONFIG_RESOURCE = ("selfcal.configs", "default.toml")


def default_config_text() -> str:
    """The text of the packaged default configuration (``importlib.resources``)."""
    return resources.files(DEFAULT_CONFIG_RESOURCE[0]).joinpath(DEFAULT_CONFIG_RESOURCE[1]).read_text("utf-8")


def _merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def read_toml(path: str | Path) -> dict[str, Any]:
    """Read one TOML file; a parse error names the file and the position."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as exc:
        raise InputError(f"{path}: config file not found") from exc
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: invalid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start}): not a TOML config file") from None
    except OSError as exc:  # a folder, no permission
        raise InputError(f"{path}: cannot read the config file ({exc.strerror or exc})") from None


def load_config(path: str | Path | None = None) -> dict[str, Any]:
    """Return the merged configuration: defaults, overridden by ``path`` if given.

    Returns a dict of sections (``{"detector": {...}, "fit": {...}, ...}``); each
    consumer validates its own section with its pydantic model.
    """
    cfg = tomllib.loads(default_config_text())
    if path is not None:
        user = read_toml(path)
        for name, value in user.items():  # a section given as a value would replace the whole table
            if isinstance(cfg.get(name), dict) and not isinstance(value, dict):
                raise InputError(f"{path}: [{name}] must be a table of settings, got {name} = {value!r}")
        cfg = _merge(cfg, user)
    return cfg


def section(cfg: dict[str, Any] | None, name: str) -> dict[str, Any]:
    """The section ``name`` of a loaded config (empty dict if absent)."""
    if not cfg:
        return {}
    value = cfg.get(name, {})
    if not isinstance(value, dict):
        raise InputError(f"config: [{name}] must be a table, got {type(value).__name__}")
    return value
