"""The command of every stage rule's job: ``python -m physgs_steps.job STAGE SPEC [LOG]``.

The stage rules (prepare ... render, metrics, stage_report, bench_stress) are ``shell:`` rules
that run this module, not ``script:`` rules.  A ``script:`` job is a Python process that
imports Snakemake and unpickles its job object before the stage even starts (0.4-1 s on the
2-core CPU machine, more than the warm worker's whole work for most jobs); this client imports
the standard library and ``physgs_steps.worker`` only, then hands the job to the warm stage
worker (``worker.run_stage_job``), or, where no worker is wanted or none can be started, runs
the stage in this process exactly as the ``script:`` adapter did.

``SPEC`` is JSON text ``{"input": {name: path}, "output": {name: path}, "cfg": {...},
"worker": {...}}`` (the job's named inputs and outputs, the stage's config subset, which is
also the rule's ``params.cfg`` that Snakemake's rerun trigger compares, and the config's
``worker`` section), or ``@PATH`` of a file holding it where the text would be too long for one
command-line argument.  ``LOG`` is the rule's ``log:`` file.  :func:`command` writes the whole
command line (the rules' ``params.job``, run as ``{params.job} {log:q}``).
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

USAGE = "usage: python -m physgs_steps.job STAGE SPEC [LOG]  (SPEC: JSON text or @file; see the module docstring)"


# one command-line argument may hold 128 KiB (MAX_ARG_STRLEN); longer specs go to a file
SPEC_ARG_LIMIT = 60000
SPEC_DIR = Path(".snakemake") / "physgs_jobs"


def command(stage: str, inputs: dict, outputs: dict, cfg: dict, worker_cfg: dict | None = None,
            python: str | None = None) -> str:
    """The shell command of one job of ``stage`` (a stage rule's ``params.job``; the rule runs
    ``{params.job} {log:q}``): this module under ``python`` (default: this interpreter, the one
    Snakemake runs in, as a ``script:`` rule would use) with the job's spec, quoted for the shell.
    A spec longer than SPEC_ARG_LIMIT is written to ``.snakemake/physgs_jobs/<sha1>.json``
    (relative to the working folder, content-addressed) and passed as ``@path``."""
    import hashlib
    import shlex

    text = json.dumps({"input": inputs, "output": outputs, "cfg": cfg, "worker": worker_cfg or {}},
                      separators=(",", ":"), default=str)
    if len(text) > SPEC_ARG_LIMIT:
        path = (SPEC_DIR / f"{hashlib.sha1(text.encode()).hexdigest()}.json").resolve()
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(text)
            os.replace(tmp, path)
        text = f"@{path}"
    return f"{shlex.quote(python or sys.executable)} -m physgs_steps.job {shlex.quote(stage)} {shlex.quote(text)}"


class StageFailed(Exception):
    """A stage that the warm worker ran for a rule's ``run:`` block failed (its message is in
    the relayed output above and in its log)."""


def run_in_worker(stage: str, inputs: dict, outputs: dict, cfg: dict, log: str | None,
                  worker_cfg: dict | None = None, client: str = "Snakemake's process") -> bool:
    """A stage rule's ``run:`` block (common.smk ``stage_job``), in a thread of Snakemake's own
    process: hand the job to the warm stage worker straight from there, with no process started
    for it.  True when the worker ran it (raises :class:`StageFailed` when the stage failed);
    False when no worker is wanted or none could be started: the rule then runs the job client
    in its own process (``shell(STAGE_JOB)``), the stage in that process, as a ``shell:`` rule did."""
    from .worker import DEFAULT_IDLE_SECONDS, run_job, wants_worker

    wcfg = worker_cfg or {}
    if not wants_worker(stage, wcfg):
        return False
    rc = run_job(stage, inputs, outputs, cfg, log, float(wcfg.get("idle_seconds", DEFAULT_IDLE_SECONDS)), client)
    if rc is None:
        sys.stderr.write("physgs worker: none could be started; running the stage in its own process\n")
        return False
    if rc != 0:
        raise StageFailed(f"physgs: {stage} failed in the warm stage worker (exit status {rc}); its log: {log}")
    return True


def read_spec(arg: str) -> dict:
    """The job's spec from ``SPEC`` (JSON text, or ``@path`` of a JSON file)."""
    where = "the job spec (command line)"
    if arg.startswith("@"):
        where = f"the job spec file {arg[1:]}"
        try:
            with open(arg[1:], encoding="utf-8") as f:
                arg = f.read()
        except OSError as e:
            raise SystemExit(f"physgs job: cannot read {where}: {e.strerror}")
    try:
        spec = json.loads(arg)
    except ValueError as e:
        raise SystemExit(f"physgs job: {where} is not valid JSON: {e}")
    if not isinstance(spec, dict) or not all(isinstance(spec.get(k, {}), dict) for k in ("input", "output", "cfg")):
        raise SystemExit(f"physgs job: {where} must be an object with 'input', 'output' and 'cfg' objects")
    return spec


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if len(argv) not in (2, 3) or argv[0] in ("-h", "--help"):
        print(USAGE, file=sys.stderr)
        return 2
    stage, spec = argv[0], read_spec(argv[1])
    log = argv[2] if len(argv) == 3 and argv[2] else None
    from .worker import ENTRIES, run_stage_job

    if stage not in ENTRIES:
        print(f"physgs job: unknown stage {stage!r} (one of: {', '.join(sorted(ENTRIES))})", file=sys.stderr)
        return 2
    run_stage_job(stage, spec.get("input") or {}, spec.get("output") or {}, spec.get("cfg") or {}, log,
                  spec.get("worker"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
