"""Per-particle stress against the initial Young's modulus (the paper's Fig. "Variation of the
particle stress tau with different initial E", 60 runs), with the BGDO step of each run.

    python benchmarks/bgdo_stress_vs_E.py [--scene bear] [--runs 60] [--E-min 30] [--E-max 3e10]
        [--n-gaussians 3000] [--forward-frames 30] [--bgdo KEY=VALUE ...]
        [--out benchmarks/out/bgdo_stress_vs_E]

Only E changes between runs (log-spaced from E-min to E-max; every instance gets the same E):
the scene is prepared once (prepare -> cluster -> fill -> vlm_params), then each run is one
forward_sim (physgs_steps.simulate.run_forward) and one bgdo_update (physgs_steps.bgdo.run).
From each run's key frames the per-particle stress signal g_p = d||tau_p||/dlog E (= ||tau_p||,
Pa) is collected over all key frames after the first (frame 0 is the rest state, tau = 0).

Writes <out>/stress_vs_E.png (top: per-particle stress, median and 10-90 % band, and the
compressed signal; bottom: the deformation delta and the BGDO step -G = change of log E, with
the material's band) and <out>/stress_vs_E.json, and prints the table. Needs matplotlib
(benchmark-only dependency: pip install matplotlib).
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from bgdo_robustness import _logger, band_of, make_config, prepare_scene, write_scenes  # noqa: E402


def particle_stress(keyframes: str, params: str, cfg: dict) -> dict:
    """Per-particle stress-gradient samples of every key frame after frame 0 (one pseudo step each)."""
    import torch

    from physgs_steps import bgdo as B
    from physgs_steps.runtime import read_json

    p = read_json(params)
    meta = B.read_keyframes_meta(keyframes)
    table = B.instance_table(p["instances"], meta["label"], meta["vol"])
    grid = B.grid_from_config(cfg, meta.get("sim_config"))
    log_E = B.log_E_from_instances(p["instances"])
    samples = []
    for kf in B.iter_keyframes(keyframes, meta["frames"]):
        if kf["frame"] == 0:
            continue
        st = {k: torch.as_tensor(kf[k], dtype=torch.float32) for k in ("x", "v", "C", "F")}
        ok = B._finite_rows(*st.values())
        idx = torch.nonzero(ok, as_tuple=True)[0]
        leaf = log_E.clone().requires_grad_(True)
        out = B.pseudo_step({k: v[idx] for k, v in st.items()}, kf["dt"], leaf, table.select(idx), grid)
        s = out["tau"].flatten(1).norm(dim=1)
        g, = torch.autograd.grad(s.sum(), [out["log_E_p"]])
        samples.append(g.detach().abs().numpy())
    if not samples:
        return {"n": 0}
    a = np.concatenate(samples)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {"n": 0}
    q = np.percentile(a, [10, 50, 90])
    return {"n": int(a.size), "mean": float(a.mean()), "p10": float(q[0]), "median": float(q[1]), "p90": float(q[2])}


def plot(rows: list[dict], band, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    E = np.array([r["E"] for r in rows])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7.5, 7.5), sharex=True)
    ax1.set_xscale("log")
    ax1.set_yscale("log")
    have = [i for i, r in enumerate(rows) if r["stress"].get("n")]
    if have:
        med = np.array([rows[i]["stress"]["median"] for i in have])
        lo = np.array([rows[i]["stress"]["p10"] for i in have])
        hi = np.array([rows[i]["stress"]["p90"] for i in have])
        mean = np.array([rows[i]["stress"]["mean"] for i in have])
        ax1.fill_between(E[have], np.maximum(lo, 1e-3), np.maximum(hi, 1e-3), alpha=0.25, label="per-particle 10-90 %")
        ax1.plot(E[have], np.maximum(med, 1e-3), "o-", ms=3, label="per-particle median")
        ax1.plot(E[have], np.maximum(mean, 1e-3), "s", ms=2.5, label="per-particle mean")
    ylo, yhi = ax1.get_ylim() if have else (1e-3, 1.0)
    bottom, top = ylo * 2.0, yhi / 2.0
    expl = [i for i, r in enumerate(rows) if r["fate"] == "exploded"]
    if expl:
        ax1.plot(E[expl], np.full(len(expl), top), "rx", label="forward run exploded (stress diverged; BGDO: +inf)")
    broken = [i for i, r in enumerate(rows) if r["fate"] == "broken"]
    if broken:
        ax1.plot(E[broken], np.full(len(broken), bottom), "kv", ms=4, label="forward run collapsed (J < j_min)")
    ax1.text(0.99, 0.02, "unstable runs: stress of the last stable key frame", transform=ax1.transAxes,
             ha="right", va="bottom", fontsize=7)
    ax1.set_ylim(ylo, yhi)
    ax1.set_ylabel("stress signal |d||tau_p||/dlog E| = ||tau_p|| [Pa]")
    ax1.legend(loc="upper left", fontsize=8)
    ax1.set_title(title, fontsize=9)
    G = np.array([r["G"] if r["G"] is not None else np.nan for r in rows])
    delta = np.array([r["delta"] if r["delta"] is not None else np.nan for r in rows])
    ax2.plot(E, -G, "o-", ms=3, color="C3", label="BGDO step -G = change of log E")
    ax2.axhline(0.0, color="k", lw=0.6)
    ax2.set_ylabel("change of log E in one iteration")
    ax3 = ax2.twinx()
    ax3.plot(E, delta, "^", ms=3, color="C2", label="mean deformation delta (key frames)")
    ax3.set_ylabel("delta = mean ||sigma' - 1||", color="C2")
    for a in (ax1, ax2):
        if band:
            a.axvspan(band[0], band[1], color="C1", alpha=0.12, label="material band (KB E_range)" if a is ax2 else None)
    ax2.set_xlabel("initial Young's modulus E [Pa]")
    h1, l1 = ax2.get_legend_handles_labels()
    h2, l2 = ax3.get_legend_handles_labels()
    ax2.legend(h1 + h2, l1 + l2, loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bear")
    ap.add_argument("--runs", type=int, default=60)
    ap.add_argument("--E-min", type=float, default=30.0)
    ap.add_argument("--E-max", type=float, default=3e10)
    ap.add_argument("--n-gaussians", type=int, default=3000)
    ap.add_argument("--forward-frames", type=int, default=30)
    ap.add_argument("--bgdo", nargs="*", default=[], help="bgdo config overrides KEY=VALUE (YAML values)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "out" / "bgdo_stress_vs_E"))
    args = ap.parse_args(argv)
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print("bgdo_stress_vs_E needs matplotlib (benchmark-only dependency): pip install matplotlib", file=sys.stderr)
        return 2
    import torch

    torch.set_num_threads(args.threads)
    from physgs_steps import bgdo, plan as P, simulate
    from physgs_steps.runtime import read_json, write_json

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    scenes_dir = Path(tempfile.mkdtemp(prefix="scenes_", dir=out))
    write_scenes([args.scene], args.n_gaussians, scenes_dir)
    args.frames, args.iterations = args.forward_frames, 1
    cfg = make_config(args, scenes_dir)
    os.chdir(out)
    log = _logger()
    plan = P.make_plan(cfg, args.scene)
    prepare_scene(plan, log)
    p0 = read_json(plan.path("params0"))
    material = p0["instances"][0].get("material")
    band = band_of(material)
    rows = []
    runs = out / "runs"
    runs.mkdir(exist_ok=True)
    for E in np.geomspace(args.E_min, args.E_max, args.runs):
        E = float(E)
        p = copy.deepcopy(p0)
        for inst in p["instances"]:
            inst["E"] = E
        pin, kf, pout = runs / f"p_{E:.4g}.json", runs / f"f_{E:.4g}.h5", runs / f"o_{E:.4g}.json"
        write_json(pin, p)
        t0 = time.perf_counter()
        r = simulate.run_forward({"particles": plan.path("particles"), "params": str(pin)}, {"keyframes": str(kf)},
                                 plan.cfgs["sim"], log)
        t1 = time.perf_counter()
        bgdo.run({"keyframes": str(kf), "params": str(pin)}, {"params": str(pout)}, plan.cfgs["bgdo"], log)
        t2 = time.perf_counter()
        rec = read_json(pout)["bgdo"]
        i0 = rec["instances"][0]
        ds = [f["delta"] for f in i0["frames"] if f.get("delta") is not None and f.get("weight", 1) > 0]
        row = {"E": E, "stable": r["stable"], "fate": rec["instance_fates"][0], "G": i0["G"], "eta": i0["eta"],
               "E_after": i0["E_after"], "delta": float(np.mean(ds)) if ds else None,
               "stress": particle_stress(str(kf), str(pin), plan.cfgs["bgdo"]),
               "forward_s": round(t1 - t0, 2), "bgdo_s": round(t2 - t1, 2)}
        rows.append(row)
        st = row["stress"]
        print(f"E={E:9.3g}  {'stable  ' if r['stable'] else 'UNSTABLE'} {row['fate']:8s}  "
              f"stress median {st.get('median', float('nan')):9.3g} Pa  p90 {st.get('p90', float('nan')):9.3g}  "
              f"delta {row['delta'] if row['delta'] is not None else float('nan'):7.4f}  eta {row['eta']:.3f}  "
              f"G {row['G'] if row['G'] is not None else float('nan'):7.3f}  -> E {row['E_after']:9.3g}  "
              f"({row['forward_s']} s + {row['bgdo_s']} s)", flush=True)
        for pth in (kf,):
            pth.unlink()
    title = (f"{args.scene} ({material}), {args.runs} runs, {args.forward_frames} forward frames, "
             f"n_grid {cfg['sim']['n_grid']}, max_substeps {cfg['sim']['max_substeps']}; "
             f"BGDO {cfg['bgdo']['variant']}/{cfg['bgdo']['scaling']}")
    plot(rows, band, out / "stress_vs_E.png", title)
    (out / "stress_vs_E.json").write_text(json.dumps({"args": vars(args), "band": band, "rows": rows}, indent=2))
    print(f"wrote {out / 'stress_vs_E.png'} and {out / 'stress_vs_E.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
