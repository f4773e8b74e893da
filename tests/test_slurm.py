"""The workflow through a real SLURM: a one-node cluster on localhost, started by this test.

munged (as the munge user), slurmctld and slurmd run from a throwaway slurm.conf in a temporary
folder (proctrack/linuxproc, task/none, no cgroups, no accounting). The README's cluster
command (`snakemake --workflow-profile profiles/slurm ...`) then regenerates the tiny bear's video
(every rule of the chain, one SLURM job each), and every artifact is compared with the same file
of the session's local run of that configuration (conftest.py `tiny_bear_run`, also read by
test_workflow.py: the local run is made once per session, not once per test).
Only the daemons started here are stopped, by their PIDs, also when the test fails.

Settings that only this test needs (README.md, "Running on a cluster", explains them): the config at
/etc/slurm/slurm.conf (a symlink to the throwaway one, removed afterwards), and on the
command line --slurm-status-command squeue, --slurm-no-account,
--slurm-init-seconds-before-status-checks 3 (plus --slurm-keep-successful-logs to check them).

Needs: the SLURM and MUNGE programs (tools/ci_slurm_setup.sh installs them), root, and the
`slurm` extra (snakemake-executor-plugin-slurm).
"""
from __future__ import annotations

import importlib.util
import json
import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import make_run_dir

REPO = Path(__file__).resolve().parents[1]
TEST_CONFIG = "tests/slurm/config.yaml"
SCENES = ("bear", "duck_stone")
TARGETS = [f"results/{s}/video.mp4" for s in SCENES]  # the dry runs' (resource requests)
RUN_TARGET = "results/bear/video.mp4"  # the SLURM run's: the smallest scene runs every rule
DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "srun", "squeue", "sinfo", "scontrol", "scancel", "munge")
SEARCH_PATH = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin", "/usr/bin"])
SYSTEM_CONF = Path("/etc/slurm/slurm.conf")
TMP_PREFIX = "physgs-slurm-"
# bound for a hung run (the SLURM run takes about 1.5 minutes on 2 cores)
SLURM_TIMEOUT_S = 270


def which(prog: str) -> str | None:
    return shutil.which(prog, path=SEARCH_PATH)


def ours(path: Path) -> bool:
    """Whether ``path`` is a link into a folder that this test creates."""
    return path.is_symlink() and os.readlink(path).startswith(str(Path(tempfile.gettempdir()) / TMP_PREFIX))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def node_memory_mb() -> int:
    """90 % of this machine's memory in MB (slurm.conf RealMemory must not exceed what slurmd
    finds), from /proc/meminfo."""
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) // 1024 * 9 // 10
    raise RuntimeError("MemTotal missing from /proc/meminfo")


def tail(path: Path, n: int = 40) -> str:
    if not path.exists():
        return f"({path} does not exist)"
    return f"--- {path} (last {n} lines)\n" + "\n".join(path.read_text(errors="replace").splitlines()[-n:])


class LocalSlurm:
    """munged + slurmctld + slurmd on localhost from a throwaway folder ``base``."""

    def __init__(self, base: Path):
        self.base = base
        self.conf = base / "slurm.conf"
        self.munge_dir = base / "munge"
        self.socket = self.munge_dir / "munge.socket"
        self.procs: dict[str, subprocess.Popen] = {}
        self.linked_system_conf = False
        self.env = dict(os.environ, SLURM_CONF=str(self.conf), PATH=SEARCH_PATH)

    # ---------------------------------------------------------------- set-up
    def write_config(self) -> None:
        for d in ("state", "spool"):
            (self.base / d).mkdir()
        self.conf.write_text(f"""# throwaway one-node cluster of tests/test_slurm.py
ClusterName=physgstest
SlurmctldHost=localhost
SlurmctldPort={free_port()}
SlurmdPort={free_port()}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={self.socket}
SlurmUser=root
SlurmdUser=root
StateSaveLocation={self.base}/state
SlurmdSpoolDir={self.base}/spool
SlurmctldPidFile={self.base}/slurmctld.pid
SlurmdPidFile={self.base}/slurmd.pid
SlurmctldLogFile={self.base}/slurmctld.log
SlurmdLogFile={self.base}/slurmd.log
MailProg=/bin/true
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/builtin
SchedulerParameters=batch_sched_delay=0,sched_min_interval=0
MpiDefault=none
ReturnToService=2
MinJobAge=300
NodeName=localhost NodeAddr=127.0.0.1 CPUs={os.cpu_count()} RealMemory={node_memory_mb()} State=UNKNOWN
PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP
""")

    def write_munge_key(self) -> None:
        """A private key and socket folder owned by the munge user (munged insists on it)."""
        self.munge_dir.mkdir()
        key = self.munge_dir / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o600)
        user = pwd.getpwnam("munge")
        for p in (self.munge_dir, key):
            os.chown(p, user.pw_uid, user.pw_gid)
        self.munge_dir.chmod(0o755)

    def link_system_conf(self) -> None:
        """The job-step plugin drops SLURM_CONF before its inner srun, which then reads the
        default /etc/slurm/slurm.conf: point that at our config for the test's lifetime."""
        SYSTEM_CONF.parent.mkdir(parents=True, exist_ok=True)
        if ours(SYSTEM_CONF):
            SYSTEM_CONF.unlink()  # left by an earlier run of this test that was killed
        os.symlink(self.conf, SYSTEM_CONF)
        self.linked_system_conf = True

    def spawn(self, name: str, argv: list[str], **kw) -> None:
        log = open(self.base / f"{name}.out", "w")
        self.procs[name] = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                            env=self.env, **kw)
        log.close()

    def wait_for(self, what: str, check, timeout: float = 30.0) -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            for name, p in self.procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f"{name} exited with {p.returncode} while waiting for {what}\n"
                                       + tail(self.base / f"{name}.out") + "\n" + self.logs())
            if check():
                return
            time.sleep(0.2)
        raise RuntimeError(f"timed out after {timeout:.0f} s waiting for {what}\n" + self.logs())

    def start(self) -> None:
        self.write_munge_key()
        self.write_config()
        self.link_system_conf()
        m = self.munge_dir
        self.spawn("munged", [which("munged"), "--foreground", "--socket", str(self.socket),
                              "--key-file", str(m / "munge.key"), "--pid-file", str(m / "munged.pid"),
                              "--log-file", str(m / "munged.log"), "--seed-file", str(m / "munged.seed")],
                   user="munge", group="munge")
        self.wait_for("the munge socket", self.socket.exists)
        self.spawn("slurmctld", [which("slurmctld"), "-D", "-f", str(self.conf)])
        self.wait_for("slurmctld", lambda: self.run(["scontrol", "ping"], check=False).stdout.count("UP") > 0)
        self.spawn("slurmd", [which("slurmd"), "-D", "-N", "localhost", "-f", str(self.conf)])
        self.wait_for("the node to be idle", lambda: self.run(["sinfo", "-h", "-o", "%T"], check=False).stdout.strip() == "idle")

    # ---------------------------------------------------------------- use
    def run(self, argv: list[str], check: bool = True) -> subprocess.CompletedProcess:
        return subprocess.run([which(argv[0]), *argv[1:]], env=self.env, capture_output=True, text=True,
                              timeout=30, check=check)

    def completed_job_ids(self) -> list[int]:
        text = (self.base / "slurmctld.log").read_text(errors="replace")
        return sorted({int(j) for j in re.findall(r"_job_complete: JobId=(\d+) done", text)})

    def logs(self) -> str:
        return "\n".join(tail(self.base / f"{n}.log") for n in ("slurmctld", "slurmd"))

    # ---------------------------------------------------------------- tear-down
    def job_pids(self) -> set[int]:
        """PIDs of the processes of our jobs on the node and of their slurmstepd parents."""
        out = self.run(["scontrol", "listpids"], check=False).stdout.splitlines()[1:]
        pids = {int(line.split()[0]) for line in out if line.split() and line.split()[0].isdigit()}
        for pid in list(pids):
            try:  # /proc/<pid>/stat: "pid (comm) state ppid ..."
                ppid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            if Path(f"/proc/{ppid}/comm").exists() and Path(f"/proc/{ppid}/comm").read_text().strip() == "slurmstepd":
                pids.add(ppid)
        return pids

    def cancel_jobs(self) -> None:
        """Cancel what is left in our queue and wait for its processes to end (SIGKILL, by PID,
        after 30 s)."""
        slurmd = self.procs.get("slurmd")
        pids = self.job_pids() if slurmd is not None and slurmd.poll() is None else set()
        left = self.run(["squeue", "-h", "-o", "%i"], check=False).stdout.split()
        if left:
            self.run(["scancel", *left], check=False)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 30 and (
                self.run(["squeue", "-h", "-o", "%i"], check=False).stdout.strip()
                or any(Path(f"/proc/{pid}").exists() for pid in pids)):
            time.sleep(0.3)
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def stop(self) -> None:
        """Cancel our jobs, then stop our daemons (by PID), newest first, and remove the
        /etc/slurm/slurm.conf link."""
        if "slurmctld" in self.procs and self.procs["slurmctld"].poll() is None:
            try:
                self.cancel_jobs()
            except (subprocess.SubprocessError, OSError) as e:  # stop the daemons all the same
                print(f"cancelling the test cluster's jobs failed: {e}")
        for name in reversed(list(self.procs)):
            p = self.procs[name]
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(timeout=5)
        if self.linked_system_conf and SYSTEM_CONF.is_symlink() and os.readlink(SYSTEM_CONF) == str(self.conf):
            SYSTEM_CONF.unlink()


@pytest.fixture(scope="module")
def slurm():
    missing = [p for p in DAEMONS + CLIENTS if which(p) is None]
    if missing:
        pytest.skip(f"SLURM/MUNGE programs not installed ({', '.join(missing)}); "
                    "bash tools/ci_slurm_setup.sh installs them")
    if os.geteuid() != 0:
        pytest.skip("the throwaway cluster runs munged as the munge user and slurmd as root: needs root")
    if (SYSTEM_CONF.exists() or SYSTEM_CONF.is_symlink()) and not ours(SYSTEM_CONF):
        pytest.skip(f"{SYSTEM_CONF} exists: this machine has a SLURM set-up of its own, which this test "
                    "leaves alone")
    assert importlib.util.find_spec("snakemake_executor_plugin_slurm"), (
        "SLURM is installed but snakemake-executor-plugin-slurm is not: pip install -e '.[slurm]' "
        "(tools/ci_slurm_setup.sh installs it)")

    base = Path(tempfile.mkdtemp(prefix=TMP_PREFIX))
    base.chmod(0o755)  # munged (munge user) must reach its socket folder
    cluster = LocalSlurm(base)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()
        shutil.rmtree(base, ignore_errors=True)


def snakemake(cwd: Path, args: list[str], timeout: float, env: dict, context=lambda: "") -> str:
    """Run snakemake in its own process group; on timeout kill that group (Snakemake waiting
    on a job status that never comes ignores SIGTERM). ``context()`` is added to a failure."""
    log_path = cwd / "snakemake.out"
    with open(log_path, "w") as log:
        p = subprocess.Popen([sys.executable, "-m", "snakemake", *args], cwd=cwd, env=env, stdout=log,
                             stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            pytest.fail(f"snakemake {' '.join(args)} did not finish in {timeout:.0f} s\n" + tail(log_path, 60)
                        + "\n" + context())
    out = log_path.read_text(errors="replace")
    assert p.returncode == 0, f"snakemake {' '.join(args)} failed ({p.returncode})\n" + tail(log_path, 80) + "\n" + context()
    return out


def artifacts(results: Path) -> dict[str, Path]:
    """Relative path -> file for every artifact (logs and benchmark tables left out)."""
    out = {}
    for f in results.rglob("*"):
        rel = f.relative_to(results).as_posix()
        if f.is_file() and "/logs/" not in f"/{rel}" and "/benchmarks/" not in f"/{rel}":
            out[rel] = f
    return out


def is_measurement(key: str) -> bool:
    """Keys that record how long or how much memory something took (differ between runs)."""
    return re.search(r"second|timing|time_s|_s$|_ms$|peak|rss|memory|_mb$|_mib$|elapsed|duration|per_s",
                     key) is not None


def assert_json_close(a, b, where: str, rtol: float = 1e-2) -> None:
    """Equal JSON, numbers within rtol; keys that are timings or memory are not compared."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            if is_measurement(k):
                continue
            assert_json_close(a[k], b[k], f"{where}.{k}", rtol)
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{where}: lists of {len(a)} and {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_json_close(x, y, f"{where}[{i}]", rtol)
    elif isinstance(a, float) or isinstance(b, float):
        assert np.isclose(a, b, rtol=rtol, atol=1e-9), f"{where}: {a} != {b}"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def video_frames(path: Path) -> tuple[int, tuple]:
    """(number of frames, frame shape) of a video, decoded with imageio's ffmpeg reader."""
    import imageio

    n, shape = 0, None
    with imageio.get_reader(path, "ffmpeg") as reader:
        for frame in reader:
            n, shape = n + 1, frame.shape
    return n, shape


def assert_positions_close(xa: np.ndarray, xb: np.ndarray, where: str, atol: float = 1e-3) -> None:
    """Particle positions (domain units) of both runs: the CPU solver sums with parallel
    atomics, so bit-equal results are not promised; 1e-3 is 0.1 % of the domain."""
    assert xa.shape == xb.shape, f"{where}: {xa.shape} != {xb.shape}"
    assert np.all(np.isfinite(xb)), where
    diff = float(np.max(np.abs(xa - xb))) if xa.size else 0.0
    assert diff <= atol, f"{where}: positions differ by up to {diff:.3g}"


def compare_runs(local: Path, remote: Path) -> None:
    """Every artifact of the SLURM run against the same file of the local run. The local run
    went on to the metrics and the stage report (test_workflow.py reads those): only these
    may be missing from the SLURM run."""
    a, b = artifacts(local / "results"), artifacts(remote / "results")
    assert set(b) <= set(a), f"only in the SLURM run: {sorted(set(b) - set(a))}"
    beyond_video = {"metrics.json", "stage_report.tsv"}
    assert {rel.rsplit("/", 1)[-1] for rel in set(a) - set(b)} <= beyond_video, \
        f"missing from the SLURM run: {sorted(set(a) - set(b))}"
    a = {rel: f for rel, f in a.items() if rel in b}
    import h5py

    for rel in sorted(a):
        name = rel.rsplit("/", 1)[-1]
        if name == "scene.ply":
            assert a[rel].read_bytes() == b[rel].read_bytes(), rel
        elif name.endswith(".json"):
            assert_json_close(json.loads(a[rel].read_text()), json.loads(b[rel].read_text()), rel)
        elif name.endswith(".npz"):
            za, zb = np.load(a[rel]), np.load(b[rel])
            assert sorted(za.files) == sorted(zb.files), rel
            for k in (k for k in za.files if not is_measurement(k)):
                np.testing.assert_array_equal(za[k], zb[k], err_msg=f"{rel}:{k}")
        elif name == "particles.h5":
            with h5py.File(a[rel]) as fa, h5py.File(b[rel]) as fb:
                for k in ("x", "label", "filled", "vol"):
                    np.testing.assert_array_equal(fa[k][()], fb[k][()], err_msg=f"{rel}:{k}")
        elif name == "final.h5":
            with h5py.File(a[rel]) as fa, h5py.File(b[rel]) as fb:
                np.testing.assert_array_equal(fa["particle_index"][()], fb["particle_index"][()], err_msg=rel)
                np.testing.assert_array_equal(fa["frame_row"][()], fb["frame_row"][()], err_msg=rel)
                assert_positions_close(fa["x"][()], fb["x"][()], rel)
        elif name == "forward.h5":
            with h5py.File(a[rel]) as fa, h5py.File(b[rel]) as fb:
                assert sorted(fa["keyframes"]) == sorted(fb["keyframes"]), rel
                for k in fa["keyframes"]:
                    assert_positions_close(fa["keyframes"][k]["x"][()], fb["keyframes"][k]["x"][()], f"{rel}:{k}")
        elif name.endswith(".png"):
            import imageio.v3 as iio

            assert iio.imread(a[rel]).shape == iio.imread(b[rel]).shape, rel
        elif name == "video.mp4":
            na, shape_a = video_frames(a[rel])
            nb, shape_b = video_frames(b[rel])
            assert na == nb and na > 1 and shape_a == shape_b, f"{rel}: {na} frames {shape_a} vs {nb} frames {shape_b}"
        else:
            assert a[rel].stat().st_size > 0 and b[rel].stat().st_size > 0, rel


@pytest.mark.slurm
def test_workflow_through_slurm_matches_local_run(slurm, tiny_bear_run, tmp_path):
    env = dict(slurm.env)
    env.setdefault("PHYSGS_CACHE_DIR", str(REPO / ".cache"))
    remote = make_run_dir(tmp_path / "slurm")

    # the target first: --configfile takes every following word up to the next option
    t0 = time.monotonic()
    out = snakemake(remote, [RUN_TARGET, "--workflow-profile", "profiles/slurm", "--configfile", TEST_CONFIG,
                             # test-only settings (README "Running on a cluster": a real cluster needs none)
                             "--slurm-status-command", "squeue", "--slurm-no-account",
                             "--slurm-init-seconds-before-status-checks", "3", "--seconds-between-status-checks", "1",
                             "--slurm-keep-successful-logs", "--latency-wait", "10"],
                    SLURM_TIMEOUT_S, env, context=slurm.logs)
    print(f"SLURM run {time.monotonic() - t0:.0f} s")

    assert (remote / RUN_TARGET).stat().st_size > 0
    # every job went through sbatch: one SLURM log per job, each job completed in slurmctld
    slurm_logs = sorted((remote / "logs" / "slurm").rglob("*.log"))
    submitted = re.findall(r"has been submitted with SLURM jobid (\d+)", out)
    assert submitted, "no job was submitted through sbatch\n" + out[-3000:]
    assert len(slurm_logs) == len(submitted), (len(slurm_logs), len(submitted))
    assert {int(j) for j in submitted} <= set(slurm.completed_job_ids()), slurm.logs()
    rules = {p.relative_to(remote / "logs" / "slurm").parts[0] for p in slurm_logs}
    for rule in ("prepare", "cluster", "fill", "vlm_params", "forward_sim", "bgdo_update", "final_sim", "render"):
        assert f"rule_{rule}" in rules, sorted(rules)

    compare_runs(tiny_bear_run, remote)


GPU_RULES = {"vlm_params", "forward_sim", "bgdo_update", "final_sim", "render"}
CPU_RULES = {"prepare", "cluster", "fill"}


def dry_run_resources(run_dir: Path, extra: list[str]) -> dict[str, list[dict[str, str]]]:
    """rule -> the resources of each of its jobs, as a dry run with the SLURM profile plans them."""
    proc = subprocess.run([sys.executable, "-m", "snakemake", *TARGETS, "--dry-run", "--forceall",
                           "--workflow-profile", "profiles/slurm", "--configfile", TEST_CONFIG, *extra],
                          cwd=run_dir, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    jobs: dict[str, list[dict[str, str]]] = {}
    rule = None
    for line in proc.stdout.splitlines():
        m = re.match(r"^(?:local)?rule (\w+):$", line)
        if m:
            rule = m.group(1)
        elif rule and line.strip().startswith("resources:"):
            items = [kv.split("=", 1) for kv in line.split(":", 1)[1].split(", ")]
            jobs.setdefault(rule, []).append({k.strip(): v.strip() for k, v in items})
            rule = None
    return jobs


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_gpu_requested_only_for_gpu_stages_on_cuda(tmp_path, device):
    pytest.importorskip("snakemake_executor_plugin_slurm", reason="the `slurm` extra is not installed")
    jobs = dry_run_resources(make_run_dir(tmp_path / "run"), ["--config", f"device={device}"])
    assert GPU_RULES | CPU_RULES <= set(jobs), sorted(jobs)
    for rule, reqs in jobs.items():
        for r in reqs:
            want = "1" if device == "cuda" and rule in GPU_RULES else "0"
            if rule in GPU_RULES | CPU_RULES:
                assert r.get("gpu", "0") == want, (rule, r)
                assert int(r["mem_mb"]) > 0 and int(r["runtime"]) > 0, (rule, r)
