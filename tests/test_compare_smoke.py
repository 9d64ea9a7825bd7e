"""Smoke test of bench/compare.py on a tiny configuration (< 20 s): JSON shape, selfcal row."""

from __future__ import annotations

import json
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"


def test_compare_tiny_json(capsys, tmp_path):
    sys.path.insert(0, str(BENCH))
    try:
        import compare
    finally:
        sys.path.remove(str(BENCH))
    md = tmp_path / "compare.md"
    rc = compare.main(["--quick", "--tiny", "--json", "--seeds", "1", "--draws", "3", "--no-real",
                       "--methods", "seed_lm,lm_fixed,ellipsoid6,quadric9", "--markdown", str(md)])
    assert rc == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) >= {"rows", "speedup_vs_seed_lm"}
    rows = {r["method"]: r for r in report["rows"]}
    assert "selfcal" in rows and "seed_lm" in rows
    for r in report["rows"]:
        assert {"method", "sphere_norm_rms_mg", "heldout_rms_mg", "fit_ms", "crlb_efficiency", "poses_needed"} <= set(r)
    sc = rows["selfcal"]
    assert sc["sphere_norm_rms_mg"] is not None and sc["sphere_norm_rms_mg"] > 0
    assert sc["fit_ms"] > 0
    assert report["speedup_vs_seed_lm"] > 0
    assert "| `selfcal` |" in md.read_text()
