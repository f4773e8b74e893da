"""BGDO robustness study (paper Sec. 5.3 "W/o BGDO"): start built-in scenes from corrupted
Young's moduli and let BGDO correct them.

    python benchmarks/bgdo_robustness.py [--scenes bear] [--E0 3e10 3e8 30 kb] [--iterations 2]
        [--n-gaussians 6000] [--frames 90] [--forward-frames 90] [--bgdo KEY=VALUE ...] [--sim KEY=VALUE ...]
        [--no-baseline] [--out benchmarks/out/bgdo_robustness]

For every scene the library stages prepare -> cluster -> fill -> vlm_params run once (prior
backend, no network). Then for every E0 every instance's E is set to E0 (``kb``: each
instance keeps the knowledge-base E of the material stage, the workflow's own start) and the chain
forward_sim -> bgdo_update (x iterations) -> final_sim runs through the same stage functions
the workflow calls (physgs_steps.simulate.run_forward / run_final, physgs_steps.bgdo.run).
"Without BGDO" (--no-baseline to skip) runs final_sim at E0 directly.

Printed per instance: the material's plausible band (E_range of the knowledge base), E0 -> E1
-> E2, whether the last E lies in the band, whether the final simulation is stable, the mean
deformation at its last frame (||F - I||_F, and ||F - R|| = ||sigma - 1|| without the rotation),
the mean displacement of the visible gaussians, and seconds per stage. Everything is also
written to <out>/robustness.json. Sizes are small by default so that it runs on a CPU.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]


def _logger() -> logging.Logger:
    log = logging.getLogger("bgdo_robustness")
    log.handlers[:] = [logging.NullHandler()]
    log.propagate = False
    return log


def _parse_value(v: str):
    try:
        return yaml.safe_load(v)
    except yaml.YAMLError:
        return v


def _parse_e0(v: str):
    if v == "kb":
        return v
    try:
        return float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--E0 takes numbers (Pa) or kb, got {v!r}") from None


def make_config(args, scenes_dir: Path) -> dict:
    from physgs_steps import config as C

    cfg = C.load_config()
    cfg["scenes_dir"] = str(scenes_dir)
    cfg["device"] = args.device
    cfg.setdefault("sim", {})["n_frames"] = args.frames
    b = cfg.setdefault("bgdo", {})
    b["iterations"] = args.iterations
    b["forward_frames"] = args.forward_frames
    for kv in args.bgdo:
        key, _, val = kv.partition("=")
        b[key] = _parse_value(val)
    for kv in getattr(args, "sim", []):
        key, _, val = kv.partition("=")
        cfg["sim"][key] = _parse_value(val)
    return C.validate_config(cfg, "bgdo_robustness")


def write_scenes(names: list[str], n_gaussians: int, dest: Path) -> None:
    """Copies of the scene files with a smaller built-in gaussian count."""
    for name in names:
        src = REPO / "config" / "scenes" / f"{name}.yaml"
        data = yaml.safe_load(src.read_text())
        if str(data.get("source", "")).startswith("builtin:"):
            data.setdefault("builtin", {})["n_gaussians"] = n_gaussians
        (dest / f"{name}.yaml").write_text(yaml.safe_dump(data, sort_keys=False))


def prepare_scene(plan, log) -> dict:
    """prepare -> cluster -> fill -> vlm_params; returns seconds per stage."""
    from physgs_steps import cli

    secs = {}
    for name in ("prepare", "cluster", "fill", "vlm_params"):
        ins, outs, scfg = cli.stage_io(plan, name)
        if all(Path(o).exists() for o in outs.values()):
            continue
        t0 = time.perf_counter()
        cli._stage_fn(name)(ins, outs, scfg, log)
        secs[name] = round(time.perf_counter() - t0, 2)
    return secs


def final_metrics(path: str, particles: str) -> list[dict]:
    """Per instance: deformation and motion of its visible gaussians in final.h5 at the last frame."""
    import h5py

    with h5py.File(particles, "r") as f:
        label_all = f["label"][...]
    with h5py.File(path, "r") as f:
        rows = f["gaussian_index"][...]
        x0, x1 = f["x"][0].astype(np.float64), f["x"][-1].astype(np.float64)
        F = f["F"][-1].astype(np.float64)
    label = label_all[rows]
    sig = np.linalg.svd(F, compute_uv=False)
    J = np.linalg.det(F)
    dF = np.linalg.norm((F - np.eye(3)).reshape(len(F), -1), axis=1)
    st = np.linalg.norm(sig - 1.0, axis=1)
    disp = np.linalg.norm(x1 - x0, axis=1)
    out = []
    for k in range(int(label.max()) + 1):
        m = label == k
        out.append({"label": k, "n": int(m.sum()), "mean_F_minus_I": float(dF[m].mean()) if m.any() else None,
                    "mean_stretch": float(st[m].mean()) if m.any() else None,
                    "J_min": float(J[m].min()) if m.any() else None,
                    "mean_displacement": float(disp[m].mean()) if m.any() else None})
    return out


def _start_params(plan, E0):
    """params_0 with every E set to E0 (a number), or as the material stage wrote it ("kb")."""
    from physgs_steps.runtime import read_json

    p0 = read_json(plan.path("params0"))
    if E0 != "kb":
        for inst in p0["instances"]:
            inst["E"] = float(E0)
            inst["provenance"] = {"source": "corrupted", "E0": float(E0), "previous": inst.get("provenance")}
    return p0


def _e0_name(E0) -> str:
    return "kb" if E0 == "kb" else f"{float(E0):g}"


def run_case(plan, E0, args, log, root: Path) -> dict:
    """One start (corrupted E0 or "kb"): forward/bgdo iterations then the final simulation."""
    from physgs_steps import bgdo, simulate
    from physgs_steps.runtime import peak_rss_mb, read_json, write_json

    d = root / plan.scene / f"E0_{_e0_name(E0)}"
    d.mkdir(parents=True, exist_ok=True)
    p0 = _start_params(plan, E0)
    write_json(d / "params0.json", p0)
    particles = plan.path("particles")
    Es = [[float(i["E"]) for i in p0["instances"]]]
    secs, fwd, rules = {}, [], []
    for it in range(args.iterations):
        t0 = time.perf_counter()
        r = simulate.run_forward({"particles": particles, "params": str(d / f"params{it}.json")},
                                 {"keyframes": str(d / f"forward{it}.h5")}, plan.cfgs["sim"], log)
        secs[f"forward{it}"] = round(time.perf_counter() - t0, 2)
        fwd.append({"stable": r["stable"], "key_frames": r["key_frames"]})
        t0 = time.perf_counter()
        bgdo.run({"keyframes": str(d / f"forward{it}.h5"), "params": str(d / f"params{it}.json")},
                 {"params": str(d / f"params{it + 1}.json")}, plan.cfgs["bgdo"], log)
        secs[f"bgdo{it + 1}"] = round(time.perf_counter() - t0, 2)
        pj = read_json(d / f"params{it + 1}.json")
        Es.append([i["E"] for i in pj["instances"]])
        rules.append([f"{r.get('fate')}: {r.get('rule')}" + (" (ceiling)" if r.get("capped_by_ceiling") else "")
                      for r in pj["bgdo"]["instances"]])
    final = run_final(plan, str(d / f"params{args.iterations}.json"), str(d / "final.h5"), log)
    secs["final"] = final.pop("seconds")
    last = read_json(d / f"params{args.iterations}.json")
    records = (last.get("bgdo") or {}).get("instances") or []
    return {"E0": E0, "E": Es, "rules": rules, "forward": fwd, "final": final, "seconds": secs, "peak_rss_mb": round(peak_rss_mb(), 1),
            "bgdo_last": [{k: r.get(k) for k in ("G", "eta", "E_hat", "reference_pressure", "delta_target", "ceiling",
                                                 "static_stress", "clipped", "capped_by_ceiling")} for r in records],
            "instances": [{"label": int(i["label"]), "name": i.get("name"), "material": i.get("material")}
                          for i in last["instances"]]}


def run_final(plan, params: str, out: str, log) -> dict:
    from physgs_steps import simulate
    from physgs_steps.errors import SimulationError

    t0 = time.perf_counter()
    try:
        simulate.run_final({"particles": plan.path("particles"), "params": params}, {"frames": out}, plan.cfgs["sim"], log)
        res = {"stable": True, "instances": final_metrics(out, plan.path("particles"))}
    except SimulationError as e:
        res = {"stable": False, "error": str(e)[:300]}
    res["seconds"] = round(time.perf_counter() - t0, 2)
    return res


def baseline(plan, E0, log, root: Path) -> dict:
    """Without BGDO: the final simulation straight from E0."""
    from physgs_steps.runtime import write_json

    d = root / plan.scene / f"E0_{_e0_name(E0)}"
    d.mkdir(parents=True, exist_ok=True)
    p0 = _start_params(plan, E0)
    write_json(d / "params_nobgdo.json", p0)
    return run_final(plan, str(d / "params_nobgdo.json"), str(d / "final_nobgdo.h5"), log)


def _bgdo_child(args) -> dict:
    """bgdo.run in a fresh process: resident memory before and (sampled every 5 ms) during the
    stage, in MiB. (ru_maxrss is not used: a spawned child inherits its parent's peak.)"""
    keyframes, params, out, cfg = args
    import threading

    import psutil
    import torch

    from physgs_steps import bgdo

    torch.set_num_threads(1)
    proc = psutil.Process()
    base = proc.memory_info().rss / 2**20
    peak = [base]
    done = threading.Event()

    def sample():
        while not done.is_set():
            peak[0] = max(peak[0], proc.memory_info().rss / 2**20)
            done.wait(0.005)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    t0 = time.perf_counter()
    bgdo.run({"keyframes": keyframes, "params": params}, {"params": out}, cfg, _logger())
    seconds = time.perf_counter() - t0
    done.set()
    th.join()
    peak[0] = max(peak[0], proc.memory_info().rss / 2**20)
    return {"seconds": round(seconds, 3), "rss_before_mb": round(base, 1), "peak_rss_mb": round(peak[0], 1),
            "bgdo_increment_mb": round(peak[0] - base, 1)}


def measure_memory(keyframes: str, params: str, cfg: dict) -> dict:
    """Peak memory of one bgdo_update in its own process, and the key-frame data it reads."""
    import multiprocessing as mp

    import h5py

    with h5py.File(keyframes, "r") as f:
        n_kf = len(f["keyframes"])
        P = int(f["particles/label"].shape[0])
    with mp.get_context("spawn").Pool(1) as pool:
        res = pool.map(_bgdo_child, [(keyframes, params, str(Path(keyframes).with_suffix(".mem.json")), cfg)])[0]
    res.update(particles=P, key_frames=n_kf, key_frame_mb=round(P * 24 * 4 / 2**20, 2),
               all_key_frames_mb=round(n_kf * P * 24 * 4 / 2**20, 2))
    return res


def band_of(material):
    from physgs_steps import materials_kb
    from physgs_steps.errors import ConfigError

    try:
        return materials_kb.get_material(material)["E_range"]
    except ConfigError:
        return None


def _short_rule(text: str) -> str:
    """'ok: signals' -> 'signals', 'exploded: min(E_cap, ...)' -> 'exploded->static', ..."""
    fate, _, rule = text.partition(": ")
    if rule.startswith("exploded"):
        short = "exploded->static" if "static" in rule else "exploded->E_cap"
    elif fate == "broken":
        short = "broken"
    else:
        short = rule.split(":")[0].replace(" (ceiling)", "")
    return short + (" (ceiling)" if "(ceiling)" in text else "")


def print_table(rows: list[dict], iterations: int) -> None:
    hdr = ["scene", "instance (material)", "band [Pa]", " -> ".join(f"E{i}" for i in range(iterations + 1)),
           "in band", "final", "|F-I| last", "|s-1| last", "J min", "disp", "w/o BGDO", "BGDO rule", "seconds"]
    lines = [hdr]
    for r in rows:
        case = r["case"]
        for k, inst in enumerate(case["instances"]):
            band = band_of(inst["material"])
            Es = [e[k] for e in case["E"]]
            inb = "n/a" if band is None else ("yes" if band[0] <= Es[-1] <= band[1] else "NO")
            fin = case["final"]
            fm = fin["instances"][inst["label"]] if fin["stable"] else {}
            base = r.get("baseline")
            lines.append([
                r["scene"], f"{inst['name']} ({inst['material']})",
                "n/a" if band is None else f"{band[0]:.0e}-{band[1]:.0e}",
                " -> ".join(f"{e:.3g}" for e in Es), inb,
                "stable" if fin["stable"] else "UNSTABLE",
                f"{fm['mean_F_minus_I']:.3f}" if fm else "-",
                f"{fm['mean_stretch']:.3f}" if fm else "-",
                f"{fm['J_min']:.3f}" if fm else "-",
                f"{fm['mean_displacement']:.3f}" if fm else "-",
                "-" if base is None else ("stable" if base["stable"] else "unstable"),
                ", ".join(_short_rule(it[k]) for it in case.get("rules", [])),
                " ".join(f"{s}={v:g}" for s, v in case["seconds"].items()),
            ])
    widths = [max(len(str(l[i])) for l in lines) for i in range(len(hdr))]
    for i, l in enumerate(lines):
        print("  ".join(str(c).ljust(w) for c, w in zip(l, widths)))
        if i == 0:
            print("  ".join("-" * w for w in widths))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["bear"])
    ap.add_argument("--E0", nargs="+", type=_parse_e0, default=[3e10, 3e8, 30.0],
                    help="start moduli in Pa, or kb for the material stage's own E")
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--n-gaussians", type=int, default=6000)
    ap.add_argument("--frames", type=int, default=90, help="frames of the final simulation (sim.n_frames)")
    ap.add_argument("--forward-frames", type=int, default=90, help="frames of each forward simulation")
    ap.add_argument("--bgdo", nargs="*", default=[], help="bgdo config overrides KEY=VALUE (YAML values)")
    ap.add_argument("--sim", nargs="*", default=[], help="sim config overrides KEY=VALUE (e.g. n_grid=64)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--no-baseline", action="store_true", help="skip the final simulation without BGDO")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 avoids oversubscription)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "out" / "bgdo_robustness"))
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from physgs_steps import plan as P

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    scenes_dir = Path(tempfile.mkdtemp(prefix="scenes_", dir=out))
    write_scenes(args.scenes, args.n_gaussians, scenes_dir)
    cfg = make_config(args, scenes_dir)
    os.chdir(out)  # the plan's paths (results/...) are relative
    log = _logger()
    rows = []
    for scene in args.scenes:
        plan = P.make_plan(cfg, scene)
        prep = prepare_scene(plan, log)
        for E0 in args.E0:
            t0 = time.perf_counter()
            case = run_case(plan, E0, args, log, out / "cases")
            base = None if args.no_baseline else baseline(plan, E0, log, out / "cases")
            rows.append({"scene": scene, "E0": E0, "case": case, "baseline": base, "prepare_seconds": prep,
                         "wall_seconds": round(time.perf_counter() - t0, 1)})
            print(f"[{scene} E0={_e0_name(E0)}] E: {case['E']}  final stable: {case['final']['stable']}  "
                  f"({rows[-1]['wall_seconds']} s)", flush=True)
    print()
    print(f"BGDO robustness: variant {cfg['bgdo']['variant']}, scaling {cfg['bgdo']['scaling']}, "
          f"deformation {cfg['bgdo']['deformation_measure']}, {args.iterations} iterations, "
          f"{args.n_gaussians} gaussians, n_grid {cfg['sim']['n_grid']}, {args.forward_frames} forward / "
          f"{args.frames} final frames at {cfg['sim']['fps']:g} fps, max_substeps {cfg['sim']['max_substeps']}")
    print_table(rows, args.iterations)
    mem = None
    for r in rows:  # memory of one BGDO update, from the first stable forward run with all its key frames
        d = out / "cases" / r["scene"] / f"E0_{_e0_name(r['E0'])}"
        for it in range(args.iterations):
            if r["case"]["forward"][it]["stable"]:
                plan = P.make_plan(cfg, r["scene"])
                mem = measure_memory(str(d / f"forward{it}.h5"), str(d / f"params{it}.json"), plan.cfgs["bgdo"])
                mem["case"] = f"{r['scene']} E0={_e0_name(r['E0'])} forward{it}"
                break
        if mem:
            break
    if mem:
        print(f"\nBGDO memory ({mem['case']}, {mem['particles']} particles, {mem['key_frames']} key frames of "
              f"{mem['key_frame_mb']} MiB each): peak RSS {mem['peak_rss_mb']} MiB in its own process, "
              f"{mem['bgdo_increment_mb']} MiB above the {mem['rss_before_mb']} MiB after imports; {mem['seconds']} s")
    (out / "robustness.json").write_text(json.dumps({"args": vars(args), "rows": rows, "memory": mem}, indent=2,
                                                    default=str))
    print(f"\nwrote {out / 'robustness.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
