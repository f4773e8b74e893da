"""physgs_steps.pipeline_bench: the parts that need no GPU and no pipeline run (the runs
themselves are measurements, printed by ``physgs bench``, never asserted)."""
from __future__ import annotations

import time

import pytest
import yaml

from physgs_steps import pipeline_bench as B


def test_set_overrides_are_nested_and_typed():
    assert B.parse_sets(["render.width=1920", "sim.compression=0", "render.backend=cpu"]) == \
        {"render": {"width": 1920, "backend": "cpu"}, "sim": {"compression": 0}}
    with pytest.raises(ValueError):
        B.parse_sets(["render.width"])


def test_workdir_holds_the_scene_and_config(tmp_path):
    wd = B.make_workdir(tmp_path / "wd", "bear", n_gaussians=3000, overrides={"render": {"width": 96}})
    cfg = yaml.safe_load((wd / "config.yaml").read_text())
    assert cfg["render"]["width"] == 96 and cfg["scenes_dir"] == str(wd / "scenes")
    scene = yaml.safe_load((wd / "scenes" / "bear.yaml").read_text())
    assert scene["builtin"]["n_gaussians"] == 3000 and scene["source"] == "builtin:bear"
    assert (wd / "Snakefile").exists() and (wd / "config" / "config.yaml").exists()
    jobs = B._jobs(wd, "bear", with_metrics=False)
    assert [j[0] for j in jobs][:4] == ["prepare", "cluster", "fill", "vlm_params"]
    assert jobs[-1][0] == "render" and all(j[0] != "metrics" for j in jobs)


def test_gpu_memory_sampler_windows():
    m = B.GpuMemory()
    m._read = None  # as on a machine without NVML or nvidia-smi
    with m:
        pass
    assert m.peak_above_baseline is None and m.peak_between(0, time.time()) is None
    m = B.GpuMemory()
    m.samples = [(10.0, 500.0), (11.0, 900.0), (12.0, 700.0), (13.0, 1500.0)]
    assert m.baseline == 500.0 and m.peak_above_baseline == 1000.0
    assert m.peak_between(10.5, 12.5) == 400.0 and m.peak_between(20, 30) is None


def test_table_lists_every_run():
    res = {"target": "bear", "n_gaussians": None, "device": "test", "runs": [
        {"structure": "inprocess", "temperature": "warm", "total_seconds": 3.5, "substep_seconds": 1.2,
         "peak_gpu_mib": 800.0, "jobs": [{"stage": "fill", "seconds": 0.5}, {"stage": "render", "seconds": 1.0}]},
        {"structure": "worker", "temperature": "cold", "total_seconds": 9.0, "substep_seconds": None,
         "peak_gpu_mib": None, "jobs": [{"stage": "render", "seconds": None}]}]}
    text = B.table(res)
    assert "| inprocess | warm | 3.50 | 1.2 | 800.0 | render 1.00, fill 0.50 |" in text
    assert "| worker | cold | 9.00 |" in text


def test_snakemake_overhead_table_and_worker_lines():
    from physgs_steps import pipeline_bench as B

    text = ("[worker 12] prepare: 0.05 s in the warm worker (0.00 s importing its modules), peak RSS 496 MiB, "
            "handed over by Snakemake's main process (pid 3)\n"
            "[worker 12] fill: 0.75 s in the warm worker (0.00 s importing its modules), peak RSS 523 MiB\n")
    secs, n = B._worker_seconds(text)
    assert n == 2 and abs(secs - 0.80) < 1e-9
    runs = [{"mode": m, "kind": k, "run": i, "wall_seconds": w, "cpu_seconds": 1.0, "jobs": 10 if k == "forceall" else 0,
             "worker_seconds": 5.0 if k == "forceall" else 0.0, "outside_stages": w - (5.0 if k == "forceall" else 0),
             "phases": {"import": 2.0 if m == "snakemake" else 0.0, "jobs": 6.0}, "outside_phases": 0.3,
             "per_job_outside_worker": 0.1 if k == "forceall" else None}
            for i, w in enumerate((3.0, 4.0)) for m in ("snakemake", "server") for k in ("noop", "forceall")]
    t = B.overhead_table({"target": "bear", "device": "cpu", "runs": runs})
    assert "| snakemake | noop | 3.50 |" in t and "| server | forceall | 3.50 |" in t
    assert "| snakemake | forceall | 2.00 |" in t  # the phase table: import
