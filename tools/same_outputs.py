#!/usr/bin/env python3
"""Compare the stage outputs of two results folders, for changes that must not change them.

    python3 tools/same_outputs.py results_before/bear results_after/bear [--ignore-key KEY ...]

Every file under the first folder is compared with the file of the same relative path under
the second (``logs/`` and ``benchmarks/`` are left out: they hold times):

* ``.h5``: every dataset bit for bit (dtype, shape and bytes) and every attribute;
* ``.npz``: every array bit for bit, apart from the cluster stage's ``seconds`` and
  ``peak_alloc_mb``;
* ``.json``: equal after dropping the keys that hold times or memory (``timings``,
  ``seconds``, ``peak_alloc_mb``, ``process_peak_rss_mb``, ``peak_rss_mb`` and any
  ``--ignore-key``), at any depth;
* anything else: byte for byte.

Prints one line per difference and a summary; exits 1 when anything differs or is missing.
The fill speed-ups of issue 18 were checked with it (docs/MEASURED.md "Fixed costs, second round").
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

TIME_KEYS = {"timings", "seconds", "peak_alloc_mb", "process_peak_rss_mb", "peak_rss_mb"}
NPZ_TIME_KEYS = {"seconds", "peak_alloc_mb"}
SKIP_DIRS = {"logs", "benchmarks"}


def _strip(obj, keys: set):
    if isinstance(obj, dict):
        return {k: _strip(v, keys) for k, v in obj.items() if k not in keys}
    if isinstance(obj, list):
        return [_strip(v, keys) for v in obj]
    return obj


def _same_array(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype == object:
        return bool(np.all(a == b))
    return a.tobytes() == b.tobytes()


def _h5_items(path: Path) -> dict:
    import h5py

    out = {}
    with h5py.File(path, "r") as h:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[f"dataset {name}"] = obj[()]
            for k, v in obj.attrs.items():
                out[f"attribute {name}:{k}"] = v
        h.visititems(visit)
        for k, v in h.attrs.items():
            out[f"attribute /:{k}"] = v
    return out


def compare_files(a: Path, b: Path, ignore: set) -> list[str]:
    """Differences between file ``a`` and file ``b`` (empty when they agree)."""
    if a.suffix == ".h5":
        x, y = _h5_items(a), _h5_items(b)
        out = [f"{k} only in one file" for k in sorted(set(x) ^ set(y))]
        return out + [f"{k} differs" for k in sorted(set(x) & set(y)) if not _same_array(x[k], y[k])]
    if a.suffix == ".npz":
        with np.load(a, allow_pickle=False) as x, np.load(b, allow_pickle=False) as y:
            names = (set(x.files) | set(y.files)) - NPZ_TIME_KEYS
            return [f"array {k} differs" for k in sorted(names)
                    if k not in x.files or k not in y.files or not _same_array(x[k], y[k])]
    if a.suffix == ".json":
        keys = TIME_KEYS | ignore
        same = _strip(json.loads(a.read_text()), keys) == _strip(json.loads(b.read_text()), keys)
        return [] if same else ["JSON differs (times and memory left out)"]
    return [] if a.read_bytes() == b.read_bytes() else ["bytes differ"]


def compare_trees(before: Path, after: Path, ignore: set = frozenset()) -> tuple[int, list[str]]:
    """(files compared, differences as 'relative/path: what') of two results folders."""
    n, problems = 0, []
    for a in sorted(p for p in before.rglob("*") if p.is_file()):
        rel = a.relative_to(before)
        if SKIP_DIRS & set(rel.parts[:-1]):
            continue
        n += 1
        b = after / rel
        if not b.is_file():
            problems.append(f"{rel}: missing under {after}")
            continue
        problems += [f"{rel}: {d}" for d in compare_files(a, b, set(ignore))]
    return n, problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--ignore-key", action="append", default=[], help="a further JSON key to leave out")
    args = ap.parse_args(argv)
    for p in (args.before, args.after):
        if not p.is_dir():
            print(f"same_outputs: {p} is not a folder", file=sys.stderr)
            return 2
    n, problems = compare_trees(args.before, args.after, set(args.ignore_key))
    for line in problems:
        print(line)
    print(f"{n} files compared: {'all the same' if not problems else f'{len(problems)} differences'}")
    return 1 if problems or n == 0 else 0


if __name__ == "__main__":
    sys.exit(main())
