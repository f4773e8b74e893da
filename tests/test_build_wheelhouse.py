"""tools/build_wheelhouse.py: offline wheelhouse for air-gapped nodes.

Everything here runs without a package index (``--no-index``): the project's own wheel is
built with the installed setuptools, and the dependency path is exercised with a tiny
pure-Python project whose dependency exists only as a source distribution in a local folder.
"""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("build_wheelhouse", REPO / "tools" / "build_wheelhouse.py")
bw = importlib.util.module_from_spec(spec)
sys.modules["build_wheelhouse"] = bw
spec.loader.exec_module(bw)

OFFLINE = ["--no-build-isolation", "--pip-arg=--no-index"]


def run_tool(*args: str) -> dict:
    return bw.build(bw.parser().parse_args(list(args)), log=lambda msg: None)


def write_project(root: Path, name: str, deps: list[str]) -> Path:
    """A minimal setuptools project (one module) that builds without downloading anything."""
    root.mkdir(parents=True)
    dep_list = ", ".join(f'"{d}"' for d in deps)
    (root / "pyproject.toml").write_text(
        '[build-system]\nrequires = []\nbuild-backend = "setuptools.build_meta"\n\n'
        f'[project]\nname = "{name}"\nversion = "1.0"\ndependencies = [{dep_list}]\n')
    (root / name).mkdir()
    (root / name / "__init__.py").write_text(f'NAME = "{name}"\n')
    return root


def write_sdist(index: Path, name: str) -> Path:
    """``index/<name>-1.0.tar.gz``: a source-only package, as some PyPI projects ship."""
    src = write_project(index.parent / "sdist-src" / f"{name}-1.0", name, [])
    index.mkdir(parents=True, exist_ok=True)
    path = index / f"{name}-1.0.tar.gz"
    with tarfile.open(path, "w:gz") as tar:
        tar.add(src, arcname=f"{name}-1.0")
    return path


def test_project_wheel_manifest_and_parts(tmp_path):
    before = {p.name for p in REPO.iterdir()} | {p.name for p in (REPO / "src").iterdir()}
    out = tmp_path / "wh"
    summary = run_tool("--out", str(out), "--no-deps", "--split-mb", "2", *OFFLINE)  # the project wheel: ~0.5 MiB

    wheel = out / summary["project_wheel"]
    assert wheel.name.startswith("physgs_steps-") and wheel.name.endswith("-py3-none-any.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "physgs_steps/__init__.py" in names and "physgs_steps/runtime.py" in names
    # building left nothing (build/, *.egg-info) in the source tree
    after = {p.name for p in REPO.iterdir()} | {p.name for p in (REPO / "src").iterdir()}
    assert after - before == set()

    manifest = json.loads((out / "manifest.json").read_text())
    entry = {e["file"]: e for e in manifest["wheels"]}[wheel.name]
    assert entry["sha256"] == bw.sha256(wheel) and entry["pure"] and entry["name"] == "physgs-steps"
    assert f"{entry['sha256']}  {wheel.name}" in (out / "SHA256SUMS").read_text()

    parts = [Path(p) for p in summary["parts"]]
    assert parts and all(p.stat().st_size <= 2 * 2**20 for p in parts)
    unpacked = tmp_path / "unpacked"
    for p in parts:
        with tarfile.open(p) as tar:
            tar.extractall(unpacked, filter="data")
    assert bw.sha256(unpacked / wheel.name) == entry["sha256"]
    # the unpacked parts install with pip and no index
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--find-links",
                    str(unpacked), "--target", str(target), "physgs-steps"], check=True)
    assert (target / "physgs_steps" / "plan.py").exists()


def test_binary_target_resolves_and_builds_source_only_dependency(tmp_path):
    index = tmp_path / "index"
    write_sdist(index, "fakedep")
    project = write_project(tmp_path / "proj", "fakeproj", ["fakedep>=1.0"])
    common = ["--project", str(project), "--extras", "", "--python-version", "3.12",
              "--platform", "manylinux2014_x86_64", "--platform", "manylinux_2_28_x86_64",
              *OFFLINE, f"--pip-arg=--find-links={index}"]

    dry = run_tool("--out", str(tmp_path / "dry"), "--dry-run", *common)
    assert sorted(i["metadata"]["name"] for i in dry["items"]) == ["fakedep", "fakeproj"]
    assert dry["built_here"] == ["fakedep==1.0"]
    assert not (tmp_path / "dry").exists()

    out = tmp_path / "wh"
    out.mkdir()
    (out / "stale-1.0-py3-none-any.whl").write_bytes(b"from an earlier run for another target")
    summary = run_tool("--out", str(out), "--split-mb", "1", *common)
    assert sorted(summary["wheels"]) == ["fakedep-1.0-py3-none-any.whl", "fakeproj-1.0-py3-none-any.whl"]
    with tarfile.open(summary["parts"][0]) as tar:
        assert "stale-1.0-py3-none-any.whl" not in tar.getnames()
        assert "fakedep-1.0-py3-none-any.whl" in tar.getnames()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["python_version"] == "3.12" and manifest["built_here"] == ["fakedep==1.0"]
    assert len(summary["parts"]) == 1


def test_target_pip_args():
    t = bw.Target("3.12", ["manylinux2014_x86_64"])
    args = t.pip_args()
    assert args[0] == "--only-binary=:all:"
    assert args[args.index("--python-version") + 1] == "3.12"
    assert "cp312" in args and args[args.index("--platform") + 1] == "manylinux2014_x86_64"
    with pytest.raises(bw.WheelhouseError, match="3.11"):
        bw.parse_python_version("311")


def test_binary_wheel_built_here_is_refused(tmp_path):
    with pytest.raises(bw.WheelhouseError, match="not pure Python"):
        bw.check_pure(tmp_path / "thing-1.0-cp311-cp311-linux_x86_64.whl")
    bw.check_pure(tmp_path / "thing-1.0-py2.py3-none-any.whl")


def test_part_sizes_match_tar_and_respect_limit(tmp_path):
    sizes = {"a.whl": 700_000, "b.whl": 300_000, "c.whl": 200_000, "d.whl": 5, "e.whl": 512}
    for name, size in sizes.items():
        (tmp_path / name).write_bytes(b"x" * size)
    with tarfile.open(tmp_path / "all.tar", "w", format=tarfile.USTAR_FORMAT) as tar:
        for name in sizes:
            tar.add(tmp_path / name, arcname=name)
    assert bw.tar_size(list(sizes.values())) == (tmp_path / "all.tar").stat().st_size

    limit = 1_000_000
    parts = bw.plan_parts(sizes, limit)
    assert sorted(n for p in parts for n in p) == sorted(sizes)
    assert all(bw.tar_size([sizes[n] for n in p]) <= limit for p in parts)
    assert len(parts) == 2
    with pytest.raises(bw.WheelhouseError, match="raise --split-mb"):
        bw.plan_parts({"huge.whl": 2_000_000}, limit)


# ---------------------------------------------------------------------------- gsplat with CUDA code
def test_cuda_arch_list_is_normalised_and_checked():
    assert bw.parse_cuda_archs("8.0;9.0") == "8.0;9.0"
    assert bw.parse_cuda_archs(" 8.6, 9.0+PTX ") == "8.6;9.0+PTX"
    assert bw.parse_cuda_archs("9.0a 10.0") == "9.0a;10.0"
    for bad in ("", "sm_90", "9", "9.0;ampere"):
        with pytest.raises(bw.WheelhouseError, match="compute capabilities"):
            bw.parse_cuda_archs(bad)


def test_compiled_extension_tells_prebuilt_from_jit_wheels(tmp_path):
    pure, built = tmp_path / "gsplat-1.5.3-py3-none-any.whl", tmp_path / "gsplat-1.5.3-cp311-cp311-linux_x86_64.whl"
    with zipfile.ZipFile(pure, "w") as z:
        z.writestr("gsplat/__init__.py", "")
        z.writestr("gsplat/cuda/_backend.py", "")
    with zipfile.ZipFile(built, "w") as z:
        z.writestr("gsplat/__init__.py", "")
        z.writestr("gsplat/csrc.so", b"\x7fELF")
    assert bw.compiled_extension(pure) == []
    assert bw.compiled_extension(built) == ["gsplat/csrc.so"]


def test_gsplat_build_host_is_checked_before_anything_is_built(tmp_path):
    torch = pytest.importorskip("torch")
    here = f"{sys.version_info.major}.{sys.version_info.minor}"
    with pytest.raises(bw.WheelhouseError, match="target is 3.99|python3.99"):
        bw.cuda_build_host(bw.Target("3.99"), None)
    if not torch.version.cuda:  # this machine (CPU torch): refused with the reason
        with pytest.raises(bw.WheelhouseError, match="CPU build"):
            bw.cuda_build_host(bw.Target(here), None)
    # wired into the tool: --gsplat-cuda-arch without gsplat among the requirements
    with pytest.raises(bw.WheelhouseError, match="gsplat is not among the requirements"):
        run_tool("--out", str(tmp_path / "wh"), "--no-deps", "--gsplat-cuda-arch", "9.0", *OFFLINE)
