"""Measure a "before" snapshot of the validation suite (the before column of the fixes table).

Runs chosen validation runs and sweep pairs through whatever solver is importable and writes
them in the format of results/validation/records.json.  To measure an older commit, export
its tree, copy this checkout's ``src/physgs_steps/validation`` into it and point PYTHONPATH at
it (the cases use only the solver's public API):

    git archive abd8117 | tar -x -C /tmp/base
    cp -r src/physgs_steps/validation /tmp/base/src/physgs_steps/
    cd /tmp/base && PYTHONPATH=/tmp/base/src python /path/to/benchmarks/validation_snapshot.py \
        --label "main before #14 (abd8117)" --commit abd8117e20b377db371987d31061b51623b39745 \
        --out before.json --settings g16-p8-c0.5 --cases free_fall rigid_rotation axial_vibration dam_break \
        --extra free_fall/main/g32-p8-c0.5 column_collapse/a0.5/g32-p8-c0.5 column_collapse/a1/g32-p8-c0.5 \
                column_collapse/a2/g32-p8-c0.5 column_collapse/a3/g32-p8-c0.5 dam_break/main/g32-p8-c0.5 \
                dam_break/main/g64-p8-c0.5 column_collapse/a2/g48-p8-c0.5 --sweep smoke

(this is how ``src/physgs_steps/validation/data/before.json`` was made).  Prints one line per run; nothing is asserted.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--label", required=True)
    ap.add_argument("--settings", nargs="+", default=["g16-p8-c0.5", "g32-p8-c0.5"])
    ap.add_argument("--extra", nargs="*", default=[], help="extra runs case/variant/setting")
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--sweep", choices=["none", "smoke", "cpu"], default="none")
    ap.add_argument("--commit", default=None, help="the commit measured (default: this checkout's HEAD)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from physgs_steps import reporting as R
    from physgs_steps.validation import sweep as S
    from physgs_steps.validation.base import Setting
    from physgs_steps.validation.cases import CASES
    from physgs_steps.validation.report import snapshot

    todo = [(c, v, s) for c in (a.cases or CASES) for s in a.settings for v in CASES[c].variants]
    todo += [tuple(e.split("/")) for e in a.extra]
    records = []
    for c, v, s in todo:
        t = time.perf_counter()
        rec = CASES[c].run(v, Setting.parse(s)).as_dict()
        rec.pop("series", None)
        records.append(rec)
        print(f"{c} {v} {s}: error {rec['error']}, {rec['sim_seconds']:.2f} s sim, {time.perf_counter() - t:.0f} s wall",
              flush=True)
    sweeps = []
    if a.sweep != "none":
        for el, pl in S.pairs(a.sweep):
            r = S.run_pair(el, pl, a.sweep)
            sweeps.append(r)
            print(f"sweep {r['pair']}: {r['counts']}", flush=True)
    prov = R.provenance()
    if a.commit:
        prov["commit"] = a.commit
        prov["dirty"] = False
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(snapshot(records, sweeps, a.label, prov), indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
