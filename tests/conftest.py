"""Shared test fixtures: paths to the repository and to ../shared data, and the tiny
workflow run that tests/test_workflow.py and tests/test_slurm.py both read (made once per
session: it is the suite's most expensive artifact after the benchmark)."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SPLATS = SHARED / "data" / "splats"
# the tiny configuration of the end-to-end runs (2000 gaussians, 16^3 grid, 16 frames, 128x128 video)
TINY_CONFIG = "tests/slurm/config.yaml"  # relative to a run folder (made by make_run_dir)
# workflow entries linked into a scratch run folder (results/, .snakemake/ and logs/ are its own)
WORKFLOW_ENTRIES = ("Snakefile", "workflow", "config", "src", "tests", "profiles")

# keep every cache inside the workspace (Taichi, torch extensions, HF)
os.environ.setdefault("PHYSGS_CACHE_DIR", str(REPO / ".cache"))
os.environ.setdefault("XDG_CACHE_HOME", str(REPO / ".cache" / "xdg"))
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


def _memoize_taichi_source_positions() -> None:
    """Taichi (1.7) turns every kernel's Python AST into its IR in each process, also when the
    offline cache holds the compiled kernel, and the suite builds many solvers: each time, for
    every AST node, ``ASTTransformerContext.get_pos_info`` formats the node's source position
    (file, line, the line and a caret line wrapped by textwrap) for Taichi's error messages
    and debug info. That formatting was about 40 % of the CPU time of the MPM tests (measured:
    tests/test_mpm_rigid_proxies.py head-on collision, user 39.3 s -> 24.5 s with this memo,
    22.6 s with the source memo below too),
    and 98 % of its calls repeat a position already formatted in the process. The result is a
    pure function of the source lines and positions it reads, which are the memo's key, so the
    strings (and every test result) are unchanged; only the suite's processes are affected
    (the stages' own processes keep Taichi as installed). PHYSGS_TEST_TI_MEMO=0 leaves Taichi
    as installed (A/B of the suite's time)."""
    if os.environ.get("PHYSGS_TEST_TI_MEMO", "1") == "0":
        return
    try:
        from taichi.lang.ast import ast_transformer_utils as U
    except ImportError:
        return
    ctx = getattr(U, "ASTTransformerContext", None)
    orig = getattr(ctx, "get_pos_info", None)
    if orig is None or getattr(orig, "_physgs_memo", False):
        return
    memo: dict = {}
    spans = ("For", "While", "FunctionDef", "If")  # get_pos_info shows these down to their body

    def get_pos_info(self, node):
        lineno, span = node.lineno, node.__class__.__name__ in spans
        end = max(node.body[0].lineno - 1, lineno) if span else node.end_lineno
        key = (self.file, self.lineno_offset, self.func.func.__name__, self.indent, lineno, node.end_lineno,
               node.col_offset, node.end_col_offset, span, tuple(self.src[lineno - 1:max(end, lineno)]))
        try:
            return memo[key]
        except KeyError:
            info = memo[key] = orig(self, node)
            return info

    get_pos_info._physgs_memo = True
    ctx.get_pos_info = get_pos_info
    # the same materialization reads each kernel function's source (inspect.getsourcelines:
    # tokenizes the file's block) every time; the suite does not edit source files while it
    # runs, so one read per function object serves them all (a copy each time: callers own it)
    from taichi.lang import kernel_impl as K

    read = getattr(K, "getsourcelines", None)
    if read is not None and not getattr(read, "_physgs_memo", False):
        sources: dict = {}

        def getsourcelines(obj):
            try:
                lines, start = sources[obj]
            except (KeyError, TypeError):
                lines, start = read(obj)
                try:
                    sources[obj] = (lines, start)
                except TypeError:  # unhashable: not kept
                    pass
            return list(lines), start

        getsourcelines._physgs_memo = True
        K.getsourcelines = getsourcelines


_memoize_taichi_source_positions()


# Parallel runs (the README's command runs the suite in 2 pytest-xdist workers, --dist loadgroup):
# each test file is one group, so a file's module fixtures and compiled Taichi kernels serve
# all its tests in one worker; the files reading the tiny bear run share one group (the run is
# made once). Groups start heaviest first (most of their time is compiling Taichi kernels), so
# the two workers finish together instead of one waiting on a slow file collected last.
# Two details make this hold (before, neither did and every test was scheduled on its own: the
# tiny bear run was made in both workers and most files' kernels compiled in both):
# - xdist's worker reads the xdist_group marks in its own pytest_collection_modifyitems (it
#   appends "@<group>" to each node id); this conftest is registered before that plugin, so
#   without tryfirst its marks came after xdist had looked;
# - loadgroup by default reorders groups by their number of tests (--loadscope-reorder),
#   which puts many quick tests first; pytest_configure turns that off here so the order below
#   is the order the groups start in.
SHARED_GROUPS = {"test_slurm.py": "tiny_bear", "test_workflow.py": "tiny_bear"}
# heaviest first, from worker-seconds of each group in full runs of the suite on the 2-core
# machine (the order matters little once the heavy groups lead: measured with a cold Taichi
# cache, as CI starts, the two workers ended 3 s apart); the rest follow in file order
HEAVY_FIRST = ("test_mpm_rigid.py", "test_mpm_materials.py", "tiny_bear", "test_benchmark.py", "test_validation.py",
               "test_mpm_solver.py", "test_mpm_p2g.py", "test_mpm_rigid_proxies.py", "test_robustness.py",
               "test_bgdo.py", "test_mpm_dynamics.py", "test_builtin_scenes.py", "test_build_wheelhouse.py",
               "test_metrics_videophy2.py", "test_metrics.py", "test_worker.py", "test_smk_server.py",
               "test_region.py", "test_mpm_rest.py")


def pytest_configure(config):
    if hasattr(config.option, "loadscopereorder"):  # pytest-xdist present
        config.option.loadscopereorder = False


def group_of(item) -> str:
    name = item.path.name
    return SHARED_GROUPS.get(name, name)


@pytest.hookimpl(tryfirst=True)  # before xdist's worker turns the marks into "@<group>" node ids
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(group_of(item)))
    rank = {g: i for i, g in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda it: rank.get(group_of(it), len(rank)))  # stable: file order kept within a rank


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def splats_dir() -> Path:
    if not SPLATS.exists():
        pytest.skip(f"shared splat data not found at {SPLATS}")
    return SPLATS


def make_run_dir(path: Path) -> Path:
    """A scratch working folder whose workflow files are links to the repository's."""
    path.mkdir(parents=True, exist_ok=True)
    for name in WORKFLOW_ENTRIES:
        (path / name).symlink_to(REPO / name)
    return path


@pytest.fixture(scope="session")
def tiny_bear_run(tmp_path_factory) -> Path:
    """``snakemake --cores 2 results/bear/stage_report.tsv --configfile tests/slurm/config.yaml``
    in a scratch folder, once per session: every stage of the tiny bear, its metrics and stage
    report. Its stages run in the warm stage worker (worker.py), as on a GPU machine; the
    worker outlives the run, so the fixture stops it. Its results/ are read, never written, by test_workflow.py (outputs, what a
    config change re-runs: dry runs) and test_slurm.py (the local run that the SLURM run must
    match)."""
    d = make_run_dir(tmp_path_factory.mktemp("tiny_bear"))
    env = dict(os.environ, PHYSGS_WORKER="1", PHYSGS_WORKER_DIR=str(d / ".worker"))
    p = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "results/bear/stage_report.tsv",
                        "--configfile", TINY_CONFIG], cwd=d, capture_output=True, text=True, timeout=600,
                       stdin=subprocess.DEVNULL, env=env)
    out = p.stdout + p.stderr
    assert p.returncode == 0, f"the tiny bear run failed:\n{out[-6000:]}"
    assert "in the warm worker" in out and "the warm stage worker (pid" in out, out[-3000:]
    assert re.search(r"\] (prepare|cluster|fill): .* in the warm worker", out), out[-3000:]
    # the worker outlives the run (worker.idle_seconds): it served every job; stop it here
    from physgs_steps import worker as W

    socks = list((d / ".worker").glob("*.sock"))
    assert len(socks) == 1
    info = W.ping(socks[0])
    assert info and info["jobs"] >= 8 and info["rss_mb"] > 0, info
    assert W.shutdown(socks[0]) and not socks[0].exists()
    return d
