"""Stage ``bench_stress``: one run of the stress-vs-E figure (the paper's "Variation of the
particle stress tau with different initial E", 60 runs in which only E changes).

inputs  {"particles": particles.h5, "params": params.json (params_0 of the scene)}
outputs {"result": run<i>.json}
cfg     {"E": initial E (Pa, every instance), "index", "runs", "sim": <the plan's sim stage cfg>,
         "bgdo": <the plan's bgdo stage cfg with iterations 1>}

The run is the workflow's own forward_sim and bgdo_update (physgs_steps.simulate.run_forward,
physgs_steps.bgdo.run) in this process on temporary files, followed by one pseudo step per key
frame after frame 0 (frame 0 is the rest state, tau = 0) that collects the per-particle stress
signal g_p = d||tau_p||/dlog E (= ||tau_p||, Pa). Only the figures are kept: the key frames of 60
full-size runs would be gigabytes. An unstable forward run is a result (BGDO's fate
"exploded" or "broken"), not a failure.
"""
from __future__ import annotations

import copy
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from ..runtime import read_json, read_json_input, write_json


def particle_stress(keyframes: str, params: dict, cfg: dict) -> dict:
    """Percentiles of |d||tau_p||/dlog E| over all particles and key frames after frame 0."""
    import torch

    from .. import bgdo as B

    meta = B.read_keyframes_meta(keyframes)
    table = B.instance_table(params["instances"], meta["label"], meta["vol"], filled=meta.get("filled"))
    grid = B.grid_from_config(cfg, meta.get("sim_config"))
    log_E = B.log_E_from_instances(params["instances"])
    samples = []
    for kf in B.iter_keyframes(keyframes, meta["frames"]):
        if kf["frame"] == 0:
            continue
        st = {k: torch.as_tensor(kf[k], dtype=torch.float32) for k in ("x", "v", "C", "F")}
        ok = torch.ones(st["x"].shape[0], dtype=torch.bool)
        for v in st.values():
            ok &= torch.isfinite(v.reshape(v.shape[0], -1)).all(dim=1)
        ok &= ((st["x"] >= 0) & (st["x"] <= 1)).all(dim=1)
        idx = torch.nonzero(ok, as_tuple=True)[0]
        if idx.numel() == 0:
            continue
        leaf = log_E.detach().clone().double().requires_grad_(True)
        out = B.pseudo_step({k: v[idx] for k, v in st.items()}, float(kf["dt"]), leaf, table.select(idx), grid)
        s = out["tau"].flatten(1).norm(dim=1)
        g, = torch.autograd.grad(s.sum(), [out["log_E_p"]])
        samples.append(g.detach().abs().double().numpy())
    if not samples:
        return {"n": 0, "reason": "no key frame after frame 0 with finite particles"}
    a = np.concatenate(samples)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {"n": 0, "reason": "no finite stress sample"}
    q = np.percentile(a, [10, 50, 90])
    return {"n": int(a.size), "mean": float(a.mean()), "p10": float(q[0]), "median": float(q[1]), "p90": float(q[2])}


def run(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    from .. import bgdo, simulate
    from ..errors import ConfigError

    E = cfg.get("E")
    if isinstance(E, bool) or not isinstance(E, (int, float)) or not E > 0:
        raise ConfigError("benchmark.stress", f"a stress run needs a positive initial E, got {E!r}")
    p0 = read_json_input(inputs["params"], "params file")
    params = copy.deepcopy(p0)
    for inst in params["instances"]:
        inst["E"] = float(E)
    material = params["instances"][0].get("material") if params["instances"] else None
    out_dir = Path(outputs["result"]).parent
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".stress-", dir=out_dir) as tmp:
        pin, kf, pout = str(Path(tmp) / "params.json"), str(Path(tmp) / "forward.h5"), str(Path(tmp) / "params1.json")
        write_json(pin, params)
        t0 = time.perf_counter()
        fwd = simulate.run_forward({"particles": inputs["particles"], "params": pin}, {"keyframes": kf}, cfg["sim"], log)
        t1 = time.perf_counter()
        bgdo.run({"keyframes": kf, "params": pin}, {"params": pout}, cfg["bgdo"], log)
        t2 = time.perf_counter()
        rec = read_json(pout)["bgdo"]
        stress = particle_stress(kf, params, cfg["bgdo"])
        t3 = time.perf_counter()
    first = rec["instances"][0]
    deltas = [f["delta"] for f in first.get("frames") or [] if f.get("delta") is not None and f.get("weight", 1) > 0
              and f.get("frame", 0) > 0]
    result = {
        "index": cfg.get("index"), "E": float(E), "material": material, "band": first.get("band"),
        "stable": bool(fwd["stable"]), "fate": (rec.get("instance_fates") or [None])[0], "G": first.get("G"),
        "eta": first.get("eta"), "E_after": first.get("E_after"), "rule": first.get("rule"),
        "delta": float(np.mean(deltas)) if deltas else None, "stress": stress,
        "substeps_total": fwd.get("substeps_total"),
        "seconds": {"forward": round(t1 - t0, 3), "bgdo": round(t2 - t1, 3), "stress": round(t3 - t2, 3)},
    }
    write_json(outputs["result"], result)
    log.info("stress run %s/%s: E %.4g Pa -> %s, forward %s, fate %s, stress median %s Pa -> %s", cfg.get("index"),
             cfg.get("runs"), E, "n/a" if result["E_after"] is None else f"{result['E_after']:.4g}",
             "stable" if result["stable"] else "UNSTABLE", result["fate"],
             "n/a" if not stress.get("n") else f"{stress['median']:.4g}", outputs["result"])
    return {"E": float(E), "stable": result["stable"], "fate": result["fate"]}
