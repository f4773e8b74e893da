"""Stage functions of the validation rules (workflow/rules/validation.smk).

``cfg`` is ``{"validation": <validated section>, "device": ...}``.  Each stage writes its
outputs atomically; a run that fails physically (unstable, timed out) still writes its record
(with ``error: null`` and the message): that is a result, not a stage failure.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

from ..errors import ConfigError, InputError
from ..mpm.backend import ensure_taichi
from ..runtime import read_json_input, write_json
from . import sweep as S
from .base import Setting
from .cases import CASES
from .report import build, snapshot


def _backend(cfg: dict) -> str:
    b = cfg["validation"].get("backend", "auto")
    if b == "auto":
        b = cfg.get("device", "auto")
    return ensure_taichi(b)


def run_case(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """One (case, variant, setting) run -> its record JSON.  cfg also holds ``case``, ``variant``, ``setting``."""
    name = cfg["case"]
    if name not in CASES:
        raise ConfigError("validation case", f"unknown case {name!r}; known: {', '.join(CASES)}")
    setting = Setting.parse(cfg["setting"])
    backend = _backend(cfg)
    log.info("validation run %s/%s at %s on %s", name, cfg["variant"], setting.id, backend)
    rec = CASES[name].run(cfg["variant"], setting, backend=backend, timeout_s=cfg["validation"]["timeout_s"], log=log)
    d = rec.as_dict()
    d["backend"] = backend
    write_json(outputs["record"], d)
    log.info("error %s, %.2f s simulated (%d substeps, %d particles)%s", rec.error, rec.sim_seconds, rec.substeps,
             rec.n_particles, f": {rec.message}" if rec.message else "")
    return {"error": rec.error, "sim_seconds": rec.sim_seconds}


def run_sweep(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Every cell of one elasticity x plasticity pair -> the pair's JSON."""
    el, pl = S.parse_pair(cfg["pair"])
    backend = _backend(cfg)
    v = cfg["validation"]
    res = S.run_pair(el, pl, v["scale"], backend=backend, timeout_s=v["sweep_timeout_s"], log=log)
    res["backend"] = backend
    write_json(outputs["result"], res)
    log.info("%s: %s", cfg["pair"], res["counts"])
    return res["counts"]


def report(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Runs + sweeps (+ the before snapshot) -> REPORT.md, CSVs, figures."""
    records = [read_json_input(p, "validation record") for p in inputs.get("runs", [])]
    sweeps = [read_json_input(p, "sweep result") for p in inputs.get("sweeps", [])]
    v = cfg["validation"]
    before = None
    if inputs.get("before"):
        before = read_json_input(inputs["before"], "before snapshot (validation.before)")
        if not isinstance(before, dict) or not isinstance(before.get("records"), list):
            raise InputError(inputs["before"], "a before snapshot needs a 'records' list (validation.report.snapshot)")
    device = sorted({r.get("backend", "cpu") for r in records} | {s.get("backend", "cpu") for s in sweeps}) or ["cpu"]
    figures = {Path(p).stem: p for p in outputs.get("figures", [])}  # the physics figures go next to them
    out_dir = Path(outputs["report"]).parent
    summary = build(records, sweeps, out_dir, scale=v["scale"], device="+".join(device), before=before, figures=figures)
    from .. import reporting as R

    prov = R.provenance(scale=v["scale"], device="+".join(device))
    write_json(outputs["snapshot"], snapshot(records, sweeps, f"commit {prov.get('commit')}", prov))
    log.info("validation report: %s", json.dumps(summary))
    return summary
