"""The warm stage worker (physgs_steps.worker): policy, one worker serving several jobs in
order, failures, shutdown, and the Snakemake adapter's fallback.  CPU only and fast: the jobs
are ``stage_report`` jobs (a table from benchmark files)."""
from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from physgs_steps import worker as W

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="the worker uses UNIX sockets and /proc")


@pytest.fixture()
def wdir(tmp_path, monkeypatch):
    d = tmp_path / "w"
    monkeypatch.setenv("PHYSGS_WORKER_DIR", str(d))
    yield d
    W.shutdown()  # never leave a worker behind


def _bench(tmp_path: Path, name: str, seconds: float) -> str:
    p = tmp_path / f"{name}.tsv"
    p.write_text(f"s\th:m:s\tmax_rss\n{seconds}\t0:00:01\t12.5\n")
    return str(p)


def _report_job(tmp_path: Path, tag: str):
    jobs = [{"rule": "prepare", "step": None, "benchmark": _bench(tmp_path, f"prepare{tag}", 1.5)},
            {"rule": "render", "step": None, "benchmark": _bench(tmp_path, f"render{tag}", 2.5)}]
    out = tmp_path / f"report{tag}.tsv"
    return {}, {"table": str(out)}, {"jobs": jobs}, str(tmp_path / f"report{tag}.log"), out


def test_policy(monkeypatch):
    real_probe = W.has_nvidia_gpu
    monkeypatch.delenv("PHYSGS_WORKER", raising=False)
    assert W.wants_worker("render", {"enabled": True, "stages": ["render"]})
    assert not W.wants_worker("fill", {"enabled": True, "stages": ["render"]})
    assert not W.wants_worker("render", {"enabled": False})
    monkeypatch.setattr(W, "has_nvidia_gpu", lambda: False)
    monkeypatch.delenv(W.RUN_CORES_ENV, raising=False)
    assert not W.wants_worker("render", {"enabled": "auto"})
    monkeypatch.setenv(W.RUN_CORES_ENV, "2")   # a local run with 2 cores: its jobs may run side by side
    assert not W.wants_worker("render", {"enabled": "auto"})
    monkeypatch.setenv(W.RUN_CORES_ENV, "1")   # --cores 1: the jobs run one after the other anyway
    assert W.wants_worker("render", {"enabled": "auto"})
    monkeypatch.delenv(W.RUN_CORES_ENV)
    monkeypatch.setattr(W, "has_nvidia_gpu", lambda: True)
    assert W.wants_worker("render", {"enabled": "auto"})
    monkeypatch.setenv("PHYSGS_WORKER", "0")
    assert not W.wants_worker("render", {"enabled": True})
    monkeypatch.setenv("PHYSGS_WORKER", "1")
    assert W.wants_worker("final_sim", {"enabled": False})  # default stages
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert not real_probe()


def test_key_follows_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("PHYSGS_CACHE_DIR", str(tmp_path / "a"))
    a = W.worker_key()
    assert W.worker_key() == a
    monkeypatch.setenv("PHYSGS_CACHE_DIR", str(tmp_path / "b"))
    assert W.worker_key() != a


def test_one_worker_serves_jobs_in_order_then_stops(wdir, tmp_path, capfd):
    ins, outs, cfg, log, out = _report_job(tmp_path, "1")
    assert W.run_job("stage_report", ins, outs, cfg, log, idle_seconds=60) == 0
    first = W.ping()
    assert first and first["jobs"] == 1
    assert "prepare\t\t1.500" in out.read_text()
    err = capfd.readouterr().err
    assert "stage stage_report done" in err and "warm worker" in err  # the stage's log reaches the job
    ins, outs, cfg, log, out2 = _report_job(tmp_path, "2")
    assert W.run_job("stage_report", ins, outs, cfg, log) == 0
    second = W.ping()
    assert second["pid"] == first["pid"] and second["jobs"] == 2  # the same warm process
    assert out2.exists() and Path(log).read_text().count("done in") == 1
    assert W.serving_pid() == first["pid"]  # read from the worker's pid file, no round trip
    assert W.shutdown() and W.ping() is None
    assert not W.socket_path().exists() and W.serving_pid() is None
    assert not W.socket_path().with_suffix(".pid").exists()


def test_crash_is_reported_and_ends_the_worker(wdir, tmp_path):
    ins, outs, cfg, log, out = _report_job(tmp_path, "c")
    cfg = {"jobs": [{"rule": "prepare"}]}  # no benchmark key: the stage crashes (KeyError)
    assert W.run_job("stage_report", ins, outs, cfg, log) == 1
    assert not out.exists()
    assert "crashed" in Path(log).read_text()
    assert W.ping() is None  # a crash ends the worker; the next job starts a fresh one
    ins, outs, cfg, log, out = _report_job(tmp_path, "d")
    assert W.run_job("stage_report", ins, outs, cfg, log) == 0 and out.exists()


def test_dispatch_in_process_when_disabled(wdir, tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSGS_WORKER", "0")
    ins, outs, cfg, log, out = _report_job(tmp_path, "p")
    smk = SimpleNamespace(input=SimpleNamespace(items=lambda: ins.items()),
                          output=SimpleNamespace(items=lambda: outs.items()),
                          params=SimpleNamespace(cfg=cfg), log=[log], config={"worker": {"enabled": True}})
    W.dispatch("stage_report", smk)
    assert out.exists()
    assert W.ping() is None  # no worker was started
    assert "stage_report" in W.ENTRIES and json.loads(json.dumps(W.ENTRIES))


def test_worker_module_imports_only_the_standard_library():
    import subprocess

    code = ("import sys, physgs_steps.worker, physgs_steps.job; heavy = [m for m in ('torch', 'taichi', 'yaml', "
            "'h5py', 'scipy', 'numpy', 'snakemake') if m in sys.modules]; print(heavy)")
    env = dict(os.environ, PYTHONPATH=str(Path(W.__file__).resolve().parents[1]))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr


def _job_cmd(stage: str, spec, log: str) -> list[str]:
    return [sys.executable, "-m", "physgs_steps.job", stage, spec if isinstance(spec, str) else json.dumps(spec), log]


def _job_env(**extra) -> dict:
    return dict(os.environ, PYTHONPATH=str(Path(W.__file__).resolve().parents[1]), **extra)


def test_job_client_runs_in_the_worker_or_in_process(wdir, tmp_path, monkeypatch):
    """The stage rules' command (physgs_steps.job): in the warm worker when wanted, in its own
    process when not; the spec as JSON text or as @file; the stage's failure is its exit status."""
    import subprocess

    # PYTHONPATH is part of the worker's key: this process must name the worker the jobs start
    # (and stop it at the end), whatever PYTHONPATH the suite runs under
    monkeypatch.setenv("PYTHONPATH", _job_env()["PYTHONPATH"])

    ins, outs, cfg, log, out = _report_job(tmp_path, "j1")
    spec = {"input": ins, "output": outs, "cfg": cfg, "worker": {"stages": ["stage_report"]}}
    r = subprocess.run(_job_cmd("stage_report", spec, log), capture_output=True, text=True,
                       env=_job_env(PHYSGS_WORKER="1", PHYSGS_WORKER_DIR=str(wdir)))
    assert r.returncode == 0, r.stderr
    assert "in the warm worker" in r.stderr and "prepare\t\t1.500" in out.read_text()
    assert W.ping() and W.ping()["jobs"] == 1

    ins, outs, cfg, log, out = _report_job(tmp_path, "j2")  # no worker wanted: runs here, from a spec file
    f = tmp_path / "spec.json"
    f.write_text(json.dumps({"input": ins, "output": outs, "cfg": cfg, "worker": {"stages": ["stage_report"]}}))
    r = subprocess.run(_job_cmd("stage_report", f"@{f}", log), capture_output=True, text=True,
                       env=_job_env(PHYSGS_WORKER="0", PHYSGS_WORKER_DIR=str(wdir)))
    assert r.returncode == 0, r.stderr
    assert "in the warm worker" not in r.stderr and out.exists()
    assert W.ping()["jobs"] == 1  # the worker did not see it

    ins, outs, cfg, log, out = _report_job(tmp_path, "j3")  # a failing stage: its status, no output
    spec = {"input": ins, "output": outs, "cfg": {"jobs": [{"rule": "prepare", "benchmark": str(tmp_path / "none.tsv")}]}}
    r = subprocess.run(_job_cmd("stage_report", spec, log), capture_output=True, text=True,
                       env=_job_env(PHYSGS_WORKER="0", PHYSGS_WORKER_DIR=str(wdir)))
    assert r.returncode != 0 and not out.exists()


def test_job_client_rejects_a_bad_spec(tmp_path):
    import subprocess

    env = _job_env(PHYSGS_WORKER="0")
    r = subprocess.run(_job_cmd("stage_report", "{not json", str(tmp_path / "l.log")), capture_output=True, text=True,
                       env=env)
    assert r.returncode != 0 and "not valid JSON" in r.stderr
    r = subprocess.run(_job_cmd("stage_report", f"@{tmp_path / 'missing.json'}", str(tmp_path / "l.log")),
                       capture_output=True, text=True, env=env)
    assert r.returncode != 0 and "missing.json" in r.stderr
    r = subprocess.run(_job_cmd("no_such_stage", {"input": {}, "output": {}, "cfg": {}}, str(tmp_path / "l.log")),
                       capture_output=True, text=True, env=env)
    assert r.returncode == 2 and "unknown stage 'no_such_stage'" in r.stderr


def test_job_command_round_trip(tmp_path, monkeypatch):
    """The rules' params.job: the spec survives the shell's quoting, and a spec too long for one
    argument goes to a content-addressed file under .snakemake/physgs_jobs."""
    import shlex

    from physgs_steps import job as J

    monkeypatch.chdir(tmp_path)
    cfg = {"prompt": "it's a \"bear\" $HOME `x`", "n": 3, "E": 5e4}
    argv = shlex.split(J.command("render", {"scene": "a b.ply"}, {"video": "v.mp4"}, cfg, {"enabled": True}, "py"))
    assert argv[:4] == ["py", "-m", "physgs_steps.job", "render"]
    assert J.read_spec(argv[4]) == {"input": {"scene": "a b.ply"}, "output": {"video": "v.mp4"}, "cfg": cfg,
                                    "worker": {"enabled": True}}
    big = {"items": ["x" * 100] * (J.SPEC_ARG_LIMIT // 100)}
    argv = shlex.split(J.command("render", {}, {}, big))
    assert argv[4].startswith("@") and Path(argv[4][1:]).parent == (tmp_path / ".snakemake" / "physgs_jobs").resolve()
    assert J.read_spec(argv[4])["cfg"] == big
    assert shlex.split(J.command("render", {}, {}, big))[4] == argv[4]  # the same spec, the same file


def test_run_block_hands_the_job_to_the_worker(wdir, tmp_path, monkeypatch):
    """The stage rules' run: block (common.smk stage_job -> job.run_in_worker), in Snakemake's own
    process: the worker runs the job (no process started for it) and freezes what survives its
    garbage collection; without a worker wanted it returns False (the rule then runs the job
    client); a failed stage raises with the stage and its log named."""
    from physgs_steps import job as J

    monkeypatch.delenv("PHYSGS_WORKER", raising=False)
    wcfg = {"enabled": True, "stages": ["stage_report"]}
    ins, outs, cfg, log, out = _report_job(tmp_path, "r1")
    assert J.run_in_worker("stage_report", ins, outs, cfg, log, wcfg) is True
    assert "prepare\t\t1.500" in out.read_text()
    info = W.ping()
    assert info["jobs"] == 1 and info["gc_frozen"] > 0  # the next job's collection skips the warm state

    ins, outs, cfg, log, out = _report_job(tmp_path, "r2")
    assert J.run_in_worker("stage_report", ins, outs, cfg, log, {"enabled": False}) is False
    assert not out.exists() and W.ping()["jobs"] == 1

    ins, outs, cfg, log, out = _report_job(tmp_path, "r3")
    bad = {"jobs": [{"rule": "prepare", "benchmark": str(tmp_path / "none.tsv")}]}
    with pytest.raises(J.StageFailed, match=r"stage_report failed in the warm stage worker .* its log: .*r3.log"):
        J.run_in_worker("stage_report", ins, outs, bad, log, wcfg)
    assert not out.exists()


def test_snakemake_runs_stage_jobs_in_its_own_thread(wdir, tmp_path, monkeypatch):
    """A local `snakemake --cores 1` run (profiles/default: force-use-threads) hands each stage job
    to the warm worker from Snakemake's own process: no job command is run (-p prints none), no
    Snakemake process is spawned per job, and the log, benchmark and output are made."""
    import subprocess

    repo = Path(W.__file__).resolve().parents[2]
    d = tmp_path / "run"
    d.mkdir()
    for name in ("Snakefile", "workflow", "config", "src", "tests", "profiles"):
        (d / name).symlink_to(repo / name)
    env = dict(os.environ, PHYSGS_WORKER="1", PHYSGS_WORKER_DIR=str(wdir), PYTHONPATH=str(repo / "src"))
    monkeypatch.setenv("PYTHONPATH", env["PYTHONPATH"])  # this process names the same worker (fixture stops it)
    r = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "-p", "results/bear/scene.ply",
                        "--configfile", "tests/slurm/config.yaml"], cwd=d, capture_output=True, text=True,
                       timeout=600, stdin=subprocess.DEVNULL, env=env)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-4000:]
    assert re.search(r"\] prepare: .* in the warm worker .* handed over by Snakemake's main process", out), out[-3000:]
    assert "physgs_steps.job" not in out, out[-3000:]
    assert (d / "results" / "bear" / "scene.ply").stat().st_size > 0
    assert (d / "results" / "bear" / "benchmarks" / "prepare.tsv").read_text().startswith("s\t")
    assert "done in" in (d / "results" / "bear" / "logs" / "prepare.log").read_text()
