"""The command of every stage rule's job: ``python -m physgs_steps.job STAGE SPEC [LOG]``.

The stage rules (prepare ... render, metrics, stage_report, bench_stress) are ``shell:`` rules
that run this module, not ``script:`` rules.  A ``script:`` job is a Python process that
imports Snakemake and unpickles its job object before the stage even starts (0.4-1 s on the
2-core CPU machine, more than the warm worker's whole work for most jobs); this client imports
the standard library and ``physgs_steps.worker`` only, then hands the job to the warm stage
worker (``worker.run_stage_job``), or, where no worker is wanted or none can be started, runs
the stage in this process exactly as the ``script:`` adapter did.

``SPEC`` is the rule's ``params.job``: JSON text ``{"input": {name: path}, "output": {name:
path}, "cfg": {...}, "worker": {...}}`` (the job's named inputs and outputs, the stage's config
subset, which is also the rule's ``params.cfg`` that Snakemake's rerun trigger compares, and
the config's ``worker`` section), or ``@PATH`` of a file holding it where the text would be too
long for one command-line argument.  ``LOG`` is the rule's ``log:`` file.
"""
from __future__ import annotations

import json
import sys

USAGE = "usage: python -m physgs_steps.job STAGE SPEC [LOG]  (SPEC: JSON text or @file; see the module docstring)"


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
