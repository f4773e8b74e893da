"""Why does a warm worker simulate slower in its second run? (issue 18)

Runs one simulation stage of a target several times in ONE process, as the warm stage worker
(src/physgs_steps/worker.py) does, and between the rounds does what the worker's other jobs do
to the process: start torch's CUDA, run bgdo_update (torch work), run render (gsplat), and
finally collect garbage and freeze it.  Each run prints its substeps, the frames held at rest,
its substep seconds and the milliseconds per substep, the GPU's SM clock after the run, and the
same stage's stats as the pipeline benchmark reads them, so a slower second run shows whether
it did more substeps (rest detected later, other dt) or the same substeps slower (and after
what).

    python benchmarks/bench_worker_repeat.py bear --runs 3            # default bear, forward_sim
    python benchmarks/bench_worker_repeat.py bear --n-gaussians 300000 --stage final_sim --json out.json

The scratch folder is made like ``physgs bench pipeline``'s (pipeline_bench.make_workdir); the
chain up to the stage runs first, once, in this process.
"""
from __future__ import annotations

import argparse
import gc
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from physgs_steps import pipeline_bench as PB  # noqa: E402


def _sm_clock() -> int | None:
    if not shutil.which("nvidia-smi"):
        return None
    r = subprocess.run(["nvidia-smi", "--id=0", "--query-gpu=clocks.sm", "--format=csv,noheader,nounits"],
                       capture_output=True, text=True)
    try:
        return int(r.stdout.strip().splitlines()[0])
    except (ValueError, IndexError):
        return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("target", nargs="?", default="bear")
    ap.add_argument("--n-gaussians", type=int, default=None)
    ap.add_argument("--set", action="append", help="config override key=value, repeatable")
    ap.add_argument("--config", default=None)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--stage", default="forward_sim", choices=("forward_sim", "final_sim"))
    ap.add_argument("--runs", type=int, default=3, help="runs of the stage after each step")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)

    import os

    wd = PB.make_workdir(Path(a.workdir or tempfile.mkdtemp(prefix="physgs-repeat-")), a.target.split("/")[0],
                         a.n_gaussians, PB.parse_sets(a.set), a.config)
    os.chdir(wd)
    from physgs_steps.cli import _stage_fn, stage_io
    from physgs_steps.runtime import run_stage

    plan = PB._plan("config.yaml", a.target)
    jobs = plan.jobs()

    def run(name, step):
        ins, outs, scfg = stage_io(plan, name, step)
        return run_stage(name, _stage_fn(name), ins, outs, scfg, None)

    # the chain up to (and with) the stage's first job, so every input exists
    first = next(i for i, j in enumerate(jobs) if j[0] == a.stage)
    t0 = time.perf_counter()
    for name, step in jobs[:first]:
        run(name, step)
    print(f"chain before {a.stage}: {time.perf_counter() - t0:.2f} s", flush=True)
    step = jobs[first][1]
    rows = []

    def rounds(label):
        for i in range(a.runs):
            t = time.perf_counter()
            res = run(a.stage, step)
            wall = time.perf_counter() - t
            st = PB._sim_stats(wd, plan, a.stage, step)
            n, sim = st.get("substeps_total"), st.get("simulate_seconds")
            row = {"after": label, "run": i, "wall": round(wall, 3), "simulate_seconds": sim, "substeps": n,
                   "held_frames": st.get("held_frames"), "ms_per_substep": round(1e3 * sim / n, 4) if n else None,
                   "first_substep": (res.get("timings") or {}).get("first_substep"), "sm_clock_mhz": _sm_clock()}
            rows.append(row)
            print(f"after {label:22s} run {i}: {row['substeps']} substeps ({row['held_frames']} frames held) in "
                  f"{sim} s = {row['ms_per_substep']} ms each; stage {wall:.2f} s; SM clock {row['sm_clock_mhz']} MHz",
                  flush=True)
            gc.collect()

    rounds("chain start" + (" (torch loaded)" if "torch" in sys.modules else " (no torch loaded)"))
    rest = [j for j in jobs[first + 1:] if j[0] not in ("metrics", "stage_report")]

    def rest_of_chain():
        for name, st in rest:
            t = time.perf_counter()
            run(name, st)
            print(f"  {name} {st or ''}: {time.perf_counter() - t:.2f} s", flush=True)

    steps = [("torch CUDA start", "import torch\nif torch.cuda.is_available():\n    torch.zeros(1, device='cuda')\n"
                                  "    torch.cuda.synchronize()"),
             ("rest of the chain", rest_of_chain),
             ("gc.collect + gc.freeze", "gc.collect(); gc.freeze()")]
    for label, what in steps:
        try:
            exec(what, {"gc": gc}) if isinstance(what, str) else what()
        except Exception as e:  # e.g. render without gsplat: say so, go on
            print(f"{label}: failed ({type(e).__name__}: {e}); continuing", flush=True)
            label += " (failed)"
        rounds(label)
    if a.json:
        Path(a.json).write_text(json.dumps({"target": a.target, "n_gaussians": a.n_gaussians, "stage": a.stage,
                                            "device": PB._device(), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
