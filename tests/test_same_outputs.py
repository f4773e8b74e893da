"""tools/same_outputs.py: the bitwise comparison of two results folders (used to show that the
fill speed-ups of issue 18 leave every output as it was)."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import h5py
import numpy as np

REPO = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("same_outputs", REPO / "tools" / "same_outputs.py")
so = importlib.util.module_from_spec(spec)
spec.loader.exec_module(so)


def _write(root: Path, w: np.ndarray, seconds: float, recall: float, labels: np.ndarray) -> None:
    (root / "fill" / "x").mkdir(parents=True)
    (root / "logs").mkdir()
    with h5py.File(root / "fill" / "x" / "carrier.h5", "w") as h:
        h.create_dataset("weight", data=w)
        h.attrs["mode"] = "budget"
    (root / "fill" / "x" / "fill_report.json").write_text(json.dumps(
        {"timings": {"fill": {"seconds": seconds}}, "evaluation": {"recall": recall, "seconds": seconds}}))
    np.savez(root / "labels.npz", labels=labels, seconds=np.float64(seconds))
    (root / "logs" / "fill.log").write_text(f"done in {seconds} s")


def test_same_outputs_ignores_times_and_finds_one_ulp(tmp_path):
    w = np.random.default_rng(0).random((50, 8)).astype(np.float32)
    lab = np.arange(50, dtype=np.int32)
    _write(tmp_path / "a", w, 1.0, 0.75, lab)
    _write(tmp_path / "b", w.copy(), 2.5, 0.75, lab)  # other times and logs only
    assert so.compare_trees(tmp_path / "a", tmp_path / "b") == (3, [])
    w2 = w.copy()
    w2[3, 1] = np.nextafter(w2[3, 1], np.float32(2))
    _write(tmp_path / "c", w2, 1.0, 0.7500001, lab.astype(np.int64))
    n, problems = so.compare_trees(tmp_path / "a", tmp_path / "c")
    assert n == 3 and sorted(problems) == ["fill/x/carrier.h5: dataset weight differs",
                                           "fill/x/fill_report.json: JSON differs (times and memory left out)",
                                           "labels.npz: array labels differs"]
    assert so.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert so.main([str(tmp_path / "a"), str(tmp_path / "c")]) == 1
