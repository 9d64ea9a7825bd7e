"""selfcal HTTP service: FastAPI app, SQLite (WAL) storage, background refits.

Start it with ``selfcal serve --db PATH``; build it in code with
``selfcal_service.main.create_app(settings, calibrator_factory=...)``. See docs/service.md.
FastAPI is imported only when this package is used (``import selfcal`` stays light).
"""
