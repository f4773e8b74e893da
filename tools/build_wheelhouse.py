#!/usr/bin/env python3
"""Build an offline wheelhouse of physgs for air-gapped compute nodes.

Compute nodes of a cluster often have no internet access. Run this script on a machine that
has it (a login node, a laptop with Linux), copy the result to the cluster, and install with
``pip install --no-index --find-links <wheelhouse> ...`` (README.md, "Air-gapped nodes").

What it does:
1. builds the project itself as a wheel (pure Python, built here);
2. resolves the requirements (the project with the chosen extras, the build backend that an
   editable install needs, and any ``--requirement``) on this machine, allowing source
   distributions; every package that the index offers only as a source distribution is built
   here into a wheel, which must come out pure Python (``*-none-any.whl``), else the script
   stops and names it;
3. downloads binary wheels for the *target* (``--python-version``, ``--platform``) with
   ``pip download --only-binary=:all:``, the locally built wheels being offered through
   ``--find-links`` (pinned to the versions built);
4. writes ``manifest.json`` (target, files, sizes, sha256) and ``SHA256SUMS`` and, with
   ``--split-mb``, packs the wheels into tar parts of at most that size each.

``--dry-run`` resolves for the target (``pip install --dry-run --report``) and prints what
would be downloaded, without downloading binary wheels. Wheels already in ``--out`` are reused
(an interrupted download resumes); wheels there that this target does not need are left out of
the manifest and the parts.

Environment markers (``python_version < ...``) of step 2 are evaluated for the Python that runs
this script, so run it with the target's Python minor version where dependencies differ by
version (a warning says when they differ); step 3 always resolves for the target.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

from packaging.utils import canonicalize_name, parse_wheel_filename

REPO = Path(__file__).resolve().parents[1]
TAR_BLOCK = 512
TAR_RECORD = 10240  # tarfile's default record size: the end of an archive is padded to it


class WheelhouseError(Exception):
    """A wheelhouse cannot be built as asked (the message says why and what to do)."""


@dataclass
class Target:
    """The interpreter and platform the wheels are for."""

    python_version: str  # "3.11"
    platforms: list[str] = field(default_factory=list)  # pip platform tags; [] = this machine

    @property
    def abi(self) -> str:
        return "cp" + self.python_version.replace(".", "")

    def pip_args(self) -> list[str]:
        """pip options that restrict downloads to binary wheels for this target."""
        args = ["--only-binary=:all:", "--python-version", self.python_version,
                "--implementation", "cp", "--abi", self.abi, "--abi", "abi3", "--abi", "none"]
        for p in self.platforms:
            args += ["--platform", p]
        return args


def parse_python_version(text: str) -> str:
    parts = text.split(".")
    if len(parts) != 2 or not all(p.isdigit() for p in parts) or parts[0] != "3":
        raise WheelhouseError(f"--python-version must look like 3.11, got '{text}'")
    return text


def run_pip(args: list[str], log, capture: bool = False, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m pip ARGS``; raise WheelhouseError with pip's output on failure."""
    cmd = [sys.executable, "-m", "pip", *args]
    log(f"$ {' '.join(cmd)}")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        out = (proc.stdout + proc.stderr).strip().splitlines()
        raise WheelhouseError(f"pip {args[0]} failed (exit {proc.returncode}):\n" + "\n".join(out[-25:]))
    return proc


def copy_project(project: Path, dest: Path) -> Path:
    """Copy the files a wheel build needs, so that building leaves no build/ or egg-info in
    the source tree."""
    if not (project / "pyproject.toml").exists():
        raise WheelhouseError(f"{project}: no pyproject.toml (give the project folder with --project)")
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc", ".git", "build", "dist")
    dest.mkdir(parents=True)
    for entry in project.iterdir():
        keep = entry.name in ("pyproject.toml", "setup.py", "setup.cfg", "MANIFEST.in", "src") or \
            entry.name.upper().startswith(("README", "LICENSE", "LICENCE", "COPYING"))
        if not keep:
            continue
        if entry.is_dir():
            shutil.copytree(entry, dest / entry.name, ignore=ignore)
        else:
            shutil.copy2(entry, dest / entry.name)
    return dest


def build_project_wheel(project: Path, out: Path, pip_extra: list[str], log) -> Path:
    """Build the project's wheel into ``out``; it must be pure Python."""
    with tempfile.TemporaryDirectory(prefix="wheelhouse-src-") as tmp:
        src = copy_project(project, Path(tmp) / "project")
        before = set(out.glob("*.whl"))
        run_pip(["wheel", "--no-deps", "--wheel-dir", str(out), *pip_extra, str(src)], log)
    new = sorted(set(out.glob("*.whl")) - before)
    if len(new) != 1:
        raise WheelhouseError(f"building {project} gave {len(new)} wheels, expected 1")
    check_pure(new[0])
    return new[0]


def check_pure(wheel: Path) -> None:
    """Raise unless ``wheel`` runs on any platform (tag ``*-none-any``)."""
    _, _, _, tags = parse_wheel_filename(wheel.name)
    if not all(t.abi == "none" and t.platform == "any" for t in tags):
        raise WheelhouseError(
            f"{wheel.name} was built here but is not pure Python, so it would not run on the target; "
            "build the wheelhouse on a machine with the target's platform and Python, or add a binary "
            "wheel of it with --find-links")


def read_build_requires(project: Path) -> list[str]:
    """``[build-system] requires`` of the project (what pip needs to install it editable)."""
    import tomllib

    with open(project / "pyproject.toml", "rb") as f:
        data = tomllib.load(f)
    return list(data.get("build-system", {}).get("requires", []))


def host_resolution(reqs: list[str], pip_extra: list[str], workdir: Path, log) -> list[dict]:
    """Resolve ``reqs`` for this machine, source distributions allowed; pip's report items."""
    report = workdir / "host-report.json"
    run_pip(["install", "--dry-run", "--ignore-installed", "--quiet", "--report", str(report),
             *pip_extra, *reqs], log)
    return json.loads(report.read_text())["install"]


def is_sdist(item: dict) -> bool:
    url = item["download_info"]["url"]
    return not url.endswith(".whl") and "dir_info" not in item["download_info"]


def build_sdist_only(items: list[dict], out: Path, pip_extra: list[str], log) -> list[str]:
    """Build a wheel here for every item that resolved to a source distribution; return pins."""
    pins = []
    for item in items:
        if not is_sdist(item):
            continue
        name, version = item["metadata"]["name"], item["metadata"]["version"]
        before = set(out.glob("*.whl"))
        run_pip(["wheel", "--no-deps", "--wheel-dir", str(out), *pip_extra, f"{name}=={version}"], log)
        for w in sorted(set(out.glob("*.whl")) - before):
            check_pure(w)
        log(f"built {name}=={version} here (no wheel on the index)")
        pins.append(f"{name}=={version}")
    return pins


def target_resolution(reqs: list[str], target: Target, find_links: Path, constraints: Path,
                      pip_extra: list[str], workdir: Path, log) -> list[dict]:
    """Resolve for the target without downloading wheels (pip's --dry-run report)."""
    report = workdir / "target-report.json"
    run_pip(["install", "--dry-run", "--ignore-installed", "--quiet", "--report", str(report),
             "--target", str(workdir / "unused-target"), *target.pip_args(),
             "--find-links", str(find_links), "--constraint", str(constraints), *pip_extra, *reqs], log)
    return json.loads(report.read_text())["install"]


def download_for_target(reqs: list[str], target: Target, out: Path, constraints: Path,
                        pip_extra: list[str], log) -> None:
    run_pip(["download", "--dest", str(out), *target.pip_args(), "--find-links", str(out),
             "--constraint", str(constraints), *pip_extra, *reqs], log)


# ---------------------------------------------------------------------------- gsplat with CUDA code
ARCH_RE = re.compile(r"^\d+\.\d+a?(\+PTX)?$")


def parse_cuda_archs(text: str) -> str:
    """``"8.0;9.0"``, ``"8.6 9.0+PTX"`` or ``"8.0,9.0"`` -> ``"8.0;9.0"`` (TORCH_CUDA_ARCH_LIST form)."""
    archs = [a for a in re.split(r"[;,\s]+", text.strip()) if a]
    bad = [a for a in archs if not ARCH_RE.match(a)]
    if not archs or bad:
        raise WheelhouseError(f"--gsplat-cuda-arch takes compute capabilities like '8.0;9.0' or '8.6+PTX' "
                              f"(nvidia-smi --query-gpu=compute_cap on a node), got '{text}'")
    return ";".join(archs)


def cuda_build_host(target: Target, torch_pin: str | None) -> dict:
    """Check that this machine can compile gsplat's CUDA code for the target: the target's
    Python, a CUDA build of the target's torch, nvcc. Returns {torch, cuda, nvcc}."""
    host = f"{sys.version_info.major}.{sys.version_info.minor}"
    if host != target.python_version:
        raise WheelhouseError(f"gsplat's CUDA extension is built for the Python that builds it ({host}), the "
                              f"target is {target.python_version}: run this with python{target.python_version}")
    try:
        import torch
    except ImportError:
        raise WheelhouseError("--gsplat-cuda-arch needs torch installed here (the CUDA build the nodes will run: "
                              "the extension is compiled against it)") from None
    if not torch.version.cuda:
        raise WheelhouseError(f"torch {torch.__version__} here is a CPU build; building gsplat's CUDA code needs "
                              "the CUDA build of torch that the nodes run (and nvcc)")
    local = torch.__version__.split("+")[0]
    if torch_pin and torch_pin != local:
        raise WheelhouseError(f"the wheelhouse holds torch {torch_pin} but torch here is {torch.__version__}: "
                              "gsplat's extension only loads with the torch it was compiled against; install "
                              f"torch=={torch_pin} (CUDA build) here or pin --requirement torch=={local}")
    from torch.utils.cpp_extension import CUDA_HOME

    nvcc = shutil.which("nvcc") or (str(Path(CUDA_HOME) / "bin" / "nvcc") if CUDA_HOME else None)
    if not nvcc or not Path(nvcc).exists():
        raise WheelhouseError("nvcc (the CUDA toolkit) was not found (set CUDA_HOME or put nvcc on PATH)")
    return {"torch": torch.__version__, "cuda": torch.version.cuda, "nvcc": nvcc}


def compiled_extension(wheel: Path) -> list[str]:
    """The compiled modules (``*.so``) inside a gsplat wheel (empty for the pure JIT wheel)."""
    import zipfile

    with zipfile.ZipFile(wheel) as z:
        return [n for n in z.namelist() if n.startswith("gsplat/") and n.endswith(".so")]


def build_gsplat_cuda(version: str, archs: str, out: Path, pip_extra: list[str], log, max_jobs: int | None) -> Path:
    """Build gsplat==version from source with its CUDA code compiled for ``archs`` into ``out``."""
    env = dict(os.environ, TORCH_CUDA_ARCH_LIST=archs, BUILD_NO_CUDA="0")
    if max_jobs:
        env["MAX_JOBS"] = str(max_jobs)
    with tempfile.TemporaryDirectory(prefix="wheelhouse-gsplat-") as tmp:
        run_pip(["wheel", "--no-deps", "--no-build-isolation", "--no-binary", "gsplat", "--wheel-dir", tmp,
                 *pip_extra, f"gsplat=={version}"], log, env=env)
        built = sorted(Path(tmp).glob("gsplat-*.whl"))
        if len(built) != 1:
            raise WheelhouseError(f"building gsplat gave {len(built)} wheels, expected 1")
        if not compiled_extension(built[0]):
            raise WheelhouseError(f"{built[0].name} holds no compiled CUDA extension (was BUILD_NO_CUDA set?)")
        dest = out / built[0].name
        shutil.move(str(built[0]), dest)
    log(f"built {dest.name}: gsplat {version} with CUDA code for compute capability {archs} "
        f"({', '.join(compiled_extension(dest))})")
    return dest


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def tar_size(sizes: list[int]) -> int:
    """Bytes of an uncompressed tar holding files of these sizes (headers, padding, end)."""
    body = sum(TAR_BLOCK + math.ceil(s / TAR_BLOCK) * TAR_BLOCK for s in sizes) + 2 * TAR_BLOCK
    return math.ceil(body / TAR_RECORD) * TAR_RECORD


def plan_parts(files: dict[str, int], limit: int) -> list[list[str]]:
    """Group files (name -> size) into parts whose tar size stays <= limit (first fit,
    largest first). A file that alone exceeds the limit is an error."""
    parts: list[list[str]] = []
    sizes: list[list[int]] = []
    for name, size in sorted(files.items(), key=lambda kv: (-kv[1], kv[0])):
        if tar_size([size]) > limit:
            raise WheelhouseError(
                f"{name} is {size / 2**20:.1f} MiB, more than the part limit of {limit / 2**20:.1f} MiB "
                "(with its tar header): raise --split-mb")
        for i, part_sizes in enumerate(sizes):
            if tar_size(part_sizes + [size]) <= limit:
                parts[i].append(name)
                part_sizes.append(size)
                break
        else:
            parts.append([name])
            sizes.append([size])
    return parts


def write_parts(out: Path, names: list[str], limit: int, log) -> list[Path]:
    """Pack the wheelhouse into ``out/parts/wheelhouse-partNN.tar`` archives of <= limit bytes;
    manifest.json and SHA256SUMS go into every part."""
    meta = ["manifest.json", "SHA256SUMS"]
    sizes = {n: (out / n).stat().st_size for n in names}
    meta_sizes = [(out / m).stat().st_size for m in meta]
    overhead = tar_size(meta_sizes) - 2 * TAR_BLOCK
    groups = plan_parts(sizes, limit - overhead)
    pdir = out / "parts"
    if pdir.exists():
        shutil.rmtree(pdir)
    pdir.mkdir()
    paths = []
    width = max(2, len(str(len(groups))))
    for i, group in enumerate(groups, start=1):
        path = pdir / f"wheelhouse-part{i:0{width}d}.tar"
        with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tar:
            for n in meta + sorted(group):
                tar.add(out / n, arcname=n)
        if path.stat().st_size > limit:
            raise WheelhouseError(f"{path} came out at {path.stat().st_size} bytes, over the {limit}-byte limit")
        paths.append(path)
        log(f"part {path.name}: {len(group)} wheels, {path.stat().st_size / 2**20:.1f} MiB")
    return paths


def wheels_of(items: list[dict], out: Path, log) -> list[str]:
    """The file names in ``out`` of the resolved ``items``; other wheels there (from an earlier
    run for another target) are named and left out of the manifest and the parts."""
    needed = sorted(unquote(it["download_info"]["url"].rsplit("/", 1)[-1]) for it in items)
    missing = [n for n in needed if not (out / n).exists()]
    if missing:
        raise WheelhouseError(f"pip download did not leave {', '.join(missing)} in {out}")
    extra = sorted(p.name for p in out.glob("*.whl") if p.name not in needed)
    if extra:
        log(f"warning: {len(extra)} wheels in {out} are not needed for this target and are left out "
            f"of manifest.json and the parts: {', '.join(extra)}")
    return needed


def write_manifest(out: Path, target: Target, requirements: list[str], built_here: list[str],
                   wheels: list[str]) -> list[str]:
    entries = []
    for name in wheels:
        dist, version, _, tags = parse_wheel_filename(name)
        entries.append({"file": name, "name": str(dist), "version": str(version),
                        "size": (out / name).stat().st_size, "sha256": sha256(out / name),
                        "pure": all(t.platform == "any" for t in tags)})
    manifest = {"python_version": target.python_version, "platforms": target.platforms or ["(this machine)"],
                "requirements": requirements, "built_here": built_here, "wheels": entries}
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    (out / "SHA256SUMS").write_text("".join(f"{e['sha256']}  {e['file']}\n" for e in entries))
    return wheels


def _gsplat_plan(args, items: list[dict], target: Target) -> dict | None:
    """{version, archs, host} when --gsplat-cuda-arch asks for a compiled gsplat, else None."""
    if not getattr(args, "gsplat_cuda_arch", None):
        return None
    archs = parse_cuda_archs(args.gsplat_cuda_arch)
    found = {canonicalize_name(it["metadata"]["name"]): it["metadata"]["version"] for it in items}
    if "gsplat" not in found:
        raise WheelhouseError("--gsplat-cuda-arch: gsplat is not among the requirements (add --extras slurm,gpu)")
    host = cuda_build_host(target, found.get("torch"))
    return {"version": found["gsplat"], "archs": archs, "host": host}


def describe(items: list[dict]) -> str:
    rows = []
    for it in sorted(items, key=lambda i: canonicalize_name(i["metadata"]["name"])):
        url = it["download_info"]["url"]
        rows.append(f"  {it['metadata']['name']}=={it['metadata']['version']}  {url.rsplit('/', 1)[-1]}")
    return "\n".join(rows)


def build(args: argparse.Namespace, log=print) -> dict:
    """Build (or with ``args.dry_run`` only resolve) the wheelhouse; returns a summary."""
    target = Target(parse_python_version(args.python_version), list(args.platform or []))
    host = f"{sys.version_info.major}.{sys.version_info.minor}"
    if host != target.python_version and not args.no_deps:
        log(f"warning: running Python {host} for a {target.python_version} target: dependencies that "
            "depend on the Python version are picked for the target in step 3, but source-only "
            "packages are chosen under Python " + host)
    out = Path(args.out).resolve()
    if not args.dry_run:
        out.mkdir(parents=True, exist_ok=True)
    project = Path(args.project).resolve()
    pip_extra = list(args.pip_arg or []) + (["--no-build-isolation"] if args.no_build_isolation else [])
    with tempfile.TemporaryDirectory(prefix="wheelhouse-") as tmp:
        work = Path(tmp)
        stage = work / "wheels" if args.dry_run else out
        stage.mkdir(exist_ok=True)
        wheel = build_project_wheel(project, stage, pip_extra, log)
        extras = f"[{args.extras}]" if args.extras else ""
        reqs = [f"{wheel}{extras}"] + list(args.requirement or [])
        if not args.no_deps:
            reqs += read_build_requires(project)
        constraints = work / "constraints.txt"
        built_here: list[str] = []
        if args.no_deps:
            constraints.write_text("")
            dep_args = ["--no-deps"]
        else:
            items = host_resolution(reqs, pip_extra, work, log)
            built_here = build_sdist_only(items, stage, pip_extra, log)
            constraints.write_text("".join(p + "\n" for p in built_here))
            dep_args = []
        items = target_resolution(reqs, target, stage, constraints, pip_extra + dep_args, work, log)
        if args.dry_run:
            gsplat = _gsplat_plan(args, items, target)
            if gsplat:
                log(f"would build gsplat {gsplat['version']} here with CUDA code for {gsplat['archs']} "
                    f"(torch {gsplat['host']['torch']}, nvcc {gsplat['host']['nvcc']})")
            log(f"would put {len(items)} wheels into {out} for Python {target.python_version} "
                f"on {', '.join(target.platforms) or 'this platform'}:\n{describe(items)}")
            if built_here:
                log("built here (pure Python, no wheel on the index): " + ", ".join(built_here))
            return {"dry_run": True, "items": items, "built_here": built_here, "project_wheel": wheel.name}
        gsplat = _gsplat_plan(args, items, target)  # checks this machine before downloading
        download_for_target(reqs, target, out, constraints, pip_extra + dep_args, log)
    wheels = wheels_of(items, out, log)
    if gsplat:
        pure = [w for w in wheels if canonicalize_name(parse_wheel_filename(w)[0]) == "gsplat"]
        built = build_gsplat_cuda(gsplat["version"], gsplat["archs"], out, pip_extra, log, args.max_jobs)
        for w in pure:
            if w != built.name:
                (out / w).unlink()
        wheels = sorted([w for w in wheels if w not in pure] + [built.name])
        built_here.append(f"gsplat=={gsplat['version']} (CUDA {gsplat['archs']}, torch {gsplat['host']['torch']})")
    shown_reqs = [r.replace(str(wheel), wheel.name) for r in reqs]
    wheels = write_manifest(out, target, shown_reqs, built_here, wheels)
    parts = write_parts(out, wheels, int(args.split_mb * 2**20), log) if args.split_mb else []
    total = sum((out / w).stat().st_size for w in wheels)
    log(f"wheelhouse {out}: {len(wheels)} wheels, {total / 2**20:.1f} MiB"
        + (f", {len(parts)} parts under {args.split_mb} MiB in {out / 'parts'}" if parts else ""))
    return {"dry_run": False, "wheels": wheels, "parts": [str(p) for p in parts],
            "built_here": built_here, "project_wheel": wheel.name}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="wheelhouse", help="folder for the wheels (default: wheelhouse)")
    p.add_argument("--python-version", default=f"{sys.version_info.major}.{sys.version_info.minor}",
                   help="target Python, e.g. 3.11 (default: this Python)")
    p.add_argument("--platform", action="append",
                   help="target platform tag, repeatable, e.g. manylinux_2_28_x86_64 --platform "
                        "manylinux2014_x86_64 (default: this machine's)")
    p.add_argument("--extras", default="slurm",
                   help="project extras to include, comma-separated (default: slurm; GPU nodes: slurm,gpu)")
    p.add_argument("--requirement", action="append",
                   help="an extra requirement to include, repeatable (e.g. 'torch==2.5.1')")
    p.add_argument("--project", default=str(REPO), help="the project folder (default: this repository)")
    p.add_argument("--split-mb", type=float, help="also pack the wheels into tar parts of at most this many MiB")
    p.add_argument("--no-deps", action="store_true", help="only the project wheel and --requirement, no dependencies")
    p.add_argument("--no-build-isolation", action="store_true",
                   help="build the project and source-only packages with the build backend installed here "
                        "(pip downloads none)")
    p.add_argument("--pip-arg", action="append",
                   help="extra option passed to every pip call, repeatable, e.g. "
                        "--pip-arg=--extra-index-url=https://download.pytorch.org/whl/cu121")
    p.add_argument("--gsplat-cuda-arch", default=None,
                   help="build gsplat here with its CUDA code compiled for these compute capabilities "
                        "(e.g. '8.0;9.0': A100 and H100; nvidia-smi --query-gpu=compute_cap on a node) instead of "
                        "the pure wheel that JIT-compiles on first use; needs the target's Python, the CUDA build "
                        "of the wheelhouse's torch and nvcc here")
    p.add_argument("--max-jobs", type=int, default=None, help="parallel compiler jobs of the gsplat build (MAX_JOBS)")
    p.add_argument("--dry-run", action="store_true",
                   help="resolve for the target and list the wheels without downloading them")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.split_mb is not None and args.split_mb <= 0:
        print("error: --split-mb must be positive", file=sys.stderr)
        return 2
    try:
        build(args)
    except WheelhouseError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
