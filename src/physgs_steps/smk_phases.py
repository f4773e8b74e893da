"""Where a Snakemake run's own time goes: ``python -m physgs_steps.smk_phases OUT.json -- SNAKEMAKE ARGS``.

Runs Snakemake's command line in this process (as the ``snakemake`` command would) with timers
around its phases, and writes them to ``OUT.json`` when the process ends (measurement only:
the timers wrap Snakemake's functions and change nothing they do):

* ``import``: importing ``snakemake.cli`` (Snakemake, its plugin registries, its persistence);
* ``args``: parsing the command line and the profiles (``cli.parse_args``);
* ``snakefile``: parsing and executing the Snakefile and its includes (``Workflow.include``),
  of which ``snakefile_parse`` is Snakemake's parser (turning the rules into Python) and
  ``physgs_config`` / ``physgs_plans`` this workflow's config validation and plans;
* ``dag_prepare`` (persistence, locks), ``dag_build`` (``DAG.init``: rules matched to the
  requested files, input functions (``input_functions``), existence and mtime checks) and
  ``dag_postprocess`` (what needs to run: rerun triggers, metadata);
* ``schedule``: the scheduler from the first job to the last one's end, with ``jobs``: each
  job's ``run_wrapper`` (its ``shell:`` command: bash, the job client, the stage) and
  ``job_handling`` (Snakemake's own work per job: preparing outputs, checking and touching
  them, writing ``.snakemake/metadata``, the DAG update);
* ``end``: from the scheduler's end to the process's end (``onsuccess``, the log file).

``physgs bench snakemake`` (pipeline_bench.py) runs this in a scratch folder, warm, with
nothing to do and with ``--forceall``, and prints the table.
"""
from __future__ import annotations

import atexit
import functools
import inspect
import json
import os
import sys
import threading
import time

T0 = time.perf_counter()
_lock = threading.Lock()
TIMES: dict[str, float] = {}
COUNTS: dict[str, int] = {}
MARKS: dict[str, float] = {}
JOBS: list[dict] = []


def _add(key: str, dt: float) -> None:
    with _lock:
        TIMES[key] = TIMES.get(key, 0.0) + dt
        COUNTS[key] = COUNTS.get(key, 0) + 1


def _wrap(obj, name: str, key: str, outermost: bool = True) -> None:
    """Time every call of ``obj.name`` into ``key`` (nested calls counted once)."""
    fn = getattr(obj, name)
    depth = threading.local()

    if inspect.iscoroutinefunction(fn):
        @functools.wraps(fn)
        async def wrapper(*a, **k):
            d = getattr(depth, "n", 0)
            depth.n = d + 1
            t = time.perf_counter()
            try:
                return await fn(*a, **k)
            finally:
                depth.n = d
                if d == 0 or not outermost:
                    _add(key, time.perf_counter() - t)
    else:
        @functools.wraps(fn)
        def wrapper(*a, **k):
            d = getattr(depth, "n", 0)
            depth.n = d + 1
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                depth.n = d
                if d == 0 or not outermost:
                    _add(key, time.perf_counter() - t)
    setattr(obj, name, wrapper)


def _install() -> None:
    import snakemake.cli as cli
    import snakemake.dag as dag
    import snakemake.executors.local as local
    import snakemake.jobs as jobs
    import snakemake.rules as rules
    import snakemake.workflow as wf
    from snakemake.scheduling import job_scheduler as js

    _wrap(cli, "parse_args", "args")
    _wrap(wf.Workflow, "include", "snakefile")
    _wrap(wf, "parse", "snakefile_parse")
    _wrap(wf.Workflow, "_prepare_dag", "dag_prepare")
    _wrap(wf.Workflow, "_build_dag", "dag_build")
    _wrap(dag.DAG, "postprocess", "dag_postprocess")
    _wrap(rules.Rule, "apply_input_function", "input_functions")
    _wrap(js.JobScheduler, "schedule", "schedule")
    _wrap(jobs.Job, "prepare", "job_handling")
    _wrap(js.JobScheduler, "_finish_jobs", "job_handling")

    run_wrapper = local.run_wrapper

    @functools.wraps(run_wrapper)
    def timed_run_wrapper(job_rule, *a, **k):
        t = time.perf_counter()
        try:
            return run_wrapper(job_rule, *a, **k)
        finally:
            dt = time.perf_counter() - t
            _add("jobs", dt)
            with _lock:
                JOBS.append({"rule": job_rule.name, "seconds": round(dt, 4)})

    local.run_wrapper = timed_run_wrapper

    sched = js.JobScheduler.schedule

    @functools.wraps(sched)
    def marked_schedule(self, *a, **k):
        try:
            return sched(self, *a, **k)
        finally:
            MARKS["schedule_end"] = time.perf_counter()

    js.JobScheduler.schedule = marked_schedule

    try:  # this workflow's own parse-time work (common.smk)
        from physgs_steps import config as C
        from physgs_steps import plan as P

        _wrap(C, "validate_config", "physgs_config")
        _wrap(C, "list_scenes", "physgs_config")
        _wrap(P.Registry, "plan", "physgs_plans")
        _wrap(P.Registry, "for_id", "physgs_plans")
    except ImportError:
        pass


def report() -> dict:
    t_end = time.perf_counter()
    out = {k: round(v, 4) for k, v in TIMES.items()}
    out["counts"] = dict(COUNTS)
    out["in_process"] = round(t_end - T0, 4)
    if "schedule_end" in MARKS:
        out["end"] = round(t_end - MARKS["schedule_end"], 4)
    out["job_list"] = JOBS
    return out


def start(out_path: str) -> None:
    """Time this process's Snakemake run from now (the warm server's child, Snakemake already
    imported: smk_server.py with ``PHYSGS_SMK_PHASES=<out.json>``); written at exit."""
    global T0
    T0 = time.perf_counter()
    TIMES.clear()
    COUNTS.clear()
    t = time.perf_counter()
    _install()
    TIMES["harness"] = time.perf_counter() - t

    def write():
        with open(out_path, "w") as f:
            json.dump(report(), f, indent=1)

    atexit.register(write)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if len(argv) < 2 or argv[1] != "--":
        print("usage: python -m physgs_steps.smk_phases OUT.json -- SNAKEMAKE ARGS", file=sys.stderr)
        return 2
    out_path, smk_args = argv[0], argv[2:]

    def write():
        with open(out_path, "w") as f:
            json.dump(report(), f, indent=1)

    atexit.register(write)
    t = time.perf_counter()
    import snakemake.cli  # noqa: F401

    TIMES["import"] = time.perf_counter() - t
    t = time.perf_counter()
    _install()
    TIMES["harness"] = time.perf_counter() - t
    sys.argv = ["snakemake", *smk_args]
    from snakemake.cli import main as smk_main

    smk_main(smk_args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
