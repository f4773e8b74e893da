"""The warm Snakemake server (physgs_steps.smk_server): ``physgs snakemake ARGS`` runs Snakemake's
command line in a forked child of a process that imported Snakemake once.  A tiny Snakefile
(no physgs stage): outputs, ``log:``/``benchmark:`` files and metadata as with ``snakemake``,
the client's environment, working folder and exit status, one server for several runs, the
fallback without a server, and Ctrl-C."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from physgs_steps import smk_server as S

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="the server uses UNIX sockets and fork")

SRC = str(Path(__file__).resolve().parents[1] / "src")

SNAKEFILE = """
rule all:
    input: "out/a.txt"

rule a:
    output: "out/a.txt"
    log: "logs/a.log"
    benchmark: "bench/a.tsv"
    shell: "echo $PHYSGS_TEST_VALUE > {output}; pwd > {log}"

rule fails:
    output: "out/never.txt"
    shell: "echo 'physgs-test: rule fails on purpose' >&2; exit 3"

rule slow:
    output: "out/slow.txt"
    shell: "sleep 60; touch {output}"
"""


@pytest.fixture()
def wf(tmp_path, monkeypatch):
    d = tmp_path / "wf"
    d.mkdir()
    (d / "Snakefile").write_text(SNAKEFILE)
    env = dict(os.environ)
    env["PHYSGS_WORKER_DIR"] = str(tmp_path / "w")  # this test's own server
    env["PYTHONPATH"] = os.pathsep.join([SRC] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env.pop(S.ENV_SWITCH, None)
    monkeypatch.setenv("PHYSGS_WORKER_DIR", str(tmp_path / "w"))
    monkeypatch.setenv("PYTHONPATH", env["PYTHONPATH"])
    yield d, env
    S.stop()


def physgs_snakemake(d: Path, env: dict, *args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "physgs_steps.cli", "snakemake", "--cores", "1", *args], cwd=d,
                          env=env, capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL, **kw)


def test_runs_snakemake_in_a_warm_child(wf):
    d, env = wf
    env = dict(env, PHYSGS_TEST_VALUE="from-the-client")
    r = physgs_snakemake(d, env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (d / "out" / "a.txt").read_text().strip() == "from-the-client"  # the client's environment
    assert (d / "logs" / "a.log").read_text().strip() == str(d)              # and working folder
    assert (d / "bench" / "a.tsv").read_text().startswith("s\t")            # benchmark: as with snakemake
    assert any((d / ".snakemake" / "metadata").iterdir())                    # metadata for rerun triggers
    info = S.ping()
    assert info is not None and info["runs"] == 1
    r2 = physgs_snakemake(d, env)
    assert r2.returncode == 0 and "Nothing to be done" in r2.stdout + r2.stderr
    info2 = S.ping()
    assert info2["pid"] == info["pid"] and info2["runs"] == 2               # the same server, no new import
    r3 = physgs_snakemake(d, env, "out/never.txt")
    assert r3.returncode == 1                                                 # Snakemake's exit status
    assert "rule fails on purpose" in r3.stderr                              # the job's stderr reaches ours
    assert "Error in rule fails" in r3.stdout + r3.stderr


def test_without_server_runs_in_process(wf):
    d, env = wf
    env = dict(env, PHYSGS_TEST_VALUE="in-process", **{S.ENV_SWITCH: "0"})
    r = physgs_snakemake(d, env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (d / "out" / "a.txt").read_text().strip() == "in-process"
    assert S.ping() is None                                                   # no server was started


def test_ctrl_c_stops_the_run(wf):
    d, env = wf
    p = subprocess.Popen([sys.executable, "-m", "physgs_steps.cli", "snakemake", "--cores", "1", "out/slow.txt"],
                         cwd=d, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         stdin=subprocess.DEVNULL)
    t_end = time.monotonic() + 120
    while time.monotonic() < t_end and not list((d / ".snakemake").glob("incomplete/*")):
        time.sleep(0.2)  # the job has started
    time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    out, _ = p.communicate(timeout=60)
    assert p.returncode != 0, out
    assert not (d / "out" / "slow.txt").exists()
    assert "Terminating processes on user request" in out


def test_warm_package_kept_only_for_this_source_tree(tmp_path):
    """A child keeps the server's imported physgs_steps only where the workflow would import that
    very package (<cwd>/src/physgs_steps); another checkout imports its own."""
    src = Path(S.__file__).resolve().parents[1]
    same = tmp_path / "same"
    same.mkdir()
    (same / "Snakefile").write_text("")
    (same / "src").symlink_to(src)
    assert S._keeps_package(["--cores", "1"], str(same))
    assert not S._keeps_package(["-s", "other/Snakefile"], str(same))
    assert not S._keeps_package(["--directory=elsewhere"], str(same))
    other = tmp_path / "other"
    (other / "src" / "physgs_steps").mkdir(parents=True)
    (other / "Snakefile").write_text("")
    assert not S._keeps_package(["--cores", "1"], str(other))
    assert not S._keeps_package([], str(tmp_path))  # no Snakefile here
