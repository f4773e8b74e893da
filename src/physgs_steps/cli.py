"""Command line: inspect the artifact plan and run single stages without Snakemake.

    physgs plan bear                      # ids, paths and stage configs of a target
    physgs stage fill bear                # run one stage of a target (inputs must exist)
    physgs stage forward_sim bear --step it0
    physgs stages bear                    # every stage of a target in order, in this process
    physgs plan benchmark/cpu/runs/bear/variants/baseline   # a benchmark run (README "Regenerating the benchmark")
    physgs check                          # every problem of the config and of every scene file
    physgs bench pipeline bear            # time the whole pipeline per structure (pipeline_bench.py)
    physgs snakemake --cores 1 results/bear/video.mp4   # snakemake through the warm server (smk_server.py)

Snakemake is the way to run the pipeline (caching, clusters); this is for debugging a stage
and for machines where only the library is installed (e.g. a GPU node for benchmarks).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# config, plan and runtime are imported where used: `physgs snakemake` must start in milliseconds

STAGES = ("prepare", "cluster", "fill", "vlm_params", "pinned_params", "forward_sim", "bgdo_update", "final_sim", "render", "metrics")


def _stage_fn(name: str):
    """The library function of a stage (imported now; see worker.ENTRIES)."""
    from .errors import PhysGSError
    from .worker import stage_function

    if name not in STAGES:
        raise PhysGSError(f"unknown stage '{name}'; stages: {', '.join(STAGES)}")
    return stage_function(name)


def stage_io(plan: "P.Plan", name: str, step: str | None = None) -> tuple[dict, dict, dict]:
    """(inputs, outputs, cfg) of one stage of a plan, as the Snakemake rules wire them."""
    from . import config as C
    from . import plan as P
    from .errors import PhysGSError

    p = plan.path
    if name == "prepare":
        kind, src = C.resolve_source(plan.cfgs["prepare"]["scene"])
        ins = {"source": str(src)} if kind == "file" else {}
        return ins, {"scene": p("scene"), "transform": p("transform")}, plan.cfgs["prepare"]
    if name == "cluster":
        return {"scene": p("scene")}, {"labels": p("labels"), "clusters": p("clusters")}, plan.cfgs["cluster"]
    if name == "fill":
        return ({"scene": p("scene"), "transform": p("transform"), "labels": p("labels")},
                {"particles": p("particles"), "carrier": p("carrier"), "report": p("fill_report")}, plan.cfgs["fill"])
    if name == "vlm_params":
        return ({"scene": p("scene"), "labels": p("labels"), "clusters": p("clusters")},
                {"params": p("params0")}, plan.cfgs["params"])
    if name == "pinned_params":
        return {"clusters": p("clusters")}, {"params": p("params0")}, plan.cfgs["params"]
    if name in ("forward_sim", "final_sim"):
        step = step or ("it0" if name == "forward_sim" else plan.steps[-1])
        out = {"keyframes": p("forward", step)} if name == "forward_sim" else {"frames": p("final")}
        ins = {"particles": p("particles"), "params": p("params", step)}
        if name == "final_sim":
            ins["transform"] = p("transform")
        return ins, out, plan.cfgs["sim"]
    if name == "bgdo_update":
        if step is None or step == "it0":
            raise PhysGSError("bgdo_update needs --step it<i>-<id> with i >= 1; the plan's steps: " + ", ".join(plan.steps))
        prev = P.previous_step(step)
        return ({"keyframes": p("forward", prev), "params": p("params", prev)},
                {"params": p("params", step)}, plan.cfgs["bgdo"])
    if name == "render":
        return ({"frames": p("final"), "scene": p("scene"), "transform": p("transform"), "carrier": p("carrier")},
                {"video": p("video"), "contact_sheet": p("contact_sheet"), "report": p("render_report")},
                plan.cfgs["render"])
    if name == "metrics":
        return ({"video": p("video"), "frames": p("final"), "params": p("params", plan.steps[-1])},
                {"metrics": p("metrics")}, plan.cfgs["metrics"])
    raise PhysGSError(f"unknown stage '{name}'")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["snakemake"]:  # every other argument is Snakemake's
        from .smk_server import main as smk_main

        return smk_main(argv[1:])
    from . import config as C
    from . import plan as P
    from .errors import PhysGSError
    from .runtime import run_stage, timed_stage_function, write_json

    ap = argparse.ArgumentParser(prog="physgs", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=None, help="global config file (default config/config.yaml)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    sp = sub.add_parser("plan", help="print the plan of a target")
    sp.add_argument("target")
    ss = sub.add_parser("stage", help="run one stage of a target")
    ss.add_argument("stage", choices=STAGES)
    ss.add_argument("target")
    ss.add_argument("--step", default=None)
    ss.add_argument("--summary", default=None, help="write the stage's seconds and memory to this JSON file")
    sj = sub.add_parser("jobs", help="print the (stage, step) jobs of a target in order, one per line")
    sj.add_argument("target")
    sa = sub.add_parser("stages", help="run every stage of a target in order (skips existing outputs unless --force)")
    sa.add_argument("target")
    sa.add_argument("--force", action="store_true")
    sa.add_argument("--summary", default=None, help="write per-stage seconds and memory to this JSON file "
                    "(rewritten after every stage)")
    sa.add_argument("--until", choices=STAGES, default=None,
                    help="stop after the last job of this stage (e.g. final_sim where nothing can render)")
    sub.add_parser("check", help="list every problem of the global config and of every scene file (exit 1 if any)")
    sb = sub.add_parser("bench", help="pipeline benchmarks (physgs bench pipeline|startup ...; see pipeline_bench.py)",
                        add_help=False)
    sb.add_argument("rest", nargs=argparse.REMAINDER)
    sub.add_parser("snakemake", help="run snakemake with these arguments through the warm Snakemake server "
                   "(no import of Snakemake per run; smk_server.py)", add_help=False)
    args = ap.parse_args(argv)
    if args.cmd == "check":
        return _check(args.config)
    if args.cmd == "bench":
        from .pipeline_bench import main as bench_main

        return bench_main(args.rest)
    try:
        cfg = C.load_config(args.config)
        plan = P.plan_for_target(cfg, args.target)
        if args.cmd == "plan":
            print(json.dumps({"target": plan.target, "ids": plan.ids, "steps": plan.steps,
                              "paths": {k: plan.path(k) for k in ("scene", "labels", "particles", "params0", "final", "video")},
                              "cfgs": plan.cfgs}, indent=2, default=str))
            return 0
        if args.cmd == "jobs":
            for name, step in plan.jobs():
                print(name, step or "")
            return 0
        jobs = [(args.stage, args.step)] if args.cmd == "stage" else [j for j in plan.jobs() if j[0] != "stage_report"]
        until = getattr(args, "until", None)
        if until:
            last = [i for i, j in enumerate(jobs) if j[0] == until]
            if not last:
                raise PhysGSError(f"--until {until}: target {args.target} has no {until} job")
            jobs = jobs[:last[-1] + 1]
        summary = []
        for name, step in jobs:
            ins, outs, scfg = stage_io(plan, name, step)
            if args.cmd == "stages" and not args.force and all(Path(o).exists() for o in outs.values()):
                continue
            log = str(Path(P.RESULTS) / plan.target / "logs" / f"{name}{'-' + step if step else ''}.cli.log")
            fn, imp = timed_stage_function(name, _stage_fn)
            res = run_stage(name, fn, ins, outs, scfg, log, import_seconds=imp)
            summary.append({"stage": name, "step": step, **{k: v for k, v in res.items() if isinstance(v, (int, float, str))}})
            if getattr(args, "summary", None):
                write_json(args.summary, summary)
        if getattr(args, "summary", None):
            write_json(args.summary, summary)
        return 0
    except PhysGSError as e:
        print(f"physgs: {e}", file=sys.stderr)
        return 1


def _check(config_path) -> int:
    from .check import check_all

    problems, n_files = check_all(config_path)
    for p in problems:
        print(p)
    files = len({p.file for p in problems})
    if problems:
        print(f"physgs check: {len(problems)} problem(s) in {files} file(s) ({n_files} scene files checked)",
              file=sys.stderr)
        return 1
    print(f"physgs check: no problems (global config and {n_files} scene files)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
