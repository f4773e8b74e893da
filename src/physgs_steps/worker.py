"""Warm stage worker: the GPU chain's jobs run in one long-lived process per machine.

Why.  A Snakemake job is a new Python process.  On a GPU, each such process pays for the
interpreter, torch (seconds), Taichi's start, a CUDA context, loading every simulation kernel
from Taichi's offline cache (seconds: the cache holds LLVM IR, code generation runs again in
every process) and gsplat's extension, for a stage whose own work may take a second.  The
worker pays that once: Snakemake keeps its DAG, its cached artifacts, its rerun triggers and
its ``benchmark:`` files, but the job's process is a thin client (``physgs_steps.job``, the
stage rules' command, standard library only) that hands the job (stage, inputs, outputs,
config, log path, working folder) to a warm process over a UNIX socket and relays the stage's
log lines and exit status.  The stage runs there exactly as it
would in the job (``runtime.run_stage``: same outputs, same atomic writes, same errors).

Which jobs use it: ``worker.stages`` (default: every stage but ``metrics`` and the report
jobs: prepare, cluster, fill and the parameter stages too, whose own work is a fraction of a
second to a few seconds, less than a process start) when ``worker.enabled`` is true, or
``auto`` and this machine has an
NVIDIA GPU (``/proc/driver/nvidia/gpus`` lists one and CUDA_VISIBLE_DEVICES does not hide
it) or the local Snakemake run has one core (``--cores 1``: its jobs run one after the other
anyway, so serving them in one process queues nothing; on the 2-core CPU machine it saves
the 2-7 s start of every job and the kernel loading of the second and third simulation;
common.smk sets ``PHYSGS_RUN_CORES``).  The environment variable ``PHYSGS_WORKER`` (``0``/``1``) overrides the config.  Every
other case runs the stage in the job's own process, as without a worker.

Lifetime and safety:

* one worker per user, machine, Python, source tree and relevant environment
  (``PHYSGS_CACHE_DIR``, ``TORCH_EXTENSIONS_DIR``, ``CUDA_VISIBLE_DEVICES``, ``PYTHONPATH``):
  editing the code starts a new worker, the old one ends when idle.  The socket and the
  worker's own log live in ``$PHYSGS_WORKER_DIR`` (default ``/tmp/physgs-worker-<uid>``,
  mode 0700);
* the first job that finds none starts one (under a file lock, so concurrent jobs start one);
  it ends after ``worker.idle_seconds`` (300) without a job, on ``shutdown`` (the Snakefile's
  ``onerror`` asks for it, and ``onsuccess`` too with ``worker.stop_after_run: true``), and
  after a stage crashed with an unexpected exception (a possibly broken CUDA context is never
  reused).  By default it outlives a successful run by ``idle_seconds``, so that the next run
  (a changed setting, the next scene) finds torch, Taichi's loaded kernels, gsplat and the
  CUDA context ready; ``ping`` reports what it holds (``rss_mb``, ``cuda_reserved_mb``);
* jobs are served one at a time (one GPU); parallel jobs queue;
* if the client goes away mid-job (Snakemake interrupted), the worker removes the job's
  outputs after the stage, as Snakemake would treat them as incomplete anyway;
* if no worker can be started or reached, the job runs in its own process (logged).

On a SLURM cluster each job runs on its own allocation, so a worker serves the jobs of one
allocation: put the GPU chain into one group (``--groups forward_sim=gpu bgdo_update=gpu
final_sim=gpu render=gpu``; README "GPU") and its jobs share one worker and one submission.

This module imports only the standard library at module level: the client side of a job
must start in milliseconds.
"""
from __future__ import annotations

import contextlib
import gc
import hashlib
import importlib
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

PROTOCOL = 1
DEFAULT_STAGES = ("prepare", "cluster", "fill", "vlm_params", "pinned_params", "forward_sim", "bgdo_update",
                  "final_sim", "render", "bench_stress")
DEFAULT_IDLE_SECONDS = 300.0
START_TIMEOUT_S = 60.0

# stage name -> "module:function" (the library entry of each stage; cli._stage_fn agrees)
ENTRIES = {
    "prepare": "physgs_steps.prepare:run",
    "cluster": "physgs_steps.cluster:run",
    "fill": "physgs_steps.fill:run",
    "vlm_params": "physgs_steps.params.stage:run",
    "pinned_params": "physgs_steps.params.stage:run_pinned",
    "forward_sim": "physgs_steps.simulate:run_forward",
    "final_sim": "physgs_steps.simulate:run_final",
    "bgdo_update": "physgs_steps.bgdo:run",
    "render": "physgs_steps.render.stage:run",
    "metrics": "physgs_steps.metrics.stage:run",
    "stage_report": "physgs_steps.stage_report:run",
    "bench_stress": "physgs_steps.benchmark.stress:run",
}


def stage_function(name: str):
    """The library function ``run(inputs, outputs, cfg, log)`` of stage ``name`` (imported now)."""
    mod, fn = ENTRIES[name].split(":")
    return getattr(importlib.import_module(mod), fn)


# ============================================================================ policy
def has_nvidia_gpu() -> bool:
    """True when the NVIDIA driver lists a GPU and CUDA_VISIBLE_DEVICES does not hide it all
    (no CUDA library is loaded to find out)."""
    vis = os.environ.get("CUDA_VISIBLE_DEVICES")
    if vis is not None and vis.strip() in ("", "-1", "none", "NoDevFiles"):
        return False
    d = Path("/proc/driver/nvidia/gpus")
    try:
        return d.is_dir() and any(d.iterdir())
    except OSError:
        return False


RUN_CORES_ENV = "PHYSGS_RUN_CORES"  # the local Snakemake run's --cores (set by common.smk)


def note_run_cores(cores) -> None:
    """Record a local Snakemake run's ``--cores`` for the jobs' ``worker.enabled: auto`` policy
    (called by common.smk in the main process; ``cores()`` raises where none were given, e.g.
    a dry run, and inside a SLURM job the run is not local: both leave the policy to the GPU
    probe)."""
    n = None
    if not os.environ.get("SLURM_JOB_ID"):
        try:
            n = str(cores())
        except Exception:
            n = None
    if n is None:
        os.environ.pop(RUN_CORES_ENV, None)
    else:
        os.environ[RUN_CORES_ENV] = n


def wants_worker(stage: str, wcfg: dict | None) -> bool:
    """Whether ``stage`` runs in the warm worker under the ``worker`` config section."""
    wcfg = wcfg or {}
    env = os.environ.get("PHYSGS_WORKER")
    if env is not None and env.strip() != "":
        enabled = env.strip().lower() not in ("0", "false", "no", "off")
    else:
        enabled = wcfg.get("enabled", "auto")
        if enabled == "auto":
            enabled = has_nvidia_gpu() or os.environ.get(RUN_CORES_ENV, "").strip() == "1"
    return bool(enabled) and stage in tuple(wcfg.get("stages", DEFAULT_STAGES))


# ============================================================================ identity
def worker_dir() -> Path:
    d = Path(os.environ.get("PHYSGS_WORKER_DIR") or f"/tmp/physgs-worker-{os.getuid()}")
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    return d


def _source_fingerprint() -> str:
    """Paths, sizes and mtimes of the package's source and data files."""
    pkg = Path(__file__).resolve().parent
    h = hashlib.sha1(str(pkg).encode())
    for root, dirs, files in os.walk(pkg):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for f in sorted(files):
            if f.endswith((".py", ".yaml", ".json")):
                st = os.stat(os.path.join(root, f))
                h.update(f"{root}/{f}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()


# the environment a worker is started with and keyed by: a run with other values gets its own
# worker (the knobs below are read when a stage or the solver starts: A/B runs need their own)
ENV_KEYS = ("PHYSGS_CACHE_DIR", "TORCH_EXTENSIONS_DIR", "CUDA_VISIBLE_DEVICES", "PYTHONPATH", "TI_ARCH",
            "PHYSGS_TI_REPS", "PHYSGS_TI_GRAPH", "PHYSGS_TI_FAST_LAUNCH", "PHYSGS_TI_BLOCK_DIM",
            "PHYSGS_TI_ADVANCED_OPT", "PHYSGS_PROFILE_DIR", "PHYSGS_RENDER_PER_FRAME")


def worker_key() -> str:
    """16 hex digits naming the worker that may run this process's jobs."""
    parts = [str(PROTOCOL), sys.executable, _source_fingerprint()] + [f"{k}={os.environ.get(k, '')}" for k in ENV_KEYS]
    return hashlib.sha1("\n".join(parts).encode()).hexdigest()[:16]


def socket_path(key: str | None = None) -> Path:
    return worker_dir() / f"w-{key or worker_key()}.sock"


# ============================================================================ wire format
def _send(conn: socket.socket, msg: dict) -> None:
    conn.sendall((json.dumps(msg, default=str) + "\n").encode())


def _messages(conn: socket.socket):
    """Yield the newline-delimited JSON messages arriving on ``conn`` until it closes."""
    buf = b""
    while True:
        chunk = conn.recv(65536)
        if not chunk:
            return
        buf += chunk
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            if line.strip():
                yield json.loads(line)


# ============================================================================ server
class _ConnStream:
    """A text stream that forwards writes to the client (stderr of the job)."""

    def __init__(self, conn: socket.socket, fallback):
        self.conn, self.fallback, self.alive = conn, fallback, True

    def write(self, s: str) -> int:
        if s and self.alive:
            try:
                _send(self.conn, {"out": s})
            except OSError:
                self.alive = False
        self.fallback.write(s)
        return len(s)

    def flush(self) -> None:
        self.fallback.flush()

    def isatty(self) -> bool:
        return False


def _peak_rss_mb() -> float:
    """VmHWM of this process in MiB (reset per job, see _reset_peak_rss)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _holding() -> dict:
    """What this idle worker holds: resident memory and torch's reserved CUDA memory (MiB; the
    CUDA context and Taichi's device memory pool are not visible from here: the pipeline
    benchmark samples the GPU's memory in use through NVML)."""
    rss = None
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                rss = round(int(line.split()[1]) / 1024.0, 1)
    reserved = None
    torch = sys.modules.get("torch")
    if torch is not None:
        with contextlib.suppress(Exception):
            if torch.cuda.is_initialized():
                reserved = round(torch.cuda.memory_reserved() / 2**20, 1)
    return {"rss_mb": rss, "cuda_reserved_mb": reserved, "gc_frozen": gc.get_freeze_count(),
            "loaded": [m for m in ("torch", "taichi", "gsplat") if m in sys.modules]}


def _reset_peak_rss() -> None:
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def _release_memory() -> None:
    """Return what a finished job held: Python garbage (Taichi arrays of dropped solvers) and
    torch's cached CUDA blocks.  Compiled kernels stay (that is what the worker is for).

    What survives the collection (modules, Taichi's and torch's state, compiled kernels: the
    warm worker's whole point) is then frozen (``gc.freeze``): later collections, this one after
    every job and the interpreter's own during a stage, look only at objects made since.  A full
    collection over the loaded worker took 0.32-0.40 s after every job on the 2-core CPU machine
    (0.12 s on the H100 machine) and Snakemake's next job waited for it; frozen objects are still
    freed when their last reference goes, only cycles among them are never collected."""
    gc.collect()
    gc.freeze()
    torch = sys.modules.get("torch")
    if torch is not None:
        with contextlib.suppress(Exception):
            if torch.cuda.is_available() and torch.cuda.is_initialized():
                torch.cuda.empty_cache()


def _run_job(req: dict, conn: socket.socket) -> tuple[int, bool]:
    """Run one job; returns (exit status, whether the worker may serve another job)."""
    from .runtime import _remove_outputs, run_stage

    name = req["stage"]
    os.chdir(req["cwd"])
    out = _ConnStream(conn, sys.__stderr__)
    old = sys.stdout, sys.stderr
    sys.stdout = sys.stderr = out
    _reset_peak_rss()
    healthy = True
    rc = 0
    t0 = time.perf_counter()
    try:
        fn = stage_function(name)
        t_imp = round(time.perf_counter() - t0, 3)
        summary = run_stage(name, fn, req["inputs"], req["outputs"], req["cfg"], req.get("log"), import_seconds=t_imp)
        out.write(f"[worker {os.getpid()}] {name}: {time.perf_counter() - t0:.2f} s in the warm worker "
                  f"({t_imp:.2f} s importing its modules), peak RSS {_peak_rss_mb():.0f} MiB, "
                  f"handed over by {req.get('client') or 'a job process'} (pid {req.get('client_pid')})\n")
    except SystemExit as e:  # run_stage: the stage failed (message logged) or crashed
        rc = int(e.code) if isinstance(e.code, int) else 1
        healthy = not getattr(e, "physgs_crash", False)
    except BaseException:  # an import error or worse: report it, then end this worker
        import traceback

        out.write(traceback.format_exc())
        rc, healthy = 1, False
    finally:
        sys.stdout, sys.stderr = old
    if not out.alive:  # the job was abandoned (e.g. Snakemake interrupted): leave nothing behind
        import logging

        _remove_outputs(req["outputs"], logging.getLogger("physgs.worker"))
    return rc, healthy


def serve(path: str | os.PathLike, idle_seconds: float = DEFAULT_IDLE_SECONDS) -> int:
    """Serve jobs on the UNIX socket ``path`` until idle for ``idle_seconds`` or told to stop."""
    path = Path(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(path))
    except OSError:  # another worker got there first
        return 0
    os.chmod(path, 0o600)
    ino = os.stat(path).st_ino  # the file is removed on exit only if it is still ours
    with contextlib.suppress(OSError):  # read by serving_pid() (the run's end message), no round trip
        path.with_suffix(".pid").write_text(str(os.getpid()))
    sock.listen(64)
    sock.settimeout(idle_seconds)
    jobs = 0
    print(f"[worker {os.getpid()}] serving {path} (idle limit {idle_seconds:g} s)", file=sys.stderr, flush=True)
    try:
        while True:
            try:
                conn, _ = sock.accept()
            except socket.timeout:
                _close_listener(sock, path, ino)
                print(f"[worker {os.getpid()}] idle for {idle_seconds:g} s after {jobs} jobs: exiting",
                      file=sys.stderr, flush=True)
                return 0
            with conn:
                conn.settimeout(None)
                try:
                    req = next(_messages(conn), None)
                except (OSError, ValueError):
                    continue
                if not req:
                    continue
                op = req.get("op")
                if op == "ping":
                    _send(conn, {"pid": os.getpid(), "jobs": jobs, "protocol": PROTOCOL, **_holding()})
                    continue
                if op == "shutdown":
                    _close_listener(sock, path, ino)  # no new job may queue up behind this one
                    with contextlib.suppress(OSError):
                        _send(conn, {"bye": os.getpid()})
                    return 0
                if op != "run" or req.get("protocol") != PROTOCOL:
                    with contextlib.suppress(OSError):
                        _send(conn, {"rc": 2, "error": f"unknown request {op!r} / protocol {req.get('protocol')}"})
                    continue
                jobs += 1
                rc, healthy = _run_job(req, conn)
                if not healthy:
                    _close_listener(sock, path, ino)
                with contextlib.suppress(OSError):
                    _send(conn, {"rc": rc, "pid": os.getpid()})
                conn.close()
                # after the reply: the job is done (its outputs are written) and Snakemake goes on while
                # this collects the job's garbage (a full collection over torch's and Taichi's objects
                # took 0.12 s on the 2-core machine, once per job)
                t_gc = time.perf_counter()
                _release_memory()
                print(f"[worker {os.getpid()}] job {jobs} ({req.get('stage')}): rc {rc}, garbage collected in "
                      f"{time.perf_counter() - t_gc:.3f} s after the reply", file=sys.stderr, flush=True)
                if not healthy:
                    print(f"[worker {os.getpid()}] a stage crashed: exiting so that the next job starts clean",
                          file=sys.stderr, flush=True)
                    return 0
    finally:
        _close_listener(sock, path, ino)


def _close_listener(sock: socket.socket, path: Path, ino: int) -> None:
    """Stop accepting: remove the socket file (new clients start a new worker), then close."""
    with contextlib.suppress(OSError):
        if os.stat(path).st_ino == ino:
            path.unlink()
            pid = path.with_suffix(".pid")
            if pid.read_text().strip() == str(os.getpid()):
                pid.unlink()
    with contextlib.suppress(OSError):
        sock.close()


# ============================================================================ client
def _connect(path: Path) -> socket.socket | None:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(str(path))
        return s
    except OSError:
        s.close()
        return None


def _start(path: Path, idle_seconds: float) -> socket.socket | None:
    """Start a worker for ``path`` (one at a time under a lock) and connect to it."""
    import fcntl

    lock = path.with_suffix(".lock")
    with open(lock, "w") as lf:
        fcntl.flock(lf, fcntl.LOCK_EX)
        conn = _connect(path)
        if conn is not None:
            return conn
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # a stale socket of a worker that died
        env = os.environ.copy()  # the package this client imported, whatever put it on sys.path
        src = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join([src] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        log = open(path.with_suffix(".log"), "w")  # this worker's log (a new worker starts a new one)
        proc = subprocess.Popen([sys.executable, "-m", "physgs_steps.worker", "serve", str(path),
                                 "--idle-seconds", str(idle_seconds)],
                                stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True,
                                cwd="/", env=env)
        log.close()
        t_end = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < t_end:
            conn = _connect(path)
            if conn is not None:
                return conn
            if proc.poll() is not None:
                return _connect(path)  # it lost a race to another worker, or failed
            time.sleep(0.005)
    return None


def run_job(stage: str, inputs: dict, outputs: dict, cfg: dict, log: str | None,
            idle_seconds: float = DEFAULT_IDLE_SECONDS, client: str | None = None) -> int | None:
    """Run one job in the warm worker (starting it if needed); relay its output to stderr.

    Returns the stage's exit status, or None when no worker could be reached (the caller then
    runs the stage itself).
    """
    path = socket_path()
    req = {"op": "run", "protocol": PROTOCOL, "stage": stage, "inputs": dict(inputs), "outputs": dict(outputs),
           "cfg": cfg, "log": str(log) if log else None, "cwd": os.getcwd(), "client": client or "the job client",
           "client_pid": os.getpid()}
    for attempt in range(2):  # a worker that was just exiting (idle, stopped) drops the job unread: start one
        conn = _connect(path) or _start(path, idle_seconds)
        if conn is None:
            return None
        heard = False
        with conn:
            try:
                _send(conn, req)
                for msg in _messages(conn):
                    heard = True
                    if "out" in msg:
                        sys.stderr.write(msg["out"])
                        sys.stderr.flush()
                    elif "rc" in msg:
                        if msg.get("error"):
                            sys.stderr.write(f"physgs worker: {msg['error']}\n")
                        return int(msg["rc"])
            except OSError as e:
                if heard:
                    sys.stderr.write(f"physgs worker: connection lost: {e}\n")
        if heard:
            break
    sys.stderr.write(f"physgs worker: the worker ended without finishing {stage} (its log: "
                     f"{path.with_suffix('.log')})\n")
    for v in outputs.values():  # nothing half-done stays behind
        with contextlib.suppress(OSError):
            Path(v).unlink()
    return 1


def shutdown(path: str | os.PathLike | None = None, wait_s: float = 15.0) -> bool:
    """Ask the worker of this code and environment (or at ``path``) to exit and wait up to
    ``wait_s`` for its process to be gone (its GPU memory freed); True if one was running."""
    conn = _connect(Path(path) if path else socket_path())
    if conn is None:
        return False
    bye = None
    with conn:
        with contextlib.suppress(OSError, ValueError):
            _send(conn, {"op": "shutdown"})
            bye = next(_messages(conn), None)
    pid = (bye or {}).get("bye")
    t_end = time.monotonic() + wait_s
    while pid and time.monotonic() < t_end:
        try:
            if os.waitpid(int(pid), os.WNOHANG)[0]:  # our own child (this process started it): reap it
                break
        except ChildProcessError:  # started by an earlier job's client: gone once kill(0) fails
            try:
                os.kill(int(pid), 0)
            except (ProcessLookupError, PermissionError):
                break
        time.sleep(0.02)
    return True


def serving_pid(path: str | os.PathLike | None = None) -> int | None:
    """The pid of the worker listening on ``path`` (default: this code's and environment's)
    as it wrote it at its start, without asking it (a ping waits until the worker has
    collected its last job's garbage); None when no socket is there."""
    path = Path(path) if path else socket_path()
    if not path.exists():
        return None
    try:
        pid = int(path.with_suffix(".pid").read_text().strip())
        os.kill(pid, 0)  # a worker killed outright leaves its files behind
    except PermissionError:  # alive, another user's (not ours to judge)
        return pid
    except (OSError, ValueError):
        return None
    return pid


def ping(path: str | os.PathLike | None = None) -> dict | None:
    """The worker's {pid, jobs, protocol}, or None when none is listening."""
    conn = _connect(Path(path) if path else socket_path())
    if conn is None:
        return None
    with conn:
        try:
            _send(conn, {"op": "ping"})
            return next(_messages(conn), None)
        except OSError:
            return None


def run_stage_job(stage: str, inputs: dict, outputs: dict, cfg: dict, log: str | None,
                  wcfg: dict | None = None) -> None:
    """Run one job of ``stage`` in the warm worker when the ``worker`` config section ``wcfg``
    asks for it (see the module docstring), else in this process.  Exits with the stage's
    status on failure.  The stage rules' jobs call it through ``python -m physgs_steps.job``."""
    wcfg = wcfg or {}
    if wants_worker(stage, wcfg):
        rc = run_job(stage, inputs, outputs, cfg, log, float(wcfg.get("idle_seconds", DEFAULT_IDLE_SECONDS)))
        if rc is not None:
            if rc != 0:
                sys.exit(rc)
            return
        sys.stderr.write("physgs worker: none could be started; running the stage in this process\n")
    from .runtime import run_stage, timed_stage_function

    fn, imp = timed_stage_function(stage, stage_function)
    run_stage(stage, fn, inputs, outputs, cfg, log, import_seconds=imp)


def dispatch(stage: str, smk) -> None:
    """``run_stage_job`` for a Snakemake ``script:`` adapter (``snakemake`` object)."""
    from .runtime import snakemake_io

    inputs, outputs, cfg, log = snakemake_io(smk)
    run_stage_job(stage, inputs, outputs, cfg, log, (getattr(smk, "config", None) or {}).get("worker"))


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m physgs_steps.worker", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve", help="serve jobs on a socket (started by the first job that needs it)")
    s.add_argument("path")
    s.add_argument("--idle-seconds", type=float, default=DEFAULT_IDLE_SECONDS)
    sub.add_parser("status", help="print the worker of this code and environment, if one runs")
    sub.add_parser("stop", help="ask the worker of this code and environment to exit")
    a = ap.parse_args(argv)
    if a.cmd == "serve":
        return serve(a.path, a.idle_seconds)
    if a.cmd == "status":
        info = ping()
        print(json.dumps({"socket": str(socket_path()), "worker": info}))
        return 0
    print("stopped" if shutdown() else "no worker running")
    return 0


if __name__ == "__main__":
    sys.exit(main())
