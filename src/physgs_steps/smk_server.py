"""Warm Snakemake: ``physgs snakemake ARGS`` runs ``snakemake ARGS`` without paying Snakemake's import.

Why.  A warm run of the default bear's pipeline spends more time in Snakemake's own start than
in most stages (README "GPU", "Snakemake's own time"): importing ``snakemake.cli`` (its plugin
registries import every installed executor plugin, the SLURM one brings pandas; its persistence
layer brings SQLAlchemy/SQLModel) took 1.7-2.6 s on the 2-core CPU machine and about 2 s on the
H100 machine, building its argument parser and collecting plugins 0.3 s, ``smart_open`` (imported
by the source cache on the first ``include:``) 0.34 s and the interpreter's shutdown 0.3 s.  None
of that depends on the workflow.

How.  A small server process per user, machine, Python, Snakemake installation and source tree
(``$PHYSGS_WORKER_DIR/s-<key>.sock``, next to the warm stage worker's socket) imports Snakemake
once and then forks one child per request: the child takes the client's working folder,
environment, umask and standard input/output/error (passed over the UNIX socket), drops any
``physgs_steps`` module so the workflow imports its own (``common.smk``), and runs Snakemake's
command line (``snakemake.cli.main``) exactly as the ``snakemake`` command would, in a fresh
copy of the imported-but-unused interpreter.  Everything Snakemake does is unchanged: DAG,
cached artifacts and rerun triggers, ``.snakemake`` metadata and locks, ``log:`` and
``benchmark:`` files, profiles, SLURM submission (the SLURM executor runs from the child as it
would from the command).  The client relays signals (Ctrl-C stops the run as it stops
``snakemake``), exits with Snakemake's exit status, and falls back to running ``python -m
snakemake`` itself where no server can be started (``PHYSGS_SMK_SERVER=0`` forces that).  The
server ends after ``--idle-seconds`` (600) without a request; ``python -m physgs_steps.smk_server
--stop`` ends it now.  Jobs of the run still go to the warm stage worker (worker.py).

The server is forked from before any thread starts; each child is a normal Snakemake process
(its own pid, threads, logging).  At its end the child runs the interpreter's exit handlers
(Snakemake's temporary folders, log files) and leaves without the interpreter's slow teardown.
"""
from __future__ import annotations

import contextlib
import importlib
import json
import os
import signal
import socket
import sys
import time
from pathlib import Path

from .worker import _connect  # a connection to a Unix socket, or None where nothing listens
from .worker import _messages as _lines  # newline-delimited JSON messages, as the worker reads them

DEFAULT_IDLE_SECONDS = 600.0
START_TIMEOUT_S = 60.0
PROTOCOL = 1
ENV_SWITCH = "PHYSGS_SMK_SERVER"


# ============================================================================ identity
def _snakemake_stamp() -> str:
    """Where Snakemake is installed and when it changed (an upgrade starts a new server)."""
    import importlib.util

    spec = importlib.util.find_spec("snakemake")
    if spec is None or not spec.origin:
        return "none"
    d = Path(spec.origin).parent
    try:
        return f"{d}:{os.stat(d / '__init__.py').st_mtime_ns}:{os.stat(d / 'cli.py').st_mtime_ns}"
    except OSError:
        return str(d)


def server_key() -> str:
    import hashlib

    from .worker import worker_key

    return hashlib.sha1(f"smk{PROTOCOL}\n{worker_key()}\n{_snakemake_stamp()}".encode()).hexdigest()[:16]


def socket_path(key: str | None = None) -> Path:
    from .worker import worker_dir

    return worker_dir() / f"s-{key or server_key()}.sock"


def _send(conn: socket.socket, msg: dict, fds: list[int] | None = None) -> None:
    data = (json.dumps(msg) + "\n").encode()
    if fds:
        socket.send_fds(conn, [data], fds)
    else:
        conn.sendall(data)


# ============================================================================ server
def _warm() -> None:
    """Import what every Snakemake run imports (no thread may be started here: we fork)."""
    import snakemake.cli as cli

    cli.get_argument_parser()  # collects the executor, storage, logger ... plugins once
    with contextlib.suppress(ImportError):
        import smart_open  # noqa: F401  (the source cache's, on the first include:)
    with contextlib.suppress(ImportError):  # what common.smk's config validation uses
        import jsonschema  # noqa: F401
        import yaml  # noqa: F401
    with contextlib.suppress(ImportError):  # validation.smk plans its runs with numpy (0.1-0.2 s to import)
        import numpy  # noqa: F401
    for mod in WORKFLOW_MODULES:  # kept in a child only for a workflow of this very source tree (_keeps_package)
        with contextlib.suppress(Exception):
            importlib.import_module(mod)


# what common.smk and validation.smk import while Snakemake parses them (no state: their caches
# fill on first use, in the child)
WORKFLOW_MODULES = ("physgs_steps.config", "physgs_steps.plan", "physgs_steps.errors", "physgs_steps.worker",
                    "physgs_steps.resources", "physgs_steps.job", "physgs_steps.benchmark.spec",
                    "physgs_steps.validation")


def _keeps_package(argv: list[str], cwd: str) -> bool:
    """Whether the run's workflow imports the ``physgs_steps`` this server imported: the Snakefile
    is ``<cwd>/Snakefile`` (no -s/--snakefile, -d/--directory) and common.smk puts ``<cwd>/src``
    first on sys.path, which must hold this very package (the server's key covers its sources)."""
    if any(a in ("-s", "--snakefile", "-d", "--directory") or a.startswith(("--snakefile=", "--directory="))
           for a in argv):
        return False
    here = Path(__file__).resolve().parent
    try:
        return (Path(cwd) / "Snakefile").is_file() and (Path(cwd) / "src" / "physgs_steps").resolve() == here
    except OSError:
        return False


def _recv_request(conn: socket.socket) -> tuple[dict, list[int]]:
    buf, fds = b"", []
    while b"\n" not in buf:
        msg, got, _flags, _addr = socket.recv_fds(conn, 1 << 20, 8)
        fds += got
        if not msg:
            break
        buf += msg
    return json.loads(buf.split(b"\n", 1)[0]), fds


def _child(conn: socket.socket, req: dict, fds: list[int]) -> None:
    """In the forked child: become the client's Snakemake process, run it, report, leave."""
    import threading

    rc = 1
    finished = threading.Event()
    try:
        os.setpgid(0, 0)  # its own process group, which the client signals as a terminal would
        for i, fd in enumerate(fds[:3]):
            os.dup2(fd, i)
        for fd in fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        sys.stdin = open(0, "r", closefd=False) if sys.stdin is None else sys.stdin
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        os.umask(int(req.get("umask", 0o022)))
        import tempfile

        tempfile.tempdir = None  # the client's TMPDIR
        if not _keeps_package(req["argv"], req["cwd"]):
            for name in [m for m in sys.modules if m == "physgs_steps" or m.startswith("physgs_steps.")]:
                del sys.modules[name]  # the workflow imports its own (common.smk puts its src/ first)
        for p in req.get("pythonpath", []):
            if p not in sys.path:
                sys.path.insert(0, p)
        sys.argv = ["snakemake", *req["argv"]]
        _send(conn, {"pid": os.getpid()})

        import threading

        def watch():  # the client went away (killed): stop as on Ctrl-C
            with contextlib.suppress(OSError):
                while conn.recv(1):
                    pass
            if not finished.is_set():
                with contextlib.suppress(OSError):
                    os.killpg(0, signal.SIGINT)

        threading.Thread(target=watch, daemon=True).start()
        if os.environ.get("PHYSGS_SMK_PHASES"):  # time Snakemake's phases (physgs bench snakemake)
            from .smk_phases import start

            start(os.environ["PHYSGS_SMK_PHASES"])
        from snakemake.cli import main as smk_main

        try:
            smk_main(req["argv"])
            rc = 0
        except SystemExit as e:
            rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except KeyboardInterrupt:
            rc = 130
    except BaseException:
        import traceback

        traceback.print_exc()
    finally:
        finished.set()
        with contextlib.suppress(BaseException):
            import atexit

            atexit._run_exitfuncs()  # Snakemake's temporary folders, logging's flush
        with contextlib.suppress(BaseException):
            sys.stdout.flush()
            sys.stderr.flush()
        with contextlib.suppress(BaseException):
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # too late to stop: report and leave
            _send(conn, {"rc": rc})
        os._exit(rc if 0 <= rc < 256 else 1)


def serve(path: str | os.PathLike, idle_seconds: float = DEFAULT_IDLE_SECONDS) -> int:
    path = Path(path)
    _warm()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(path))
    except OSError:
        return 0  # another server got there first
    os.chmod(path, 0o600)
    ino = os.stat(path).st_ino
    sock.listen(16)
    sock.settimeout(1.0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    print(f"[smk-server {os.getpid()}] serving {path} (idle limit {idle_seconds:g} s)", file=sys.stderr, flush=True)
    last = time.monotonic()
    runs = 0
    started: dict[int, tuple[float, list[str]]] = {}
    try:
        while True:
            _reap(started)
            try:
                conn, _ = sock.accept()
            except socket.timeout:
                if time.monotonic() - last > idle_seconds:
                    print(f"[smk-server {os.getpid()}] idle for {idle_seconds:g} s after {runs} runs: exiting",
                          file=sys.stderr, flush=True)
                    return 0
                continue
            last = time.monotonic()
            conn.settimeout(None)
            try:
                req, fds = _recv_request(conn)
            except (OSError, ValueError):
                conn.close()
                continue
            op = req.get("op")
            if op in ("stop", "shutdown"):
                with contextlib.suppress(OSError):
                    _send(conn, {"bye": os.getpid()})
                conn.close()
                return 0
            if op == "ping":
                with contextlib.suppress(OSError):
                    _send(conn, {"pid": os.getpid(), "runs": runs, "protocol": PROTOCOL})
                conn.close()
                continue
            if op != "run" or req.get("protocol") != PROTOCOL or len(fds) < 3:
                with contextlib.suppress(OSError):
                    _send(conn, {"rc": 2, "error": f"bad request {op!r}"})
                conn.close()
                for fd in fds:
                    os.close(fd)
                continue
            runs += 1
            pid = os.fork()
            if pid == 0:
                sock.close()
                signal.signal(signal.SIGINT, signal.default_int_handler)
                _child(conn, req, fds)  # never returns
            started[pid] = (time.monotonic(), req["argv"])
            conn.close()
            for fd in fds:
                os.close(fd)
    finally:
        with contextlib.suppress(OSError):
            if os.stat(path).st_ino == ino:
                path.unlink()
        sock.close()


def _reap(started: dict) -> None:
    """Collect ended runs; log each one's wall and CPU seconds (Snakemake's process and the job
    processes it waited for: bash, job clients; not the warm stage worker)."""
    while True:
        try:
            pid, status, ru = os.wait4(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if not pid:
            return
        t0, argv = started.pop(pid, (None, []))
        wall = f"{time.monotonic() - t0:.2f} s wall (seen at most 1 s late), " if t0 is not None else ""
        print(f"[smk-server {os.getpid()}] run {pid} ended with status {os.waitstatus_to_exitcode(status)}: {wall}"
              f"{ru.ru_utime + ru.ru_stime:.2f} s CPU ({ru.ru_utime:.2f} user, {ru.ru_stime:.2f} system), "
              f"peak RSS {ru.ru_maxrss / 1024:.0f} MiB: snakemake {' '.join(argv)}", file=sys.stderr, flush=True)


# ============================================================================ client
def _start(path: Path, idle_seconds: float) -> socket.socket | None:
    import fcntl
    import subprocess

    with open(path.with_suffix(".lock"), "w") as lf:
        fcntl.flock(lf, fcntl.LOCK_EX)
        conn = _connect(path)
        if conn is not None:
            return conn
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        env = os.environ.copy()
        src = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join([src] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        log = open(path.with_suffix(".log"), "w")
        proc = subprocess.Popen([sys.executable, "-m", "physgs_steps.smk_server", "--serve", str(path),
                                 "--idle-seconds", str(idle_seconds)], stdin=subprocess.DEVNULL, stdout=log,
                                stderr=log, start_new_session=True, cwd="/", env=env)
        log.close()
        t_end = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < t_end:
            conn = _connect(path)
            if conn is not None:
                return conn
            if proc.poll() is not None:
                return _connect(path)
            time.sleep(0.01)
    return None


def wanted() -> bool:
    v = os.environ.get(ENV_SWITCH, "").strip().lower()
    return v not in ("0", "false", "no", "off")


def run(argv: list[str], idle_seconds: float = DEFAULT_IDLE_SECONDS) -> int:
    """Run ``snakemake argv`` in a child of the warm server (started if needed); its exit status."""
    if wanted():
        path = socket_path()
        conn = _connect(path) or _start(path, idle_seconds)
        if conn is not None:
            rc = _relay(conn, argv)
            if rc is not None:
                return rc
        print("physgs: no warm Snakemake server could be started; running snakemake in this process",
              file=sys.stderr)
    from snakemake.cli import main as smk_main

    try:
        smk_main(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    return 0


def _relay(conn: socket.socket, argv: list[str]) -> int | None:
    """Send the run to the server; forward signals to its child; its exit status (None: no child)."""
    pp = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    req = {"op": "run", "protocol": PROTOCOL, "argv": list(argv), "cwd": os.getcwd(), "env": dict(os.environ),
           "umask": _umask(), "pythonpath": pp}
    child = None
    old = {}

    def forward(signum, _frame):  # to Snakemake and its jobs, as a terminal's Ctrl-C reaches them all
        if child:
            with contextlib.suppress(OSError):
                os.killpg(child, signum)

    with conn:
        try:
            _send(conn, req, [0, 1, 2])
        except OSError:
            return None
        for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
            with contextlib.suppress(ValueError, OSError):
                old[s] = signal.signal(s, forward)
        try:
            for msg in _lines(conn):
                if "pid" in msg and child is None:
                    child = int(msg["pid"])
                elif "rc" in msg:
                    if msg.get("error"):
                        print(f"physgs: warm Snakemake server: {msg['error']}", file=sys.stderr)
                    return int(msg["rc"])
        except OSError:
            pass
        finally:
            for s, h in old.items():
                with contextlib.suppress(ValueError, OSError):
                    signal.signal(s, h)
    if child is None:
        return None
    print("physgs: the Snakemake process ended without an exit status", file=sys.stderr)
    return 1


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def stop(path: str | os.PathLike | None = None) -> bool:
    conn = _connect(Path(path) if path else socket_path())
    if conn is None:
        return False
    with conn, contextlib.suppress(OSError, ValueError):
        _send(conn, {"op": "stop"})
        next(_lines(conn), None)
    return True


def ping(path: str | os.PathLike | None = None) -> dict | None:
    conn = _connect(Path(path) if path else socket_path())
    if conn is None:
        return None
    with conn, contextlib.suppress(OSError, ValueError):
        _send(conn, {"op": "ping"})
        return next(_lines(conn), None)
    return None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--serve"]:
        idle = DEFAULT_IDLE_SECONDS
        if len(argv) >= 4 and argv[2] == "--idle-seconds":
            idle = float(argv[3])
        return serve(argv[1], idle)
    if argv == ["--stop"]:
        print("stopped" if stop() else "no server running")
        return 0
    if argv == ["--status"]:
        print(json.dumps({"socket": str(socket_path()), "server": ping()}))
        return 0
    idle = float(os.environ.get("PHYSGS_SMK_SERVER_IDLE", DEFAULT_IDLE_SECONDS))
    return run(argv, idle)


if __name__ == "__main__":
    sys.exit(main())
