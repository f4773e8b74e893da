"""The workflow end to end on a tiny scene (CPU), and what a config change re-runs.

Runs ``snakemake`` in a scratch folder whose workflow files are links to the repository,
with the tiny configuration of tests/slurm/config.yaml (2000 gaussians, 16^3 grid,
16 frames, 128x128 video).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "tests" / "slurm" / "config.yaml"
LINKED = ["Snakefile", "workflow", "config", "src", "tests", "profiles"]


def smk(cwd: Path, *args: str, timeout: float = 600, env: dict | None = None) -> str:
    p = subprocess.run([sys.executable, "-m", "snakemake", *args], cwd=cwd, capture_output=True, text=True,
                       timeout=timeout, stdin=subprocess.DEVNULL, env=env)
    out = p.stdout + p.stderr
    assert p.returncode == 0, f"snakemake {' '.join(args)} failed:\n{out[-6000:]}"
    return out


def planned_rules(out: str) -> dict[str, int]:
    """Job counts of a dry run's 'Job stats' table."""
    m = re.search(r"Job stats:\n.*?\n-+\s+-+\n(.*?)\ntotal", out, re.S)
    if not m:
        return {}
    return {line.split()[0]: int(line.split()[1]) for line in m.group(1).strip().splitlines()}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("wf")
    for name in LINKED:
        (d / name).symlink_to(REPO / name)
    return d


@pytest.fixture(scope="module")
def finished(tiny_bear_run):
    # conftest.py: the tiny bear through results/bear/stage_report.tsv, every stage in the
    # warm stage worker (shared with test_slurm.py, which compares its SLURM run with it)
    return tiny_bear_run


def test_dry_run_lists_every_stage(run_dir):
    out = smk(run_dir, "-n", "results/bear/video.mp4", "--configfile", str(TINY))
    rules = planned_rules(out)
    for r in ("prepare", "cluster", "fill", "vlm_params", "forward_sim", "bgdo_update", "final_sim", "render"):
        assert rules.get(r, 0) >= 1, f"{r} missing from the DAG: {rules}"


def test_lint_has_no_errors(run_dir):
    p = subprocess.run([sys.executable, "-m", "snakemake", "--lint"], cwd=run_dir, capture_output=True, text=True, timeout=300)
    assert "Error" not in p.stderr, p.stderr[-3000:]
    lints = {m.strip() for m in re.findall(r"^\s+\* (.*?):$", p.stdout + p.stderr, re.M)}
    # the only remaining suggestion (exit status 1): per-rule conda/containers; the software
    # environment is this package's own install (tools/setup.sh, or a wheelhouse on clusters)
    assert lints <= {"Specify a conda environment or container for each rule."}, lints


def test_end_to_end_outputs(finished):
    res = finished / "results" / "bear"
    for f in ("video.mp4", "contact_sheet.png", "metrics.json", "render.json", "scene.ply", "transform.json"):
        assert (res / f).stat().st_size > 0, f
    table = pd.read_csv(res / "stage_report.tsv", sep="\t")
    assert {"prepare", "cluster", "fill", "vlm_params", "forward_sim", "bgdo_update", "final_sim", "render"} <= set(table["rule"])
    assert table["seconds"].notna().all(), table
    logs = {p.name for p in (res / "logs").iterdir()}
    assert any(n.startswith("final_sim") for n in logs) and "render.log" in logs


def _overlay(run_dir: Path, name: str, cfg: dict) -> str:
    p = run_dir / name
    p.write_text(yaml.safe_dump(cfg))
    return str(p)


def test_render_change_reruns_only_render(finished):
    extra = _overlay(finished, "render_change.yaml", {"render": {"width": 96, "height": 96}})
    out = smk(finished, "-n", "results/bear/stage_report.tsv", "--configfile", str(TINY), extra)
    assert set(planned_rules(out)) == {"render", "metrics", "stage_report"}, planned_rules(out)


def test_bgdo_change_restarts_at_bgdo_update(finished):
    extra = _overlay(finished, "bgdo_change.yaml", {"bgdo": {"delta_target": 0.2}})
    out = smk(finished, "-n", "results/bear/stage_report.tsv", "--configfile", str(TINY), extra)
    rules = planned_rules(out)
    assert "bgdo_update" in rules and "final_sim" in rules, rules
    assert not {"prepare", "cluster", "fill", "vlm_params"} & set(rules), rules
    # the first forward simulation (params_0) is reused; with one iteration none is re-run
    assert "forward_sim" not in rules, rules


def test_no_bgdo_ablation_shares_upstream(finished):
    out = smk(finished, "-n", "results/bear/ablations/no_bgdo/video.mp4", "--configfile", str(TINY))
    rules = planned_rules(out)
    assert set(rules) == {"final_sim", "render"}, rules


def test_outputs_are_strict_json_and_readable_under_the_umask(finished):
    """Every JSON artifact (files and HDF5 JSON attributes) parses under a strict parser (no
    Infinity/NaN), and every artifact has the mode the umask gives new files (issue #19)."""
    import json
    import os

    import h5py

    def strict(text):
        return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))

    umask = os.umask(0)
    os.umask(umask)
    want = 0o666 & ~umask
    artifacts = [p for p in (finished / "results").rglob("*") if p.is_file()
                 and p.suffix in (".json", ".h5", ".ply", ".npz", ".mp4", ".png", ".tsv") and "benchmarks" not in p.parts]
    assert len(artifacts) > 10
    for p in artifacts:
        assert p.stat().st_mode & 0o777 == want, (p, oct(p.stat().st_mode))
        if p.suffix == ".json":
            strict(p.read_text())
        if p.suffix == ".h5":
            with h5py.File(p, "r") as f:
                for k in ("params", "stats", "sim_config"):
                    if k in f.attrs:
                        strict(f.attrs[k])
    assert not list((finished / "results").rglob(".*.part*")), "temporary files left behind"
