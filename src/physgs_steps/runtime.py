"""Stage plumbing shared by every stage: logging, timing, peak memory, atomic outputs,
and the entry point that Snakemake ``script:`` adapters call.

A stage is a function ``run(inputs, outputs, cfg, log) -> dict`` in a library module.
``inputs``/``outputs`` map names to paths, ``cfg`` is the stage's validated config
subset, ``log`` a :class:`logging.Logger`.  It returns a summary dict (seconds and peak
memory are added here) that is logged and, where the stage writes a JSON report,
included there.
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import resource
import socket
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Iterator

from .errors import InputError, PhysGSError

LOG_FORMAT = "%(asctime)s %(levelname)s [%(name)s] %(message)s"


def project_root() -> Path:
    """The repository root (the folder holding ``Snakefile``), else the current folder."""
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "Snakefile").exists():
            return parent
    return Path.cwd()


def cache_dir(name: str) -> Path:
    """A project-local cache folder (``.cache/<name>``), overridable by PHYSGS_CACHE_DIR."""
    base = Path(os.environ.get("PHYSGS_CACHE_DIR", project_root() / ".cache"))
    d = base / name
    d.mkdir(parents=True, exist_ok=True)
    return d


def get_logger(name: str, log_path: str | os.PathLike | None = None) -> logging.Logger:
    log = logging.getLogger(f"physgs.{name}")
    log.setLevel(logging.INFO)
    log.propagate = False
    for h in list(log.handlers):
        log.removeHandler(h)
    fmt = logging.Formatter(LOG_FORMAT)
    sh = logging.StreamHandler(sys.stderr)
    sh.setFormatter(fmt)
    log.addHandler(sh)
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(log_path, mode="w")
        fh.setFormatter(fmt)
        log.addHandler(fh)
    return log


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cuda_peak_mb() -> float | None:
    """Peak CUDA memory allocated by torch in this process, or None without CUDA."""
    torch = sys.modules.get("torch")  # never import torch just to ask
    try:
        if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
            return torch.cuda.max_memory_allocated() / 2**20
    except Exception:  # pragma: no cover - torch broken
        return None
    return None


def _reset_cuda_peak() -> None:
    torch = sys.modules.get("torch")
    try:
        if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
            torch.cuda.reset_peak_memory_stats()
    except Exception:  # pragma: no cover
        pass


class Timer:
    """Named wall-clock sections: ``with t.section("fill"): ...``; ``t.seconds`` dict."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def section(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0


def _host_tag() -> str:
    """This machine's short host name, reduced to [A-Za-z0-9_] (part of temporary file names)."""
    return re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname().split(".")[0]) or "host"


def file_mode() -> int:
    """The mode a new file gets under the process umask (0o644 under umask 022): atomic
    writes create their temporary file with mkstemp, which is always 0o600, and set this."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o022)  # no /proc: read it by setting it (and put it back at once)
    os.umask(old)
    return 0o666 & ~old


_PART = r"\.(?:(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)\.)?[A-Za-z0-9_]+\.part"


def part_pattern(path: str | os.PathLike) -> re.Pattern:
    """The names of temporary files of :func:`atomic_path` for ``path``:
    ``.<name>.<host>-<pid>.<random>.part<suffix>`` (and the older ``.<name>.<random>.part<suffix>``)."""
    path = Path(path)
    return re.compile(rf"^\.{re.escape(path.name)}{_PART}{re.escape(path.suffix)}$")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale_parts(path: str | os.PathLike, log: logging.Logger | None = None) -> list[Path]:
    """Remove temporary files that an earlier, killed write of ``path`` left beside it.

    A stage owns its outputs while it runs (Snakemake's lock), so a part file of the same
    output is left over from a killed run, unless its name says that a process still alive
    on this machine writes it (``physgs stage`` run by hand beside the workflow): those stay.
    Returns the removed paths.
    """
    path = Path(path)
    if not path.parent.is_dir():
        return []
    pat, host, me = part_pattern(path), _host_tag(), os.getpid()
    removed = []
    for p in path.parent.iterdir():
        m = pat.match(p.name)
        if not m or not p.is_file():
            continue
        if m.group("pid") and m.group("host") == host and int(m.group("pid")) != me and _alive(int(m.group("pid"))):
            continue
        try:
            p.unlink()
        except FileNotFoundError:
            continue
        removed.append(p)
        if log is not None:
            log.info("removed %s, left by an earlier run of this stage that did not finish", p)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only on success.

    A crash or an exception leaves no half-written artifact behind (a kill can leave the
    temporary file, which :func:`clean_stale_parts` removes when the stage runs again). The
    artifact gets the permissions of a new file under the umask (:func:`file_mode`), so that
    collaborators on a shared file system can read results.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{_host_tag()}-{os.getpid()}.", suffix=".part" + path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    mode = file_mode()
    os.chmod(tmp_path, mode)
    try:
        yield tmp_path
        os.chmod(tmp_path, mode)  # in case the writer replaced the file
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def strict_json(obj: Any) -> tuple[Any, dict[str, str]]:
    """``obj`` with every non-finite float (inf, -inf, NaN) replaced by None, and
    {JSON pointer: "inf" | "-inf" | "nan"} of the replacements (numpy values converted)."""
    found: dict[str, str] = {}

    def walk(o: Any, ptr: str) -> Any:
        if isinstance(o, dict):
            return {k: walk(v, f"{ptr}/{str(k).replace('~', '~0').replace('/', '~1')}") for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [walk(v, f"{ptr}/{i}") for i, v in enumerate(o)]
        if type(o).__module__ == "numpy":
            o = _json_default(o)
            return walk(o, ptr) if isinstance(o, (list, float)) else o
        if isinstance(o, float) and not math.isfinite(o):
            found[ptr or "/"] = "nan" if math.isnan(o) else ("inf" if o > 0 else "-inf")
            return None
        return o

    return walk(obj, ""), found


def json_text(obj: Any, **kwargs) -> str:
    """Strict JSON text (RFC 8259: no Infinity/NaN) of ``obj``; non-finite numbers become null,
    and a dict gets the key ``nonfinite`` listing them ({JSON pointer: "inf" | "-inf" | "nan"})."""
    clean, found = strict_json(obj)
    if found and isinstance(clean, dict):
        clean["nonfinite"] = {"description": "numbers that were not finite, written as null", "values": found}
    kwargs.setdefault("default", _json_default)
    return json.dumps(clean, allow_nan=False, **kwargs)


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write strict JSON atomically (sorted keys, numpy scalars converted; :func:`json_text`)."""
    text = json_text(obj, indent=2, sort_keys=True)
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            f.write(text + "\n")


def read_json(path: str | os.PathLike) -> Any:
    with open(path) as f:
        return json.load(f)


def read_json_input(path: str | os.PathLike, what: str = "file") -> Any:
    """Read a JSON input of a stage; a missing, unreadable or malformed file is an
    :class:`InputError` naming it (``what`` says which file, e.g. "params file")."""
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        raise InputError(path, f"{what} not found (does not exist)") from None
    except (OSError, ValueError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise InputError(path, f"not valid JSON: {e}") from None


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


StageFn = Callable[[dict, dict, dict, logging.Logger], dict]


def _release_cuda_cache() -> None:
    """Give torch's cached CUDA blocks back after a stage (BGDO's pseudo steps reserve GBs at
    300k particles; the next stage in the same process, e.g. render, must not stack on them)."""
    torch = sys.modules.get("torch")
    if torch is None:
        return
    with contextlib.suppress(Exception):
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            torch.cuda.empty_cache()


def cuda_start_seconds(torch) -> float:
    """Seconds of this process's first CUDA call through ``torch`` (driver, context, caching
    allocator, one kernel), 0.0 when torch had already started CUDA here.  Stages call it before
    their own work so that their logs show the one-off cost apart (summary ``timings``)."""
    if torch.cuda.is_initialized():
        return 0.0
    t0 = time.perf_counter()
    torch.zeros(1, device="cuda").add_(1)
    torch.cuda.synchronize()
    return round(time.perf_counter() - t0, 3)


def timed_stage_function(name: str, getter: Callable[[str], StageFn]) -> tuple[StageFn, float]:
    """``getter(name)`` and the seconds it took (importing the stage's modules: torch, Taichi,
    gsplat the first time in a process, nothing afterwards)."""
    t0 = time.perf_counter()
    fn = getter(name)
    return fn, round(time.perf_counter() - t0, 3)


def run_stage(name: str, fn: StageFn, inputs: dict, outputs: dict, cfg: dict, log_path=None,
              import_seconds: float | None = None) -> dict:
    """Run one stage with logging, timing and peak-memory accounting.

    ``import_seconds`` (the time it took to import the stage's function, when the caller
    measured it) goes into the summary line; ``seconds`` is the stage itself.

    On a :class:`PhysGSError` the message is logged, every declared output that exists
    is removed (no half-written artifact) and the process exits with status 1.
    """
    log = get_logger(name, log_path)
    log.info("stage %s: inputs %s", name, {k: str(v) for k, v in inputs.items()})
    for v in outputs.values():
        for p in v if isinstance(v, (list, tuple)) else [v]:
            clean_stale_parts(p, log)
    _reset_cuda_peak()
    t0 = time.perf_counter()
    try:
        summary = _profiled(name, fn, log)(dict(inputs), dict(outputs), cfg, log) or {}
    except PhysGSError as e:
        log.error("stage %s failed: %s", name, e)
        _remove_outputs(outputs, log)
        raise SystemExit(1) from None
    except Exception:
        log.error("stage %s crashed:\n%s", name, traceback.format_exc())
        _remove_outputs(outputs, log)
        exc = SystemExit(1)
        exc.physgs_crash = True  # not a PhysGSError: the warm worker (worker.py) does not serve on
        raise exc from None
    summary.setdefault("seconds", round(time.perf_counter() - t0, 3))
    _release_cuda_cache()
    if import_seconds is not None:
        summary.setdefault("import_seconds", import_seconds)
    summary.setdefault("peak_rss_mb", round(peak_rss_mb(), 1))
    cp = cuda_peak_mb()
    if cp is not None:
        summary.setdefault("cuda_peak_mb", round(cp, 1))
    log.info("stage %s done in %.2f s (peak RSS %.0f MiB); outputs %s", name, summary["seconds"],
             summary["peak_rss_mb"], {k: str(v) for k, v in outputs.items()})
    log.info("%s%s", SUMMARY_PREFIX, json.dumps(summary, sort_keys=True, default=_summary_default))
    return summary


PROFILE_ENV = "PHYSGS_PROFILE_DIR"


def _profiled(name: str, fn: StageFn, log: logging.Logger) -> StageFn:
    """``fn`` itself, or, where the environment variable PHYSGS_PROFILE_DIR names a folder,
    ``fn`` run under cProfile: the statistics go to ``<dir>/<stage>-<n>.prof`` (``n`` counts
    the runs of that stage in the folder) and the 30 costliest functions by own time to the
    stage's log.  For finding where a stage's fixed costs go (README "GPU")."""
    folder = os.environ.get(PROFILE_ENV)
    if not folder:
        return fn

    def run(*args):
        import cProfile
        import io
        import pstats

        Path(folder).mkdir(parents=True, exist_ok=True)
        n = len(list(Path(folder).glob(f"{name}-*.prof")))
        out = Path(folder) / f"{name}-{n}.prof"
        prof = cProfile.Profile()
        try:
            return prof.runcall(fn, *args)
        finally:
            prof.dump_stats(str(out))
            text = io.StringIO()
            pstats.Stats(prof, stream=text).sort_stats("tottime").print_stats(30)
            log.info("profile of stage %s -> %s\n%s", name, out, text.getvalue())

    return run


# The last log line of a stage: its summary as one JSON object (the benchmark reads time spent
# inside the stage and CUDA peaks from it: physgs_steps.benchmark.readers.stage_summary).
SUMMARY_PREFIX = "stage summary: "


def _summary_default(o: Any) -> Any:
    try:
        return _json_default(o)
    except TypeError:
        return str(o)


def _remove_outputs(outputs: dict, log: logging.Logger) -> None:
    for v in outputs.values():
        for p in v if isinstance(v, (list, tuple)) else [v]:
            p = Path(p)
            if p.is_file():
                p.unlink()
                log.info("removed incomplete output %s", p)


def snakemake_io(smk) -> tuple[dict, dict, dict, str | None]:
    """Turn a Snakemake ``snakemake`` script object into (inputs, outputs, cfg, log)."""
    inputs = {k: v for k, v in smk.input.items()}
    outputs = {k: v for k, v in smk.output.items()}
    cfg = dict(getattr(smk.params, "cfg", None) or {})
    log = smk.log[0] if len(smk.log) else None
    return inputs, outputs, cfg, log
