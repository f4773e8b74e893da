"""The benchmark (src/physgs_steps/benchmark/, workflow/rules/benchmark.smk).

Fast tests of its parts (readers that tolerate missing keys, the spec's variants and plans,
materials.initial_E, the physical figures, the report's n/a footnotes), and the smoke scale end to
end from a clean folder: `snakemake --cores 2 benchmark --config benchmark='{scale: smoke}'`, the
report's structure, that every number in it was computed, that a second run has nothing to do
and that a render change re-runs only render, metrics and the aggregations.
"""
from __future__ import annotations

import copy
import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgs_steps import config as C
from physgs_steps import plan as P
from physgs_steps.benchmark import physical as PH
from physgs_steps.benchmark import readers as RD
from physgs_steps.benchmark import report as RP
from physgs_steps.benchmark import spec as S
from physgs_steps.benchmark import tables as T
from physgs_steps.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
LINKED = ["Snakefile", "workflow", "config", "src", "tests", "profiles"]


def cfg(**over):
    c = C.load_config()
    for k, v in over.items():
        c[k] = C.deep_merge(c.get(k) or {}, v) if isinstance(v, dict) else v
    return C.validate_config(c)


# ------------------------------------------------------------------------------------ readers
def test_scores_read_the_metrics_package_schema():
    from physgs_steps.metrics import scores as MS

    m = {"schema_version": 2,
         "clip_score": MS.measured("clip_score", 0.29, "clip", True, per_frame=[0.3]),
         "aesthetic_score": MS.unavailable("aesthetic_score", "metrics.aesthetic_model_path is not set"),
         "semantic_adherence": MS.measured("semantic_adherence", 0.75, "videophy2_official", True, ratings=[4]),
         "physical_commonsense": MS.measured("physical_commonsense", 0.5, "videophy2_inprocess", False,
                                             label="in-process stand-in, not VideoPhy-2")}
    assert RD.score(m, "CS").value == pytest.approx(0.29)
    a = RD.score(m, "AS")
    assert a.value is None and "aesthetic_model_path" in a.reason
    assert RD.score(m, "SA").value == 0.75 and RD.score(m, "SA").note is None
    pc = RD.score(m, "PC")
    assert pc.value == 0.5 and pc.note == "in-process stand-in, not VideoPhy-2"  # not the paper's rater: labelled
    assert set(RD.SCORE_KEYS.values()) == set(MS.COLUMNS) and all(MS.COLUMNS[v] == k for k, v in RD.SCORE_KEYS.items())
    old = {"clip_score": 0.3}  # a bare number, and no VideoPhy2 keys at all
    assert RD.score(old, "CS").value == 0.3
    sa = RD.score(old, "SA")
    assert sa.value is None and "semantic_adherence" in sa.reason and "VideoPhy2" in sa.reason
    assert RD.score({"physical_commonsense": MS.unavailable("physical_commonsense", "rater crashed: boom")},
                    "PC").reason == "rater crashed: boom"
    assert RD.score(None, "CS", "no metrics for this run").reason == "no metrics for this run"
    assert RD.score({"clip_score": "high"}, "CS").value is None


def test_comparison_row_averages_scores_and_labels_a_stand_in_rater():
    from physgs_steps.metrics import scores as MS

    def run(scene, sa, pc):
        m = {"schema_version": 2, "clip_score": MS.unavailable("clip_score", "metrics.clip_model_path is not set"),
             "semantic_adherence": sa, "physical_commonsense": pc}
        return T.RunData({"scene": scene, "variant": "physgs", "render": True}, metrics=m)

    no_rater = MS.unavailable("semantic_adherence", "no VideoPhy2 rater configured")
    runs = [run("a", MS.measured("semantic_adherence", 0.75, "videophy2_official", True),
                MS.measured("physical_commonsense", 0.5, "videophy2_inprocess", False, label="stand-in")),
            run("b", no_rater, MS.measured("physical_commonsense", 0.25, "videophy2_inprocess", False, label="stand-in"))]
    row = T.method_row("physgs", "ours", runs, "cpu")
    assert row["SA"].value == 0.75 and row["SA"].note == "1 of 2 scenes"
    assert row["PC"].value == pytest.approx(0.375) and row["PC"].note == "stand-in"
    assert row["CS"].value is None and "clip_model_path" in row["CS"].reason
    notes = RP.Notes()
    md = RP.md_table([row], RP.PAPER_COLS, notes)
    assert "| 0.75 (1 of 2 scenes) | 0.38 (stand-in) |" in md and "n/a [1]" in md
    assert notes.texts[0] == "metrics.clip_model_path is not set"


def test_physical_figures_prefer_final_stats_and_keep_metrics():
    m = {"physical": {"det_F_min": {"value": 0.5}, "checks": {"stayed_in_domain": True}}}
    st = {"physical": {"det_F_min": {"value": 0.7}}}
    ph = RD.physical(m, st)
    assert RD.figure(ph, "det_F_min").value == 0.7
    assert RD.check(ph, "stayed_in_domain").value is True
    assert RD.figure(ph, "nope").value is None and RD.check({}, "finite").value is None


def test_E_history_band_and_fill_quality():
    p0 = {"instances": [{"label": 0, "E": 3e10, "material": "jelly", "name": "bear"}]}
    p2 = {"instances": [{"label": 0, "E": 9e4}], "history": [
        {"stage": "bgdo_update", "E_after": {"0": 1.2e5}}, {"stage": "bgdo_update", "E_after": {"0": 9e4}}]}
    assert RD.E_history(p0, p2) == {0: [3e10, 1.2e5, 9e4]}
    assert RD.E_history(p0, None) == {0: [3e10]}
    assert RD.material_band("jelly") == [1e4, 5e5] and RD.material_band("no such material") is None
    q = RD.fill_quality({"n_filled": 10, "timings": {"fill": {"seconds": 1.5}},
                         "evaluation": {"precision": 0.9, "recall": {"value": None, "reason": "x"},
                                        "leakage": {"gap": {"filled_inside": 3, "volume_covered": 0.25}}}})
    assert q["precision"].value == 0.9 and q["recall"].reason == "x"
    assert q["leakage"].value == "gap 3 (25%)" and q["seconds"].value == 1.5
    q = RD.fill_quality({"n_filled": 5, "evaluation": {"available": False, "reason": "not a built-in scene"}})
    assert q["precision"].reason == "not a built-in scene" and q["seconds"].value is None
    assert RD.fill_quality(None)["recall"].reason == "no fill_report.json"
    assert T._fate({"fate": "exploded", "rule": "exploded: E_cap"}).value == "exploded (E_cap)"
    assert T._fate({"fate": "ok", "rule": "rigid"}).value == "rigid: skipped by BGDO"
    assert "iterations 0" in T._fate(None).reason


def test_job_records_from_benchmark_file_and_stage_summary(tmp_path):
    b = tmp_path / "b.tsv"
    b.write_text("s\th:m:s\tmax_rss\n3.5\t0:00:03\t120.5\n")
    log = tmp_path / "x.log"
    log.write_text('2026 INFO [physgs.fill] stage fill done\n2026 INFO [physgs.fill] stage summary: '
                   '{"seconds": 1.25, "cuda_peak_mb": 300.0}\n')
    r = RD.job_record({"rule": "fill", "step": None, "benchmark": str(b), "log": str(log)})
    assert (r["seconds"], r["max_rss_mb"], r["stage_seconds"], r["cuda_peak_mb"]) == (3.5, 120.5, 1.25, 300.0)
    r = RD.job_record({"rule": "fill", "benchmark": str(tmp_path / "missing.tsv"), "log": None})
    assert r["seconds"] is None and "does not exist" in r["reason"]


# ------------------------------------------------------------------------------------ spec and plans
def test_benchmark_runs_live_in_their_own_namespace_and_share_within_it():
    c = cfg()
    sp = S.spec_for(c, "smoke")
    names = [v.name for v in sp.variants]
    assert names[:2] == [None, "baseline"] and "no_bgdo" in names and "e0_3e10" in names and "e0_3e10_no_bgdo" in names
    plans = {p.ablation: p for p in sp.plans("bear")}
    phys = plans[None]
    assert phys.target == "benchmark/smoke/runs/bear" and phys.path("scene") == "results/benchmark/smoke/runs/bear/scene.ply"
    assert plans["no_ipf"].target == "benchmark/smoke/runs/bear/variants/no_ipf"
    assert phys.cfgs["sim"]["sim"]["n_grid"] == 16 and phys.cfgs["prepare"]["scene"]["builtin"]["n_gaussians"] == 1500
    assert phys.cfgs["sim"]["sim"]["on_unstable"] == "keep"
    # no_bgdo shares fill, params and the sim id; the corrupted start shares the fill only
    assert plans["no_bgdo"].ids == phys.ids and plans["no_bgdo"].steps == ["it0"]
    e0 = plans["e0_3e10"]
    assert e0.ids["fill"] == phys.ids["fill"] and e0.ids["params"] != phys.ids["params"]
    assert e0.cfgs["params"]["materials"]["initial_E"] == 3e10
    assert plans["baseline"].cfgs["fill"]["fill"]["method"] == "global" and plans["baseline"].steps == ["it0"]
    # the user's own plan of the scene is untouched by the benchmark
    user = P.make_plan(c, "bear")
    assert user.path("scene") == "results/bear/scene.ply" and user.ids["fill"] != phys.ids["fill"]
    # parse_target and the lazy registry know both kinds of target
    assert P.parse_target("benchmark/smoke/runs/bear/variants/no_ipf") == ("benchmark/smoke/runs/bear", "no_ipf")
    with pytest.raises(ConfigError):
        P.parse_target("benchmark/smoke/runs/bear/ablations/no_ipf")
    reg = P.Registry(c, ["bear", "no_such_scene"])  # nothing is loaded until asked
    assert reg.plan("benchmark/smoke/runs/bear/variants/e0_3e10").path("final").startswith("results/benchmark/smoke/")
    assert reg.for_id("benchmark/smoke/runs/bear", "fill", plans["no_ipf"].ids["fill"]).ablation == "no_ipf"
    with pytest.raises(ConfigError, match="no_such_scene"):
        reg.plan("no_such_scene")
    with pytest.raises(ConfigError, match="unknown target 'benchmark/smoke/runs/bear/variants/nope'"):
        reg.plan("benchmark/smoke/runs/bear/variants/nope")


def test_ids_ignore_on_unstable_and_unset_initial_E():
    c = cfg()
    a = P.make_plan(c, "bear")
    b = P.make_plan(cfg(sim={"on_unstable": "keep"}), "bear")
    assert a.ids == b.ids  # a stable run writes the same final.h5 either way
    e = P.make_plan(cfg(materials={"initial_E": 30.0}), "bear")
    assert e.ids["params"] != a.ids["params"] and e.ids["fill"] == a.ids["fill"]


def test_spec_errors_name_the_key():
    with pytest.raises(ConfigError, match="benchmark.ablations"):
        S.BenchmarkSpec(cfg(benchmark={"ablations": ["no_such"]}), "cpu")
    with pytest.raises(ConfigError, match="E_max"):
        S.BenchmarkSpec(cfg(benchmark={"stress": {"E_min": 1e6, "E_max": 10.0}}), "smoke")
    with pytest.raises(ConfigError):
        C.validate_config({"benchmark": {"scale": "huge"}})
    c = cfg()
    c["ablations"] = {"baseline": {"fill": {"method": "none"}}}
    with pytest.raises(ConfigError, match="ablations.baseline"):
        S.BenchmarkSpec(c, "cpu")


def test_stress_runs_are_log_spaced_and_stale_ids_refused():
    sp = S.spec_for(cfg(), "smoke")
    E = sp.stress_E()
    assert len(E) == 3 and E[0] == pytest.approx(30.0) and E[-1] == pytest.approx(3e10)
    sid = sp.stress_id(sp.plan("bear"))
    assert all(p.endswith(f"/stress/{sid}/run{i:03d}.json") for i, p in enumerate(sp.stress_paths()))
    sc = sp.stress_cfg(sid, 1)
    assert sc["E"] == pytest.approx(E[1]) and sc["bgdo"]["bgdo"]["iterations"] == 1
    with pytest.raises(ConfigError, match="stale"):
        sp.stress_cfg("E-00000000", 0)


def test_initial_E_override_records_what_it_replaced():
    from physgs_steps.params.stage import apply_initial_E

    doc = {"instances": [{"label": 0, "name": "bear", "E": 5e4, "provenance": {"source": "prior"}}]}
    apply_initial_E(doc, 3e10)
    inst = doc["instances"][0]
    assert inst["E"] == 3e10 and inst["provenance"]["source"] == "initial_E"
    assert inst["provenance"]["E_replaced"] == 5e4 and inst["provenance"]["previous"] == {"source": "prior"}
    keep = copy.deepcopy(doc)
    apply_initial_E(doc, None)
    assert doc == keep
    with pytest.raises(ConfigError, match="initial_E"):
        apply_initial_E(doc, -1.0)


# ------------------------------------------------------------------------------------ figures from final.h5
def _final(path: Path, frames: list[np.ndarray]) -> None:
    with h5py.File(path, "w") as f:
        f.create_dataset("x", data=np.stack(frames).astype(np.float32))
        f.create_dataset("gaussian_index", data=np.arange(frames[0].shape[0]))
        f.create_dataset("time", data=np.arange(len(frames)) / 30.0)


def test_penetration_and_final_difference(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.uniform(0.3, 0.4, (400, 3))     # instance 0: a cube
    b = rng.uniform(0.5, 0.6, (400, 3))     # instance 1: another cube beside it
    b[:, 2] -= 0.3                          # resting at z = 0.2-0.3
    first = np.concatenate([a, b])
    moved = first.copy()
    moved[:400, 0] += 0.15                  # cube 0 slides halfway into cube 1's x range...
    moved[:400, 2] -= 0.15                  # ...and into its z range, and 0.05 below the ground at 0.2
    moved[:400, 1] += 0.2
    _final(tmp_path / "f.h5", [first, moved])
    np.savez(tmp_path / "labels.npz", labels=np.r_[np.zeros(400, np.int32), np.ones(400, np.int32)])
    pen = PH.penetration(str(tmp_path / "f.h5"), str(tmp_path / "labels.npz"), ground_height=0.2, domain_size=1.0)
    assert pen["ground_penetration_mm"].value == pytest.approx(1000 * (0.2 - moved[:, 2].min()), rel=1e-4)
    assert 0.1 < pen["instance_penetration"].value < 0.6
    single = PH.penetration(str(tmp_path / "f.h5"), None, None)
    assert single["instance_penetration"].value is None and single["ground_penetration_mm"].reason
    _final(tmp_path / "g.h5", [first, first])
    d = T.final_difference(str(tmp_path / "f.h5"), str(tmp_path / "g.h5"), 2.0)
    expect = 2000 * np.linalg.norm(moved - first, axis=1).mean()
    assert d["diff_mean_mm"].value == pytest.approx(expect, rel=1e-4) and d["frame"].value == 1
    assert d["ratio"].value == pytest.approx(1.0, rel=1e-4)
    # the same motion stored per particle, frames at rest sharing a row (frame 2 repeats row 1)
    with h5py.File(tmp_path / "p.h5", "w") as f:
        f.create_dataset("x", data=np.stack([first, moved]).astype(np.float32))
        f.create_dataset("particle_index", data=np.arange(800) + 5)
        f.create_dataset("frame_row", data=np.array([0, 1, 1], np.int32))
        f.create_dataset("time", data=np.arange(3) / 30.0)
    with h5py.File(tmp_path / "particles.h5", "w") as f:
        f.create_dataset("label", data=np.r_[np.full(5, 7), np.zeros(400), np.ones(400)].astype(np.int32))
    pp = PH.penetration(str(tmp_path / "p.h5"), None, 0.2, 1.0, particles_h5=str(tmp_path / "particles.h5"))
    assert pp["instance_penetration"].value == pytest.approx(pen["instance_penetration"].value)
    assert pp["ground_penetration_mm"].value == pytest.approx(pen["ground_penetration_mm"].value)
    assert RD.final_stats(str(tmp_path / "p.h5"))[1] and T.final_difference(str(tmp_path / "p.h5"), str(tmp_path / "g.h5"),
                                                                           1.0)["frame"].value is None  # rows of different kinds
    with h5py.File(tmp_path / "p.h5", "a") as f:
        f.attrs["stats"] = json.dumps({"stable": True})
    assert RD.final_stats(str(tmp_path / "p.h5"))[0]["frames_written"] == 3


def test_report_cells_print_na_with_a_footnote():
    notes = RP.Notes()
    rows = [{"a": RD.Cell(1.5), "b": RD.missing("no weights"), "c": RD.Cell(0.2, note="2 of 3 scenes")},
            {"a": RD.Cell(None, "no weights"), "b": RD.Cell(True), "c": "text"}]
    md = RP.md_table(rows, [RP.Col("a", "A", "{:.1f}"), RP.Col("b", "B"), RP.Col("c", "C", "{:.2f}")], notes)
    assert "| 1.5 | n/a [1] | 0.20 (2 of 3 scenes) |" in md and "| n/a [1] | yes | text |" in md
    assert notes.markdown().startswith("[1] no weights")
    data, cols = RP.csv_rows(rows, [RP.Col("a", "A"), RP.Col("b", "B")])
    assert data[0]["b"] is None and "b: n/a (no weights)" in data[0]["notes"]


# ------------------------------------------------------------------------------------ the smoke scale end to end
def smk(cwd: Path, *args: str, timeout: float = 1500) -> str:
    p = subprocess.run([sys.executable, "-m", "snakemake", *args], cwd=cwd, capture_output=True, text=True,
                       timeout=timeout, stdin=subprocess.DEVNULL)
    out = p.stdout + p.stderr
    assert p.returncode == 0, f"snakemake {' '.join(args)} failed:\n{out[-6000:]}"
    return out


def planned_rules(out: str) -> dict[str, int]:
    m = re.search(r"Job stats:\n.*?\n-+\s+-+\n(.*?)\ntotal", out, re.S)
    return {} if not m else {l.split()[0]: int(l.split()[1]) for l in m.group(1).strip().splitlines()}


SMOKE = ["--config", "benchmark={scale: smoke}"]


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    d = tmp_path_factory.mktemp("bench")
    for name in LINKED:
        (d / name).symlink_to(REPO / name)
    smk(d, "--cores", "2", "benchmark", *SMOKE)
    return d


NUMBER = re.compile(r"^-?\d+(\.\d+)?(e[+-]?\d+)?$")


def _md_tables(text: str) -> list[list[list[str]]]:
    tables, cur = [], []
    for line in text.splitlines():
        if line.startswith("|"):
            cur.append([c.strip() for c in line.strip().strip("|").split(" | ")])
        elif cur:
            tables.append(cur)
            cur = []
    return tables + ([cur] if cur else [])


@pytest.mark.slow
def test_smoke_report_structure_and_every_number_computed(smoke):
    out = smoke / "results" / "benchmark" / "smoke"
    report = (out / "REPORT.md").read_text()
    for heading in ("## 1. Comparison (paper Table 1)", "## 2. Stage time and memory (paper Table 3)",
                    "## 3. Ablations (paper Table 4)", "## 4. BGDO robustness", "### 4b. Stress against initial E",
                    "## 5. Filling quality", "## 6. Does BGDO change the result?", "## 7. Contact sheets", "## Notes"):
        assert heading in report, heading
    assert "- scale: smoke" in report and "from commit `" in report and "versions: python" in report
    assert "published, RTX A6000" in report
    for bad in ("TODO", "placeholder", "XXX"):
        assert bad not in report, bad
    notes = dict(re.findall(r"^\[(\d+)\] (.+?)\s*$", report.split("## Notes", 1)[1], re.M))
    for table in _md_tables(report):
        head, rows = table[0], table[2:]
        assert rows, head
        for row in rows:
            assert len(row) == len(head), (head, row)
            for h, cell in zip(head, row):
                for ref in re.findall(r"n/a \[(\d+)\]", cell):
                    assert ref in notes, (h, cell)
                if cell.startswith("n/a"):
                    continue
                assert cell and cell.split(" (")[0].lower() not in ("nan", "none", "inf", "-inf", "null"), (h, row)
    # our physical figures and costs are computed for every rendered run; only the weights-dependent
    # scores, GPU memory (CPU run) and the inter-instance figure (one instance) are n/a
    rows = list(csv.DictReader(open(out / "tables" / "comparison_scenes.csv")))
    assert {r["variant"] for r in rows} == {"physgs", "baseline", "no_ipf", "no_bgdo"}
    for r in rows:
        for k in ("stable", "in_domain", "ground_penetration_mm", "J_min", "J_max", "non_finite", "memory_gb", "minutes"):
            assert r[k] != "", (k, r)
        assert float(r["minutes"]) > 0 and 0 < float(r["J_min"]) <= 1 <= float(r["J_max"])
        for k in ("CS", "AS", "SA", "PC", "gpu_gb", "instance_penetration"):
            assert r[k] == "" and f"{k}: n/a" in r["notes"], (k, r)
    stages = {r["stage"]: r for r in csv.DictReader(open(out / "tables" / "stages.csv"))}
    assert list(stages) == ["IPF", "BGDO forward", "BGDO backward", "final sim", "render", "full"]
    for r in stages.values():
        assert float(r["seconds"]) > 0 and float(r["stage_seconds"]) > 0 and float(r["rss_gb"]) > 0
    assert float(stages["full"]["seconds"]) > float(stages["final sim"]["seconds"])
    # the corrupted start fails without BGDO and becomes a row saying so (its final.h5 kept the stable frames)
    rob = list(csv.DictReader(open(out / "tables" / "robustness.csv")))
    assert [r["start"] for r in rob] == ["KB", "3e+10"]
    corrupted = rob[1]
    assert corrupted["E_chain"].startswith("3e+10 -> ") and corrupted["stable_without_bgdo"] == "False"
    assert corrupted["in_band"] in ("True", "False") and corrupted["stable"] in ("True", "False")
    fill = {r["method"]: r for r in csv.DictReader(open(out / "tables" / "fill.csv"))}
    assert set(fill) == {"IPF+MCIS (paper)", "global (PhysGaussian)", "no filling (gaussians only)"}
    assert float(fill["IPF+MCIS (paper)"]["precision"]) > 0 and float(fill["IPF+MCIS (paper)"]["recall"]) > 0
    change = next(csv.DictReader(open(out / "tables" / "bgdo_change.csv")))
    assert float(change["diff_mean_mm"]) >= 0 and float(change["disp_mean_mm"]) > 0
    stress = list(csv.DictReader(open(out / "tables" / "stress_vs_E.csv")))
    assert len(stress) == 3 and float(stress[0]["E"]) == pytest.approx(30.0)
    for png in ("stress_vs_E.png", "sheet_bear.png", "bgdo_change_bear.png"):
        assert (out / "figures" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
        assert f"figures/{png}" in report
    data = json.loads((out / "report.json").read_text())
    assert data["provenance"]["scale"] == "smoke" and data["robustness"]
    plan = S.spec_for(cfg(benchmark={"scale": "smoke"}), "smoke").plan("bear", "e0_3e10_no_bgdo")
    with h5py.File(smoke / plan.path("final"), "r") as f:  # sim.on_unstable: keep
        stats = json.loads(f.attrs["stats"])
        assert stats["stable"] is False and stats["failure"] and 1 <= f["x"].shape[0] < plan.cfgs["sim"]["sim"]["n_frames"]


@pytest.mark.slow
def test_smoke_rerun_is_a_no_op_and_render_change_reruns_only_render(smoke):
    assert "Nothing to be done" in smk(smoke, "-n", "benchmark", *SMOKE)
    extra = smoke / "render_change.yaml"
    extra.write_text("render: {background: [0.0, 0.0, 0.0]}\n")
    out = smk(smoke, "-n", "benchmark", "--configfile", "config/config.yaml", str(extra), *SMOKE)
    assert set(planned_rules(out)) == {"render", "metrics", "benchmark_stage_table", "benchmark_report", "benchmark"}, \
        planned_rules(out)
