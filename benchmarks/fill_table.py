"""Compare the filling methods on every built-in scene and print a markdown table.

    python benchmarks/fill_table.py [--scenes bear basket_mat ...] [--n-grid 32] [--out DIR]

For each scene (config/scenes/<name>.yaml, its `builtin` options and its `config:` overrides
of the prepare / cluster / fill sections) the prepare and cluster stages run once, then the
fill stage with each method; the figures come from its fill_report.json:

* precision: share of filled particles inside the true solid of their own instance;
* recall: share of the true solids' volume covered by particles (filled + gaussians) within
  dx/2; "gauss only" is the same with the gaussians alone (no filling);
* leakage: filled particles inside the regions that must stay empty (basket_hollow, gap),
  with the share of the region's volume they cover in brackets;
* seconds: the fill stage without the ground-truth evaluation.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = ["bear", "bear_can", "duck_stone", "ficus", "basket_mat", "bread"]
METHODS = [
    ("IPF+MCIS (paper)", {"method": "ipf", "occupancy": "hull", "mcis": True}),
    ("IPF w/o MCIS", {"method": "ipf", "occupancy": "hull", "mcis": False}),
    ("surface-following", {"method": "ipf", "occupancy": "surface", "mcis": False}),
    ("global (PhysGaussian)", {"method": "global", "mcis": False}),
]


def _log() -> logging.Logger:
    log = logging.getLogger("fill_table")
    log.handlers[:] = [logging.NullHandler()]
    log.propagate = False
    return log


def _section(name: str, scene: dict, extra: dict | None = None) -> dict:
    from physgs_steps import config

    merged = config.deep_merge((scene.get("config") or {}).get(name) or {}, extra or {})
    return config.validate(merged, config.load_schema(f"{name}.schema.yaml"), f"scene {scene.get('_name')}", name)


def run_scene(name: str, root: Path, n_grid: int) -> list[dict]:
    """prepare + cluster once, fill with every method; one record per method."""
    from physgs_steps import cluster, config, fill, prepare

    log = _log()
    scene = config.read_yaml(REPO / "config" / "scenes" / f"{name}.yaml")
    scene["_name"] = name
    d = root / name
    paths = {"scene": str(d / "scene.ply"), "transform": str(d / "transform.json"),
             "labels": str(d / "labels.npz"), "clusters": str(d / "clusters.json")}
    prepare.run({}, {"scene": paths["scene"], "transform": paths["transform"]},
                {"scene": scene, "prepare": _section("prepare", scene)}, log)
    cluster.run({"scene": paths["scene"]}, {"labels": paths["labels"], "clusters": paths["clusters"]},
                {"scene": scene, "cluster": _section("cluster", scene)}, log)
    k = json.loads(Path(paths["clusters"]).read_text())["n_instances"]
    out = []
    for label, over in METHODS:
        fcfg = _section("fill", scene, dict(over, n_grid=n_grid))
        tag = label.split()[0].lower().replace("+", "_")
        rep_path = d / f"fill_report_{tag}.json"
        fill.run({"scene": paths["scene"], "labels": paths["labels"], "transform": paths["transform"]},
                 {"particles": str(d / f"particles_{tag}.h5"), "report": str(rep_path)},
                 {"scene": scene, "fill": fcfg}, log)
        rep = json.loads(rep_path.read_text())
        out.append({"scene": name, "method": label, "k": k, "report": rep})
    return out


def _num(v, fmt="{:.3f}") -> str:
    return fmt.format(v) if isinstance(v, (int, float)) else "n/a"


def table(records: list[dict]) -> str:
    lines = ["| scene | K | method | filled | precision | recall | recall gauss only | leakage | seconds |",
             "|---|---:|---|---:|---:|---:|---:|---|---:|"]
    for r in records:
        rep = r["report"]
        ev = rep["evaluation"]
        leak = ", ".join(f"{k} {v['filled_inside']} ({_num(v['volume_covered'], '{:.0%}')})"
                         for k, v in sorted(ev["leakage"].items())) or "-"
        secs = rep["timings"]["fill"]["seconds"]
        lines.append(f"| {r['scene']} | {r['k']} | {r['method']} | {rep['n_filled']} | {_num(ev['precision'])} | "
                     f"{_num(ev['recall'])} | {_num(ev['recall_gaussians_only'])} | {leak} | {secs:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=SCENES)
    ap.add_argument("--n-grid", type=int, default=32, help="simulation grid resolution (sets dx)")
    ap.add_argument("--out", default=None, help="keep artifacts and write results.json here")
    a = ap.parse_args(argv)
    tmp = tempfile.TemporaryDirectory() if a.out is None else None
    root = Path(a.out or tmp.name)
    records = []
    for name in a.scenes:
        t0 = time.perf_counter()
        records += run_scene(name, root, a.n_grid)
        print(f"[{name}] done in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    print(f"\nn_grid {a.n_grid} (dx = {1 / a.n_grid:.4g}), 8 particles per cell target\n")
    print(table(records))
    if a.out:
        (root / "results.json").write_text(json.dumps(
            [{"scene": r["scene"], "method": r["method"], "evaluation": r["report"]["evaluation"],
              "n_filled": r["report"]["n_filled"], "timings": r["report"]["timings"]} for r in records], indent=1))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
