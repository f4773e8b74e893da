"""Pipeline benchmark: wall time, start-up overhead and peak GPU memory of every stage of a
target, run the ways a user can run it (issue 18's table; the benchmark's ``full``-scale Stage
table uses the same entry point, :func:`measure`).

    physgs bench pipeline bear                          # default bear, every structure, cold + warm
    physgs bench pipeline bear --n-gaussians 300000 --set render.width=1920 --set render.height=1080
    physgs bench startup bear                           # per-stage fixed overhead (process vs warm)
    physgs bench snakemake bear                         # Snakemake's own time per phase, warm (6 frames)

Structures (``--structures``), each run twice in a fresh scratch folder: first with an empty
Taichi kernel cache (``cold``; gsplat's CUDA code stays built, in its machine-wide cache), then
again (``warm``):

* ``processes``: every job in its own ``physgs stage`` process, as Snakemake ran the GPU chain
  before the warm worker (and as ``benchmarks/gpu_pipeline.sh`` measured the issue's table);
* ``inprocess``: every job in one process, in order (``physgs stages``): the floor;
* ``snakemake``: ``snakemake --cores 1 --forceall <video>`` with ``worker.enabled: false``;
* ``worker``: the same Snakemake run with the warm worker on (the default on a GPU machine);
* ``server`` (not in the default list): as ``worker``, through ``physgs snakemake`` (the warm
  Snakemake server, smk_server.py): its cold run includes the server's start (one Snakemake import).

``physgs bench snakemake`` times Snakemake's own share of a warm run, phase by phase
(:func:`snakemake_overhead`).

Each row gives the whole pipeline's seconds (``metrics`` excluded unless ``--with-metrics``,
as in the issue), the seconds of each job, the simulation's substep seconds (the three MPM
runs' ``simulate_seconds``) and the peak GPU memory in use on the device during the run above
what was in use before it (NVML through ``pynvml`` when importable, else ``nvidia-smi``).

``startup`` measures each stage's fixed overhead: a fresh process runs the job twice; the
overhead is the process's wall time minus the second (warm) run's time, and the time to import
the stage's module is given apart.
"""
from __future__ import annotations

import contextlib
import copy
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from .runtime import project_root

STRUCTURES = ("processes", "inprocess", "snakemake", "worker")
SIM_STAGES = ("forward_sim", "final_sim")


# ============================================================================ GPU memory
class GpuMemory:
    """Samples the memory in use on one GPU (MiB) in a thread until stopped.

    ``peak_above_baseline`` is the largest sample minus the first one; ``peak_between(t0, t1)``
    the largest sample in a wall-clock window (time.time()).  Without NVML and nvidia-smi
    every figure is None.
    """

    def __init__(self, index: int = 0, interval_s: float = 0.01, baseline: float | None = None):
        self.index, self.interval, self._baseline = index, interval_s, baseline
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._read = self._reader()
        self._thread = None

    def _reader(self):
        try:
            import pynvml

            pynvml.nvmlInit()
            h = pynvml.nvmlDeviceGetHandleByIndex(self.index)
            return lambda: pynvml.nvmlDeviceGetMemoryInfo(h).used / 2**20
        except Exception:
            pass
        if shutil.which("nvidia-smi"):
            self.interval = max(self.interval, 0.05)

            def smi():
                r = subprocess.run(["nvidia-smi", f"--id={self.index}", "--query-gpu=memory.used",
                                    "--format=csv,noheader,nounits"], capture_output=True, text=True)
                return float(r.stdout.strip().splitlines()[0])

            try:
                smi()
                return smi
            except Exception:
                return None
        return None

    @property
    def available(self) -> bool:
        return self._read is not None

    def __enter__(self):
        if self._read is not None:
            self.samples.append((time.time(), self._read()))
            self._thread = threading.Thread(target=self._loop, daemon=True)
            self._thread.start()
        return self

    def _loop(self):
        while not self._stop.wait(self.interval):
            try:
                self.samples.append((time.time(), self._read()))
            except Exception:
                return

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self.samples.append((time.time(), self._read()))

    @property
    def baseline(self) -> float | None:
        """The level measured against: given (the GPU before the benchmark's first run, so that
        a warm worker left by the previous run counts), else the first sample."""
        if self._baseline is not None:
            return self._baseline
        return self.samples[0][1] if self.samples else None

    @property
    def peak_above_baseline(self) -> float | None:
        if not self.samples:
            return None
        return round(max(v for _, v in self.samples) - self.baseline, 1)

    def peak_between(self, t0: float, t1: float) -> float | None:
        vals = [v for t, v in self.samples if t0 <= t <= t1]
        if not vals or self.baseline is None:
            return None
        return round(max(vals) - self.baseline, 1)


# ============================================================================ scratch folder
def _set(cfg: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    d = cfg
    for k in keys[:-1]:
        d = d.setdefault(k, {})
    d[keys[-1]] = value


def parse_sets(items: list[str] | None) -> dict:
    """``["render.width=1920", "sim.n_grid=64"]`` -> nested overrides (values read as YAML)."""
    import yaml

    out: dict = {}
    for item in items or []:
        key, _, val = item.partition("=")
        if not key or not _:
            raise ValueError(f"--set wants key=value, got {item!r}")
        _set(out, key.strip(), yaml.safe_load(val))
    return out


def make_workdir(workdir: str | os.PathLike, scene: str = "bear", n_gaussians: int | None = None,
                 overrides: dict | None = None, config: str | os.PathLike | None = None) -> Path:
    """A scratch folder to run one scene in: ``config.yaml`` (the project config with
    ``overrides``, scenes_dir pointing at ``scenes/``), the scene file (with ``builtin.n_gaussians``
    when given) and links to the workflow files for Snakemake."""
    from . import config as C

    root = project_root()
    wd = Path(workdir).resolve()
    (wd / "scenes").mkdir(parents=True, exist_ok=True)
    cfg = C.read_yaml(Path(config) if config else root / "config" / "config.yaml")
    src_scene = C.scene_path(C.validate_config(copy.deepcopy(cfg)), scene)
    sc = C.read_yaml(src_scene)
    if n_gaussians:
        sc.setdefault("builtin", {})["n_gaussians"] = int(n_gaussians)
    with open(wd / "scenes" / f"{scene}.yaml", "w") as f:
        import yaml

        yaml.safe_dump(sc, f, sort_keys=False)
    cfg = C.deep_merge(cfg, overrides or {})
    cfg["scenes_dir"] = str(wd / "scenes")
    cfg.setdefault("ablations", {})
    with open(wd / "config.yaml", "w") as f:
        import yaml

        yaml.safe_dump(cfg, f, sort_keys=False)
    for name in ("Snakefile", "workflow", "src", "profiles"):
        link = wd / name
        if not link.exists() and (root / name).exists():
            link.symlink_to(root / name)
    (wd / "config").mkdir(exist_ok=True)  # the Snakefile's configfile: the real one, overlaid by config.yaml
    if not (wd / "config" / "config.yaml").exists():
        (wd / "config" / "config.yaml").symlink_to(root / "config" / "config.yaml")
    return wd


def _env(cache: Path, worker: bool) -> dict:
    env = os.environ.copy()
    env["PHYSGS_CACHE_DIR"] = str(cache)
    env["PHYSGS_WORKER"] = "1" if worker else "0"
    env["PHYSGS_WORKER_DIR"] = str(cache / "w")
    env["PYTHONUNBUFFERED"] = "1"
    src = str(project_root() / "src") if (project_root() / "src" / "physgs_steps").is_dir() else \
        str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([src] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return env


def _keep(jobs, with_metrics: bool, until: str | None = None) -> list[tuple[str, str | None]]:
    """The jobs a benchmark run times: ``metrics`` only with ``with_metrics``; with ``until``
    ("final_sim") none after the final simulation (where nothing can render, e.g. no gsplat)."""
    jobs = [j for j in jobs if j[0] != "stage_report" and (with_metrics or j[0] != "metrics")]
    if until == "final_sim":
        jobs = [j for j in jobs if j[0] not in ("render", "metrics")]
    elif until not in (None, "render", "metrics"):
        raise ValueError(f"until must be final_sim, render or metrics, not {until!r}")
    return jobs


def _jobs(wd: Path, target: str, with_metrics: bool, until: str | None = None) -> list[tuple[str, str | None]]:
    from . import config as C
    from . import plan as P

    cfg = C.load_config(wd / "config.yaml")
    scene, abl = P.parse_target(target)
    jobs = P.make_plan(cfg, scene, abl).jobs()
    return _keep(jobs, with_metrics, until)


def _children_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(cmd: list[str], wd: Path, env: dict, log: Path, cpu: list | None = None) -> float:
    """Run ``cmd`` in ``wd``; its wall seconds (its CPU seconds are appended to ``cpu``)."""
    c0 = _children_cpu()
    t0 = time.perf_counter()
    with open(log, "a") as f:
        f.write(f"$ {' '.join(cmd)}\n")
        f.flush()
        r = subprocess.run(cmd, cwd=wd, env=env, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    dt = time.perf_counter() - t0
    if cpu is not None:
        cpu.append(_children_cpu() - c0)
    if r.returncode != 0:
        tail = log.read_text()[-4000:]
        raise RuntimeError(f"{' '.join(cmd[:6])} ... failed (exit {r.returncode}); log {log}:\n{tail}")
    return dt


# ============================================================================ structures
def run_structure(structure: str, wd: Path, target: str, cache: Path, log: Path, with_metrics: bool = False,
                  gpu_index: int = 0, gpu_baseline: float | None = None, until: str | None = None) -> dict:
    """One timed run of the whole pipeline of ``target`` in ``wd`` (outputs are recomputed).
    GPU memory is counted above ``gpu_baseline`` (MiB in use) when given, else above the level
    at the start of this run."""
    jobs = _jobs(wd, target, with_metrics, until)
    env = _env(cache, worker=structure in ("worker", "server"))
    rows: list[dict] = []
    with GpuMemory(gpu_index, baseline=gpu_baseline) as mem:
        t0 = time.perf_counter()
        if structure == "processes":
            for name, step in jobs:
                summ = wd / f".summary-{name}-{step or ''}.json"
                cmd = [sys.executable, "-m", "physgs_steps.cli", "--config", "config.yaml", "stage", name, target,
                       "--summary", str(summ)] + (["--step", step] if step else [])
                a = time.time()
                wall = _run(cmd, wd, env, log)
                res = json.loads(summ.read_text())[0]
                rows.append({"stage": name, "step": step, "seconds": round(wall, 3),
                             "stage_seconds": res.get("seconds"), "simulate_seconds": res.get("simulate_seconds"),
                             "substeps": res.get("substeps_total"), "held_frames": res.get("held_frames"),
                             "peak_gpu_mib": mem.peak_between(a, time.time())})
        elif structure == "inprocess":
            out = wd / ".chain.json"
            cmd = [sys.executable, "-m", "physgs_steps.pipeline_bench", "chain", target, "--config", "config.yaml",
                   "--out", str(out)] + (["--with-metrics"] if with_metrics else []) + \
                (["--until", until] if until else [])
            _run(cmd, wd, env, log)
            for r in json.loads(out.read_text())["jobs"]:
                rows.append({"stage": r["stage"], "step": r["step"], "seconds": r["seconds"],
                             "stage_seconds": r["seconds"], "simulate_seconds": r.get("simulate_seconds"),
                             "substeps": r.get("substeps"), "held_frames": r.get("held_frames"),
                             "peak_gpu_mib": mem.peak_between(r["t0"], r["t1"]),
                             "import_seconds": r.get("import_seconds"), "breakdown": r.get("breakdown")})
        else:
            from . import config as C
            from . import plan as P

            scene, abl = P.parse_target(target)
            plan = P.make_plan(C.load_config(wd / "config.yaml"), scene, abl)
            goal = plan.path("final") if until == "final_sim" else plan.path("metrics") if with_metrics \
                else plan.path("video")
            smk = ["-m", "physgs_steps.cli", "snakemake"] if structure == "server" else ["-m", "snakemake"]
            cmd = [sys.executable, *smk, "--cores", "1", "--forceall", "--configfile", "config.yaml",
                   "--", goal]  # the worker is switched by PHYSGS_WORKER (_env)
            _run(cmd, wd, env, log)
            if structure in ("worker", "server"):
                idle = _idle_worker(cache, mem)
            for name, step in jobs:
                b = Path(wd / plan.benchmark_path(name, step))
                secs = None
                if b.exists():
                    lines = b.read_text().splitlines()
                    secs = float(lines[-1].split("\t")[0])
                from .benchmark.readers import stage_summary

                summ = stage_summary(wd / plan.log_path(name, step)) or {}
                st = _sim_stats(wd, plan, name, step)
                rows.append({"stage": name, "step": step, "seconds": secs, "stage_seconds": summ.get("seconds"),
                             "simulate_seconds": st.get("simulate_seconds"), "substeps": st.get("substeps_total"),
                             "held_frames": st.get("held_frames"), "peak_gpu_mib": None,
                             "breakdown": breakdown(summ)})
        total = time.perf_counter() - t0
        if structure in ("worker", "server"):
            total -= idle.pop("sampled_seconds")
    sims = [r for r in rows if r["stage"] in SIM_STAGES and r["simulate_seconds"] is not None]
    sim = [r["simulate_seconds"] for r in sims]
    n_sub = [r.get("substeps") for r in sims]
    res = {"structure": structure, "total_seconds": round(total, 2), "jobs": rows,
           "substep_seconds": round(sum(sim), 2) if sim else None,
           "substeps": sum(n_sub) if sim and None not in n_sub else None,
           "peak_gpu_mib": mem.peak_above_baseline,
           "gpu_baseline_mib": mem.baseline}
    if structure in ("worker", "server"):
        res["idle_worker"] = idle
    return res


def _idle_worker(cache: Path, mem: "GpuMemory") -> dict:
    """What the warm worker holds once the run is over and it waits for the next one: its ping
    (pid, jobs served, resident MiB, torch's reserved CUDA MiB) and the GPU memory in use above
    the level before the first run (NVML, after 0.5 s).  ``sampled_seconds`` is the time spent
    here (not part of the run)."""
    from . import worker as W

    t0 = time.perf_counter()
    socks = sorted((cache / "w").glob("w-*.sock"))
    info = W.ping(socks[0]) if socks else None
    time.sleep(0.5)
    gpu = None
    if mem.available and mem.baseline is not None:
        with contextlib.suppress(Exception):
            gpu = round(mem._read() - mem.baseline, 1)
    return {"ping": info, "gpu_in_use_above_baseline_mib": gpu, "sampled_seconds": time.perf_counter() - t0}


def stop_workers(cache: Path) -> int:
    """Stop the warm workers and warm Snakemake servers left in ``cache/w`` (they outlive a run
    by worker.idle_seconds)."""
    from . import smk_server as S
    from . import worker as W

    return sum(bool(W.shutdown(p)) for p in sorted((cache / "w").glob("w-*.sock"))) + \
        sum(bool(S.stop(p)) for p in sorted((cache / "w").glob("s-*.sock")))


def breakdown(summary: dict | None) -> dict:
    """The fixed-cost figures of a stage summary (``runtime.run_stage``'s last log line): every
    key ending in ``_seconds`` or ``_mb`` and the ``timings`` dict the GPU stages record (first
    CUDA call, Taichi start, kernel loading, reading, encoding, ...)."""
    out: dict = {}
    for k, v in (summary or {}).items():
        if k == "timings" and isinstance(v, dict):
            out.update({f"t_{kk}": vv for kk, vv in v.items()})
        elif isinstance(v, (int, float)) and (k.endswith("_seconds") or k.endswith("_mb") or k == "seconds"):
            out[k] = v
        elif k == "seconds_parts" and isinstance(v, dict):
            out.update({f"part_{kk}": vv for kk, vv in v.items()})
    return out


def _sim_stats(wd: Path, plan, name: str, step: str | None) -> dict:
    """The stats of forward.h5 / final.h5 (Snakemake runs): simulate_seconds, substeps_total,
    held_frames, ... ({} for other stages or an unreadable file)."""
    if name not in SIM_STAGES:
        return {}
    path = wd / (plan.path("forward", step) if name == "forward_sim" else plan.path("final"))
    try:
        import h5py

        with h5py.File(path, "r") as f:
            return dict(json.loads(f.attrs["stats"]))
    except Exception:
        return {}


def measure(target: str = "bear", *, structures=STRUCTURES, n_gaussians: int | None = None,
            overrides: dict | None = None, config=None, workdir=None, cold: bool = True, warm: bool = True,
            with_metrics: bool = False, out=None, log=print, until: str | None = None) -> dict:
    """Time the whole pipeline of ``target`` in each structure, cold then warm (module docstring).

    Every run recomputes every stage in one scratch folder; each structure starts from its own
    empty Taichi kernel cache.  Returns {"target", "n_gaussians", "overrides", "device", "runs":
    [{structure, temperature, total_seconds, substep_seconds, peak_gpu_mib, jobs: [...]}, ...]};
    with ``out`` the result so far is written there (JSON) after every run.
    """
    scene = target.split("/")[0]
    tmp = Path(workdir or tempfile.mkdtemp(prefix="physgs-bench-"))
    wd = make_workdir(tmp, scene, n_gaussians, overrides, config)
    result = {"target": target, "n_gaussians": n_gaussians, "overrides": overrides or {}, "until": until,
              "device": _device(), "runs": [], "workdir": str(wd)}
    gpu0 = GpuMemory()
    base = gpu0._read() if gpu0.available else None  # before any run (and any warm worker)
    for structure in structures:
        cache = wd / f".cache-{structure}"
        if cache.exists():
            stop_workers(cache)
            shutil.rmtree(cache)
        blog = wd / f"bench-{structure}.log"
        if not cold:  # warm the kernel cache first, untimed
            run_structure(structure, wd, target, cache, blog, with_metrics, gpu_baseline=base, until=until)
        for temp in (["cold"] if cold else []) + (["warm"] if warm else []):
            r = run_structure(structure, wd, target, cache, blog, with_metrics, gpu_baseline=base, until=until)
            r["temperature"] = temp
            result["runs"].append(r)
            log(f"{structure:9s} {temp:4s}: {r['total_seconds']:7.2f} s, substeps {r['substep_seconds']} s "
                f"({_per_substep(r)}), "
                f"peak GPU {r['peak_gpu_mib']} MiB  " +
                " ".join(f"{j['stage']}={j['seconds']}" for j in r["jobs"]))
            if out:
                Path(out).parent.mkdir(parents=True, exist_ok=True)
                Path(out).write_text(json.dumps(result, indent=1, default=str) + "\n")
        stop_workers(cache)  # the warm run reused the cold run's worker, as a user's next run would
    return result


def _per_substep(r: dict) -> str:
    """``N substeps, X ms each`` of a run's simulation stages (or of one job)."""
    n, secs = r.get("substeps"), r.get("substep_seconds", r.get("simulate_seconds"))
    if not n or secs is None:
        return "substeps not counted"
    return f"{n} substeps, {1e3 * secs / n:.3f} ms each"


def _device() -> str:
    if shutil.which("nvidia-smi"):
        r = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True)
        if r.returncode == 0 and r.stdout.strip():
            return r.stdout.strip().splitlines()[0]
    return "cpu"


def table(result: dict) -> str:
    """A Markdown table of :func:`measure`'s runs."""
    lines = [f"{result['target']} ({result.get('n_gaussians') or 'default'} gaussians) on {result['device']}", "",
             "| structure | caches | whole pipeline (s) | substeps (s) | peak GPU (MiB) | slowest jobs |",
             "|---|---|---|---|---|---|"]
    for r in result["runs"]:
        slow = sorted((j for j in r["jobs"] if j["seconds"] is not None), key=lambda j: -j["seconds"])[:3]
        lines.append(f"| {r['structure']} | {r['temperature']} | {r['total_seconds']:.2f} | {r['substep_seconds']} | "
                     f"{r['peak_gpu_mib']} | " + ", ".join(f"{j['stage']} {j['seconds']:.2f}" for j in slow) + " |")
    for r in result["runs"]:
        if not any(j.get("breakdown") for j in r["jobs"]):
            continue
        lines += ["", f"Fixed costs per job, {r['structure']} {r['temperature']} (seconds; `t_*`: the stage's own "
                      "timings, e.g. t_cuda_start = its first CUDA call, t_first_substep = kernel loading)", "",
                  "| job | seconds | import | peak GPU (MiB) | breakdown |", "|---|---|---|---|---|"]
        for j in r["jobs"]:
            b = dict(j.get("breakdown") or {})
            if j.get("substeps") is not None:
                b["substeps"] = f"{j['substeps']} ({_per_substep(j)}, {j.get('held_frames')} frames held)"
            imp = j.get("import_seconds", b.pop("import_seconds", None))
            b.pop("seconds", None)
            parts = ", ".join(f"{k}={v}" for k, v in b.items() if v is not None)
            lines.append(f"| {j['stage']}{' ' + j['step'] if j.get('step') else ''} | {j['seconds']} | {imp} | "
                         f"{j.get('peak_gpu_mib')} | {parts} |")
        if r.get("idle_worker"):
            lines += ["", f"Idle worker after the run: {json.dumps(r['idle_worker'], default=str)}"]
    return "\n".join(lines)


# ============================================================================ start-up
def startup(target: str = "bear", *, n_gaussians: int | None = None, overrides: dict | None = None, config=None,
            workdir=None, log=print) -> list[dict]:
    """Per-stage fixed overhead of a fresh process (module docstring).  Kernel caches are warm:
    the chain runs once first.  Returns one row per job (wall and CPU seconds: on a busy machine
    compare the CPU figures)."""
    scene = target.split("/")[0]
    wd = make_workdir(Path(workdir or tempfile.mkdtemp(prefix="physgs-startup-")), scene, n_gaussians, overrides, config)
    cache = wd / ".cache-startup"
    env = _env(cache, False)
    blog = wd / "bench-startup.log"
    _run([sys.executable, "-m", "physgs_steps.pipeline_bench", "chain", target, "--config", "config.yaml",
          "--with-metrics", "--out", str(wd / ".warmup.json")], wd, env, blog)
    rows = []
    for name, step in _jobs(wd, target, True):
        out = wd / f".twice-{name}.json"
        cmd = [sys.executable, "-m", "physgs_steps.pipeline_bench", "twice", target, name, "--config", "config.yaml",
               "--out", str(out)] + (["--step", step] if step else [])
        cpu: list = []
        wall = _run(cmd, wd, env, blog, cpu)
        r = json.loads(out.read_text())
        row = {"stage": name, "step": step, "process_seconds": round(wall, 3), "import_seconds": r["import_seconds"],
               "first_seconds": r["first_seconds"], "warm_seconds": r["second_seconds"],
               "overhead_seconds": round(wall - r["second_seconds"], 3),
               "process_cpu_seconds": round(cpu[0], 3), "warm_cpu_seconds": r["second_cpu_seconds"],
               "overhead_cpu_seconds": round(cpu[0] - r["second_cpu_seconds"], 3), "heavy_modules": r["heavy_modules"]}
        rows.append(row)
        log(f"{name:14s} process {wall:6.2f} s ({cpu[0]:5.2f} s CPU), warm run {r['second_seconds']:6.2f} s "
            f"({r['second_cpu_seconds']:5.2f} s CPU) -> overhead {row['overhead_seconds']:5.2f} s "
            f"({row['overhead_cpu_seconds']:5.2f} s CPU); imports {r['import_seconds']:.2f} s: "
            f"{', '.join(r['heavy_modules'])}")
    return rows


# ============================================================================ Snakemake's own time
FEW_FRAMES = {"sim": {"n_frames": 6}, "bgdo": {"forward_frames": 6}, "render": {"width": 128, "height": 128}}
PHASES = ("import", "args", "snakefile", "snakefile_parse", "physgs_config", "physgs_plans", "dag_build",
          "input_functions", "dag_postprocess", "schedule", "jobs", "job_handling", "end")


def _worker_seconds(text: str) -> tuple[float, int]:
    """Sum and count of the stages' "X s in the warm worker" lines of a run's output."""
    import re

    secs = [float(m) for m in re.findall(r"\] \w+: ([0-9.]+) s in the warm worker", text)]
    return sum(secs), len(secs)


def _server_cpu(log: Path, n_before: int, timeout: float = 5.0) -> float | None:
    """CPU seconds of the warm Snakemake server's latest run (its log line; the server reaps
    runs once a second)."""
    import re

    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        lines = [ln for ln in (log.read_text().splitlines() if log.exists() else []) if "ended with status" in ln]
        if len(lines) > n_before:
            m = re.search(r"([0-9.]+) s CPU", lines[-1])
            return float(m.group(1)) if m else None
        time.sleep(0.1)
    return None


def snakemake_overhead(target: str = "bear", *, runs: int = 3, n_gaussians: int | None = None,
                       overrides: dict | None = None, config=None, workdir=None, few_frames: bool = True,
                       cache=None, modes=("snakemake", "server"), log=print) -> dict:
    """Snakemake's own time in a warm run of ``target`` (README "GPU", "Snakemake's own time").

    In a scratch folder (frames cut to 6 and a 128x128 video unless ``few_frames`` is False, so
    that the stages are cheap and the overhead shows), after one untimed run that makes every
    output and starts the warm stage worker: ``runs`` times, alternating, each of ``modes`` with
    nothing to do and with ``--forceall``.  ``snakemake``: ``python -m snakemake`` with its
    phases timed (smk_phases.py: import, argument parsing, Snakefile, DAG, jobs, end);
    ``server``: ``physgs snakemake`` through the warm Snakemake server (smk_server.py).  Each
    row: wall and CPU seconds of the run (Snakemake's process with its job processes; not the
    worker), the stages' own seconds in the worker, and what is left per job.
    """
    from . import smk_server as S

    ov = C_merge(FEW_FRAMES if few_frames else {}, overrides or {})
    scene = target.split("/")[0]
    wd = make_workdir(Path(workdir or tempfile.mkdtemp(prefix="physgs-smk-")), scene, n_gaussians, ov, config)
    bench_cache = wd / ".cache-smk"
    env = _env(Path(cache) if cache else bench_cache, worker=True)
    env["PHYSGS_WORKER_DIR"] = str(bench_cache / "w")
    env.pop(S.ENV_SWITCH, None)
    from . import config as C
    from . import plan as P

    sc, abl = P.parse_target(target)
    video = P.make_plan(C.load_config(wd / "config.yaml"), sc, abl).path("video")
    base = ["--cores", "1", "--configfile", "config.yaml"]
    blog = wd / "bench-snakemake.log"
    _run([sys.executable, "-m", "snakemake", *base, "--", video], wd, env, blog)  # outputs made, worker warm
    if "server" in modes:  # the warm Snakemake server started (its first run imports Snakemake)
        _run([sys.executable, "-m", "physgs_steps.cli", "snakemake", *base, "--", video], wd, env, blog)
    slog = None
    result = {"target": target, "workdir": str(wd), "device": _device(), "overrides": ov, "runs": []}
    try:
        for i in range(runs):
            for mode in modes:
                for kind in ("noop", "forceall"):
                    args = base + (["--forceall"] if kind == "forceall" else []) + ["--", video]
                    ph = wd / f".phases-{mode}-{kind}-{i}.json"
                    if mode == "snakemake":
                        cmd = [sys.executable, "-m", "physgs_steps.smk_phases", str(ph), "--", *args]
                    else:
                        cmd = [sys.executable, "-m", "physgs_steps.cli", "snakemake", *args]
                        socks = sorted((bench_cache / "w").glob("s-*.sock"))
                        slog = socks[0].with_suffix(".log") if socks else slog
                        n0 = sum("ended with status" in ln for ln in slog.read_text().splitlines()) \
                            if slog and slog.exists() else 0
                    start = blog.stat().st_size
                    cpu: list = []
                    run_env = env if mode == "snakemake" else dict(env, PHYSGS_SMK_PHASES=str(ph))
                    wall = _run(cmd, wd, run_env, blog, cpu)
                    with open(blog) as f:
                        f.seek(start)
                        text = f.read()
                    wsec, njobs = _worker_seconds(text)
                    row = {"mode": mode, "kind": kind, "run": i, "wall_seconds": round(wall, 3), "jobs": njobs,
                           "worker_seconds": round(wsec, 3)}
                    if mode == "snakemake":
                        row["cpu_seconds"] = round(cpu[0], 3)
                    else:
                        if slog is None:
                            socks = sorted((bench_cache / "w").glob("s-*.sock"))
                            slog = socks[0].with_suffix(".log") if socks else None
                        row["cpu_seconds"] = _server_cpu(slog, n0) if slog else None
                    if ph.exists():
                        phases = json.loads(ph.read_text())
                        row["phases"] = {k: phases[k] for k in PHASES if k in phases}
                        # outside Snakemake's timed run: interpreter start and teardown (snakemake);
                        # the client's start, the fork and the relay (server)
                        row["outside_phases"] = round(wall - phases.get("in_process", wall), 3)
                        if njobs:
                            row["per_job_outside_worker"] = round((phases.get("jobs", 0) - wsec) / njobs, 3)
                    row["outside_stages"] = round(wall - wsec, 3)
                    result["runs"].append(row)
                    log(_overhead_line(row))
    finally:
        stop_workers(bench_cache)
    return result


def C_merge(a: dict, b: dict) -> dict:
    from . import config as C

    return C.deep_merge(copy.deepcopy(a), b)


def _overhead_line(r: dict) -> str:
    s = (f"{r['mode']:9s} {r['kind']:8s} run {r['run']}: {r['wall_seconds']:6.2f} s wall, "
         f"{r['cpu_seconds'] if r.get('cpu_seconds') is not None else '?'} s CPU, {r['jobs']} jobs, "
         f"{r['worker_seconds']:.2f} s in the worker, {r['outside_stages']:.2f} s outside the stages")
    if r.get("phases"):
        s += "; " + " ".join(f"{k}={v:.2f}" for k, v in r["phases"].items() if isinstance(v, (int, float)))
        s += f" outside={r['outside_phases']:.2f}"
    if r.get("per_job_outside_worker") is not None:
        s += f"; per job outside the worker {r['per_job_outside_worker']:.3f} s"
    return s


def overhead_table(result: dict) -> str:
    """Medians of :func:`snakemake_overhead`'s runs per mode and kind (Markdown)."""
    import statistics

    lines = [f"Snakemake's own time, {result['target']} on {result['device']} (medians of the runs; seconds)", "",
             "| mode | run | wall | CPU | in the worker | outside the stages | per job outside the worker |",
             "|---|---|---|---|---|---|---|"]
    keys = sorted({(r["mode"], r["kind"]) for r in result["runs"]}, key=lambda k: (k[0] != "snakemake", k[1]))
    for mode, kind in keys:
        rs = [r for r in result["runs"] if (r["mode"], r["kind"]) == (mode, kind)]

        def med(key):
            v = [r[key] for r in rs if r.get(key) is not None]
            return f"{statistics.median(v):.2f}" if v else "-"

        pj = [r["per_job_outside_worker"] for r in rs if r.get("per_job_outside_worker") is not None]
        lines.append(f"| {mode} | {kind} | {med('wall_seconds')} | {med('cpu_seconds')} | {med('worker_seconds')} | "
                     f"{med('outside_stages')} | {f'{statistics.median(pj):.3f}' if pj else '-'} |")
    lines += ["", "Phases (smk_phases.py; medians; `outside`: interpreter start and teardown for snakemake, the "
                  "client's start, fork and relay for the server; `jobs`: the stage jobs' run: blocks, "
                  "`job_handling`: Snakemake's own work per job)", "",
              "| mode | run | " + " | ".join(PHASES) + " | outside |", "|---|---|" + "---|" * (len(PHASES) + 1)]
    for mode, kind in keys:
        ph = [r for r in result["runs"] if (r["mode"], r["kind"]) == (mode, kind) and r.get("phases")]
        if not ph:
            continue
        cells = []
        for k in PHASES:
            v = [r["phases"][k] for r in ph if k in r["phases"]]
            cells.append(f"{statistics.median(v):.2f}" if v else "-")
        out = statistics.median(r["outside_phases"] for r in ph)
        lines.append(f"| {mode} | {kind} | " + " | ".join(cells) + f" | {out:.2f} |")
    return "\n".join(lines)


HEAVY = ("torch", "taichi", "gsplat", "h5py", "scipy", "sklearn", "pandas", "trimesh", "transformers", "matplotlib",
         "jsonschema", "imageio_ffmpeg", "PIL", "psutil", "yaml")


# ============================================================================ child processes
def _plan(config: str, target: str):
    from . import config as C
    from . import plan as P

    scene, abl = P.parse_target(target)
    return P.make_plan(C.load_config(config), scene, abl)


def _chain(target: str, config: str, out: str, with_metrics: bool, until: str | None = None) -> None:
    """Every job of ``target`` in this process, in order (recomputed), with wall-clock marks."""
    from .cli import _stage_fn, stage_io
    from .runtime import run_stage

    plan = _plan(config, target)
    jobs = _keep(plan.jobs(), with_metrics, until)
    rows = []
    for name, step in jobs:
        ins, outs, scfg = stage_io(plan, name, step)
        logp = str(Path("results") / plan.target / "logs" / f"{name}{'-' + step if step else ''}.bench.log")
        t0w, t0 = time.time(), time.perf_counter()
        fn = _stage_fn(name)
        t_imp = time.perf_counter() - t0
        res = run_stage(name, fn, ins, outs, scfg, logp, import_seconds=round(t_imp, 3))
        rows.append({"stage": name, "step": step, "seconds": round(time.perf_counter() - t0, 3), "t0": t0w,
                     "t1": time.time(), "simulate_seconds": res.get("simulate_seconds"),
                     "substeps": res.get("substeps_total"), "held_frames": res.get("held_frames"),
                     "import_seconds": round(t_imp, 3), "breakdown": breakdown(res)})
    Path(out).write_text(json.dumps({"jobs": rows}, indent=1))


def _twice(target: str, name: str, step: str | None, config: str, out: str) -> None:
    t_imp = time.perf_counter()
    from .cli import _stage_fn, stage_io
    from .runtime import run_stage

    fn = _stage_fn(name)
    import_s = time.perf_counter() - t_imp
    plan = _plan(config, target)
    ins, outs, scfg = stage_io(plan, name, step)
    times, cpus = [], []
    for _ in range(2):
        t0, c0 = time.perf_counter(), time.process_time()
        run_stage(name, fn, ins, outs, scfg, None)
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    heavy = [m for m in HEAVY if m in sys.modules]
    Path(out).write_text(json.dumps({"import_seconds": round(import_s, 3), "first_seconds": round(times[0], 3),
                                     "second_seconds": round(times[1], 3), "second_cpu_seconds": round(cpus[1], 3),
                                     "heavy_modules": heavy}))


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="physgs bench", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("pipeline", "startup", "snakemake"):
        p = sub.add_parser(name)
        p.add_argument("target", nargs="?", default="bear")
        p.add_argument("--n-gaussians", type=int, default=None, help="builtin.n_gaussians of the scene")
        p.add_argument("--set", action="append", help="config override key=value (YAML value), repeatable")
        p.add_argument("--config", default=None, help="base config file (default config/config.yaml)")
        p.add_argument("--workdir", default=None, help="scratch folder (default: a new temporary one)")
        p.add_argument("--out", default=None, help="write the result as JSON here")
        if name == "pipeline":
            p.add_argument("--structures", default=",".join(STRUCTURES))
            p.add_argument("--no-cold", action="store_true")
            p.add_argument("--no-warm", action="store_true")
            p.add_argument("--with-metrics", action="store_true")
            p.add_argument("--until", choices=("final_sim",), default=None,
                           help="stop after the final simulation (e.g. where nothing can render)")
        if name == "snakemake":
            p.add_argument("--runs", type=int, default=3, help="timed runs per mode and kind")
            p.add_argument("--all-frames", action="store_true",
                           help="keep the config's frame counts and video size (default: 6 frames, 128x128)")
            p.add_argument("--cache", default=None,
                           help="Taichi kernel cache to use (default: $PHYSGS_CACHE_DIR, else one in the workdir)")
            p.add_argument("--modes", default="snakemake,server")
    c = sub.add_parser("chain", help=argparse.SUPPRESS)
    c.add_argument("target")
    c.add_argument("--config", required=True)
    c.add_argument("--out", required=True)
    c.add_argument("--with-metrics", action="store_true")
    c.add_argument("--until", default=None)
    t = sub.add_parser("twice", help=argparse.SUPPRESS)
    t.add_argument("target")
    t.add_argument("stage")
    t.add_argument("--step", default=None)
    t.add_argument("--config", required=True)
    t.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    if a.cmd == "chain":
        _chain(a.target, a.config, a.out, a.with_metrics, a.until)
        return 0
    if a.cmd == "twice":
        _twice(a.target, a.stage, a.step, a.config, a.out)
        return 0
    overrides = parse_sets(a.set)
    if a.cmd == "snakemake":
        res = snakemake_overhead(a.target, runs=a.runs, n_gaussians=a.n_gaussians, overrides=overrides,
                                 config=a.config, workdir=a.workdir, few_frames=not a.all_frames,
                                 cache=a.cache or os.environ.get("PHYSGS_CACHE_DIR"),
                                 modes=[m for m in a.modes.split(",") if m])
        print(overhead_table(res))
    elif a.cmd == "startup":
        res = startup(a.target, n_gaussians=a.n_gaussians, overrides=overrides, config=a.config, workdir=a.workdir)
    else:
        res = measure(a.target, structures=[s for s in a.structures.split(",") if s], n_gaussians=a.n_gaussians,
                      overrides=overrides, config=a.config, workdir=a.workdir, cold=not a.no_cold,
                      warm=not a.no_warm, with_metrics=a.with_metrics, out=a.out, until=a.until)
        print(table(res))
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
