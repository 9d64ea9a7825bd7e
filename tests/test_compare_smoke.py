"""Smoke test of bench/compare.py on a tiny configuration (< 20 s): JSON shape, selfcal row, markdown targets."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _compare():
    sys.path.insert(0, str(BENCH))
    try:
        import compare
    finally:
        sys.path.remove(str(BENCH))
    return compare


def test_compare_tiny_json(capsys, tmp_path):
    compare = _compare()
    md = tmp_path / "compare.md"
    readme = tmp_path / "README.md"  # a second target with markers and hand-written text around them
    readme.write_text(f"# title\n\nbefore\n\n{compare.BEGIN}\nold\n{compare.END}\n\nafter\n")
    rc = compare.main(["--quick", "--tiny", "--json", "--seeds", "1", "--draws", "3", "--no-real",
                       "--methods", "seed_lm,lm_fixed,ellipsoid6,quadric9", "--markdown", str(md),
                       "--markdown", str(readme)])
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
    text = readme.read_text()
    assert text.startswith("# title\n\nbefore\n\n") and text.endswith("\n\nafter\n") and "old" not in text
    block = lambda t: t[t.index(compare.BEGIN):t.index(compare.END)]  # noqa: E731
    assert block(text) == block(md.read_text())  # same block in both files (no --plots: no figure links)


def test_markdown_block_links_figures_relative_to_each_target(tmp_path):
    compare = _compare()
    (tmp_path / "docs" / "img").mkdir(parents=True)
    report = {"wall_s": 1.0, "config": {"seeds": [0], "mc_draws": 3}}
    targets = {tmp_path / "docs" / "compare.md": "img/", tmp_path / "README.md": "docs/img/"}
    for path, prefix in targets.items():
        path.write_text(f"x\n{compare.BEGIN}\n{compare.END}\ny\n")
        compare.write_markdown(path, "| table |\n", report, ["--quick"], tmp_path / "docs" / "img")
        text = path.read_text()
        for name, _ in compare.FIGURES:
            assert f"]({prefix}{name})" in text
        assert text.startswith("x\n") and text.endswith("\ny\n") and "| table |" in text


def test_markdown_target_without_markers_is_refused_before_the_run(tmp_path):
    compare = _compare()
    readme = tmp_path / "README.md"
    readme.write_text("hand-written, no markers\n")
    assert compare.main(["--tiny", "--no-real", "--markdown", str(readme)]) == 2
    assert readme.read_text() == "hand-written, no markers\n"
    with pytest.raises(ValueError):
        compare.write_markdown(readme, "t", {"wall_s": 1.0, "config": {"seeds": [0], "mc_draws": 1}}, [])
