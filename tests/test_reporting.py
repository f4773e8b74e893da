"""The shared report plumbing (src/physgs_steps/reporting.py)."""
from __future__ import annotations

import csv

from physgs_steps import reporting as R


def test_markdown_table_formats_and_marks_missing_values():
    rows = [{"scene": "bear", "E": 5.0e4, "stable": True}, {"scene": "a|b", "E": None, "stable": False}]
    md = R.markdown_table(rows, [R.Column("scene"), R.Column("E", "E (Pa)", "{:.2g}"), R.Column("stable")])
    lines = md.strip().splitlines()
    assert lines[0] == "| scene | E (Pa) | stable |"
    assert lines[2] == "| bear | 5e+04 | yes |"
    assert lines[3] == "| a\\|b | n/a | no |"
    assert R.format_value(float("nan")) == "n/a"


def test_csv_keeps_raw_values_and_empty_cells(tmp_path):
    p = tmp_path / "t.csv"
    R.write_csv(p, [{"a": 1.5, "b": None}, {"a": 2, "b": "x"}])
    with open(p) as f:
        assert list(csv.reader(f)) == [["a", "b"], ["1.5", ""], ["2", "x"]]


def test_provenance_names_commit_versions_and_machine():
    prov = R.provenance(scale="smoke")
    assert prov["scale"] == "smoke"
    assert prov["versions"]["python"] and prov["versions"]["numpy"]
    assert prov["machine"]["cores"] >= 1
    text = R.provenance_markdown(prov)
    assert "scale: smoke" in text and "numpy" in text


def test_figure_writes_png(tmp_path):
    import pytest

    pytest.importorskip("matplotlib")
    p = tmp_path / "f.png"
    with R.figure(p) as (fig, ax):
        ax.plot([1, 2], [3, 4])
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
