"""Default configuration shipped with the package (``default.toml``)."""
