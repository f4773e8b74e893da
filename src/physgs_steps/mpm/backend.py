"""Taichi start-up: one runtime per process, offline cache in the project.

``ensure_taichi("cpu" | "cuda" | "auto")`` initialises Taichi once (f32, offline cache in
``runtime.cache_dir("taichi")`` so a stage run twice does not recompile) and returns the arch
actually used.  ``auto`` takes CUDA when Taichi finds a CUDA device, else the CPU.  Asking
for another arch later re-initialises Taichi, which invalidates arrays of earlier solvers.
If some other code re-initialises Taichi, the next call notices and starts again.
"""
from __future__ import annotations

import logging
import os

import taichi as ti

from ..errors import ConfigError
from ..runtime import cache_dir

_state: dict = {"arch": None, "prog": None, "init_seconds": 0.0, "inits": 0}
_log = logging.getLogger("physgs.mpm")


def _current_prog():
    from taichi.lang import impl

    return impl.get_runtime().prog


def advanced_optimization() -> bool:
    """Taichi's ``advanced_optimization`` IR passes: off unless PHYSGS_TI_ADVANCED_OPT=1.

    Measured on the 2-core CPU (3 material pairs, grid 32, 6000 particles, cold offline cache):
    the first substep (compilation) took 49.8 s with the passes and 9.5 s without; 200
    substeps then took 2.13 and 2.12 s with the same sum of positions. Results agree to float
    rounding, not always bit for bit (docs/MEASURED.md, kernel compilation). LLVM still
    optimises the generated code; these passes mostly shorten the IR before it, which LLVM
    does as well.
    """
    return os.environ.get("PHYSGS_TI_ADVANCED_OPT", "0") == "1"


def _init(arch) -> str:
    import time

    t0 = time.perf_counter()
    extra = {}
    if os.environ.get("PHYSGS_TI_BLOCK_DIM"):  # threads per CUDA block of parallel loops (bench_mpm.py experiments)
        extra["default_gpu_block_dim"] = int(os.environ["PHYSGS_TI_BLOCK_DIM"])
    ti.init(arch=arch, default_fp=ti.f32, default_ip=ti.i32, offline_cache=True,
            offline_cache_file_path=str(cache_dir("taichi")), log_level=ti.WARN,
            cpu_max_num_threads=os.cpu_count() or 1, advanced_optimization=advanced_optimization(),
            kernel_profiler=os.environ.get("PHYSGS_TI_PROFILER") == "1", **extra)  # bench_mpm.py --profile
    from taichi.lang import impl

    got = impl.current_cfg().arch
    name = "cuda" if got == ti.cuda else "cpu"
    _state.update(arch=name, prog=_current_prog(), init_seconds=time.perf_counter() - t0, inits=_state["inits"] + 1)
    from . import kernels

    kernels.build.cache_clear()
    kernels.build_constitutive.cache_clear()
    return name


def ensure_taichi(backend: str = "cpu") -> str:
    """Initialise Taichi for ``backend`` (cpu | cuda | auto) if needed; return "cpu" or "cuda".

    Raises:
        ConfigError(sim.backend) when CUDA is requested but not available.
    """
    if backend not in ("cpu", "cuda", "auto"):
        raise ConfigError("sim.backend", f"must be cpu, cuda or auto, got {backend!r}")
    alive = _state["prog"] is not None and _current_prog() is _state["prog"]
    if alive and (backend == "auto" or backend == _state["arch"]):
        return _state["arch"]
    if backend == "cpu":
        return _init(ti.cpu)
    name = _init(ti.cuda) if _cuda_built() else _init(ti.cpu)
    if backend == "cuda" and name != "cuda":
        raise ConfigError("sim.backend", "is 'cuda' but Taichi found no usable CUDA device; use 'cpu' or 'auto'")
    if backend == "auto":
        _log.info("Taichi backend auto -> %s", name)
    return name


def _cuda_built() -> bool:
    try:
        return bool(ti._lib.core.with_cuda())
    except AttributeError:  # pragma: no cover - very old/new Taichi
        return True


def counters() -> dict:
    """Start-up figures of this process's Taichi: ``inits`` (ti.init calls made here),
    ``init_seconds`` (the last one's), ``kernels`` (compiled kernel instances of the live
    runtime: each is compiled, or loaded from the offline cache and code-generated, once per
    process; a stage's increase is what it paid for)."""
    kernels = 0
    try:
        from taichi.lang import impl

        kernels = sum(len(getattr(k, "compiled_kernels", ())) for k in impl.get_runtime().kernels)
    except Exception:  # pragma: no cover - Taichi internals moved
        kernels = None
    return {"inits": _state["inits"], "init_seconds": _state["init_seconds"], "kernels": kernels}


def current_arch() -> str | None:
    """The arch of the live runtime started here, or None."""
    alive = _state["prog"] is not None and _current_prog() is _state["prog"]
    return _state["arch"] if alive else None


def fast_launch_enabled() -> bool:
    """Whether :class:`Launcher` skips Taichi's per-call argument processing (on unless
    PHYSGS_TI_FAST_LAUNCH=0)."""
    return os.environ.get("PHYSGS_TI_FAST_LAUNCH", "1") != "0"


class Launcher:
    """Calls one Taichi kernel whose array arguments rarely change, without Taichi's per-call
    argument processing.

    A Taichi 1.7 kernel call in Python works out the compiled instance from every argument
    (type, dtype, dimensions, layout: ``TaichiCallableTemplateMapper.lookup``) and checks each
    argument against its annotation before the launch, about 15-20 us per ndarray argument on
    the 2-core CPU machine: the MPM substep's four kernels (substep, rigid reduce, advance,
    scatter) take 80 arguments, about 1.3 ms of an 8.5 ms duck_stone substep.  A Launcher makes
    the first call (and any call whose arrays are not the same objects, or whose template
    arguments differ, as before) through Taichi, keeps the compiled instance Taichi chose and
    the argument slots, and afterwards only builds the launch context: the arrays' handles, the
    scalars, the launch.  The compiled code and the arguments it gets are the same, so results
    are bitwise those of the plain call (tests/test_mpm_solver.py).  ``PHYSGS_TI_FAST_LAUNCH=0``
    turns it off; on any Taichi without the internals it uses, it falls back to the plain call.
    """

    def __init__(self, kernel):
        self.kernel = kernel
        self._plan = None  # (arrays, templates, compiled kernel, ndarray slots, scalar setters)
        self._broken = False

    def __call__(self, *args):
        plan = self._plan
        if plan is not None:
            arrays, templates, t_kernel, nd_slots, sc_slots = plan
            same = True
            for i, a in arrays:
                if args[i] is not a:
                    same = False
                    break
            if same:
                for i, val in templates:
                    if args[i] != val:
                        same = False
                        break
            if same:
                ctx = t_kernel.make_launch_context()
                for i, idx, arr in nd_slots:
                    ctx.set_arg_ndarray(idx, arr)
                for i, idx, kind in sc_slots:
                    v = args[i]
                    if kind == 0:
                        ctx.set_arg_float(idx, float(v))
                    elif kind == 1:
                        ctx.set_arg_int(idx, int(v))
                    else:
                        ctx.set_arg_uint(idx, int(v))
                prog = _current_prog()
                prog.launch_kernel(prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel), ctx)
                return None
        out = self.kernel(*args)
        if not self._broken and fast_launch_enabled():
            try:
                self._plan = self._make_plan(args)
            except Exception:  # pragma: no cover - Taichi internals moved: plain calls from now on
                self._plan, self._broken = None, True
        return out

    def _make_plan(self, args):
        from taichi.lang import _ndarray
        from taichi.lang.enums import AutodiffMode
        from taichi.lang.util import cook_dtype
        from taichi.types import ndarray_type, primitive_types, template
        from taichi.types.utils import is_signed

        primal = self.kernel._primal
        if primal.return_type is not None or primal.autodiff_mode != AutodiffMode.NONE:
            return None
        key = primal.ensure_compiled(*args)
        t_kernel = primal.compiled_kernels[key]
        arrays, templates, nd_slots, sc_slots = [], [], [], []
        n_templates = 0
        for i, (val, arg) in enumerate(zip(args, primal.arguments)):
            need = arg.annotation
            if isinstance(need, template):
                n_templates += 1
                templates.append((i, val))
                continue
            idx = (i - n_templates,)
            if isinstance(need, ndarray_type.NdarrayType) and isinstance(val, _ndarray.Ndarray):
                if val.grad is not None:
                    return None
                arrays.append((i, val))
                nd_slots.append((i, idx, val.arr))
            elif id(need) in primitive_types.real_type_ids and isinstance(val, (float, int)):
                sc_slots.append((i, idx, 0))
            elif id(need) in primitive_types.integer_type_ids and isinstance(val, int):
                sc_slots.append((i, idx, 1 if is_signed(cook_dtype(need)) else 2))
            else:
                return None  # an argument kind the fast path does not handle: plain calls
        return tuple(arrays), tuple(templates), t_kernel, tuple(nd_slots), tuple(sc_slots)
