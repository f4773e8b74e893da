"""Careless input (issue #19): a bad scene file blocks only its own targets, numbers parse as
people write them, problems are one-line messages (never tracebacks), `physgs check`."""
from __future__ import annotations

import copy
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from physgs_steps import config as C
from physgs_steps import plan as P
from physgs_steps.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
LINKED = ["Snakefile", "workflow", "config", "src", "tests", "profiles"]
TINY = REPO / "tests" / "slurm" / "config.yaml"


# ---------------------------------------------------------------------------- numbers
def test_scientific_notation_and_string_numbers_are_accepted():
    cfg = C.load_config()
    c = copy.deepcopy(cfg)
    # YAML 1.1 (Snakemake's config loader) reads 5e4 as a string; --config nests strings
    c["sim"].update(domain_size="2.0e4", n_grid="32", n_frames=1.5e2)
    c["bgdo"].update(forward_frames="null", ceiling="false", max_step="9.2")
    c["render"]["background"] = ["1", "1e0", ".5"]
    C.validate_config(c)
    assert c["sim"]["domain_size"] == 2.0e4 and c["sim"]["n_grid"] == 32
    assert c["sim"]["n_frames"] == 150 and isinstance(c["sim"]["n_frames"], int)
    assert c["bgdo"]["forward_frames"] is None and c["bgdo"]["ceiling"] is False and c["bgdo"]["max_step"] == 9.2
    assert c["render"]["background"] == [1.0, 1.0, 0.5]
    for key, bad in (("n_grid", "wide"), ("n_grid", "3.5"), ("domain_size", "5e4 m"), ("domain_size", "inf")):
        c2 = copy.deepcopy(cfg)
        c2["sim"][key] = bad
        with pytest.raises(ConfigError, match=rf"sim\.{key}"):
            C.validate_config(c2)


def test_scene_file_reads_yaml12_numbers(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text("source: builtin:bear\ninstances:\n  - {name: b, E: 5e4, density: 1E3, nu: .3}\n"
                 "config: {sim: {domain_size: 2.0e4}}\n")
    data = C.read_yaml(p)
    assert data["instances"][0]["E"] == 5e4 and data["instances"][0]["density"] == 1e3
    C.validate(data, C.load_schema("scene.schema.yaml"), str(p))
    assert data["config"]["sim"]["domain_size"] == 2e4
    p.write_text("source: builtin:bear\ninstances:\n  - {name: b, E: 'fifty kilopascal'}\n")
    with pytest.raises(ConfigError, match=r"instances\.0\.E"):
        C.validate(C.read_yaml(p), C.load_schema("scene.schema.yaml"), str(p))
    p.write_text("source: builtin:bear\ninstances:\n  - {name: b, E: .inf}\n")  # passes every schema bound
    with pytest.raises(ConfigError, match=r"instances\.0\.E.*finite"):
        C.validate(C.read_yaml(p), C.load_schema("scene.schema.yaml"), str(p))


# ---------------------------------------------------------------------------- plans
@pytest.fixture()
def scenes(tmp_path, repo):
    """A scene folder with one good scene and three broken ones."""
    d = tmp_path / "scenes"
    d.mkdir()
    good = yaml.safe_load((repo / "config" / "scenes" / "bear.yaml").read_text())
    good["builtin"] = {"n_gaussians": 2000, "seed": 0}
    (d / "good.yaml").write_text(yaml.safe_dump(good))
    (d / "wrongtype.yaml").write_text("source: builtin:bear\ninstances:\n  - {name: x, E: abc}\n")
    (d / "syntax.yaml").write_text("source: builtin:bear\nprompt: [unclosed\n")
    (d / "unknownkey.yaml").write_text("source: builtin:bear\ncamra: {fov_deg: 40}\n")
    return d


def test_registry_records_a_broken_scene_and_plans_the_others(scenes):
    cfg = C.load_config()
    cfg["scenes_dir"] = str(scenes)
    names, why = C.list_scenes(cfg)
    assert why is None and names == ["good", "syntax", "unknownkey", "wrongtype"]
    reg = P.Registry(cfg, names)
    assert reg.plan("good").scene == "good" and reg.plan("good/ablations/no_bgdo").ablation == "no_bgdo"
    assert not reg.problems
    with pytest.raises(ConfigError, match=r"instances\.0\.E.*wrongtype\.yaml"):
        reg.plan("wrongtype")
    with pytest.raises(Exception, match=r"syntax\.yaml: not valid YAML"):
        reg.plan("syntax/ablations/no_ipf")
    with pytest.raises(ConfigError, match="camra.*allowed keys"):
        reg.for_id("unknownkey", "fill", "whatever")
    with pytest.raises(ConfigError, match="unknown ablation 'nope'.*no_bgdo"):
        reg.plan("good/ablations/nope")
    with pytest.raises(ConfigError, match="unknown scene 'other'.*known scenes: good"):
        reg.plan("other")


def test_scenes_dir_problems(tmp_path):
    cfg = C.load_config()
    for value, needle in ((str(tmp_path / "nowhere"), "does not exist"), (str(tmp_path), "holds no scene file")):
        cfg["scenes_dir"] = value
        names, why = C.list_scenes(cfg)
        assert names == [] and needle in str(why) and "scenes_dir" in str(why)


# ---------------------------------------------------------------------------- snakemake
@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("wf")
    for name in LINKED:
        (d / name).symlink_to(REPO / name)
    return d


def smk(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    # one process per job, as before worker.enabled auto served --cores 1 runs: no worker left behind
    return subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300, stdin=subprocess.DEVNULL, env={**os.environ, "PHYSGS_WORKER": "0"})


def one_line_error(p: subprocess.CompletedProcess) -> str:
    """The physgs message of a failed run: exit 1, one 'physgs:' line, no traceback."""
    out = p.stdout + p.stderr
    assert p.returncode == 1, out[-3000:]
    assert "Traceback" not in out and "Exception" not in out, out[-3000:]
    lines = [ln for ln in out.splitlines() if ln.startswith("physgs: ")]
    assert len(lines) == 1, out[-3000:]
    return lines[0]


def test_bad_scene_next_to_a_good_one(run_dir, scenes):
    cfg = ["--configfile", str(TINY), "--config", f"scenes_dir={scenes}"]
    p = smk(run_dir, "-n", *cfg)  # the default target: the first scene, 'good'
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    assert "results/good/video.mp4" in p.stdout
    msg = one_line_error(smk(run_dir, "-n", "results/wrongtype/video.mp4", *cfg))
    assert "wrongtype.yaml" in msg and "instances.0.E" in msg and "'abc'" in msg
    msg = one_line_error(smk(run_dir, "-n", "results/syntax/scene.ply", *cfg))
    assert "syntax.yaml: not valid YAML" in msg and "line 2" in msg
    # the good scene really runs (its first stage) beside the broken ones
    p = smk(run_dir, "results/good/scene.ply", *cfg)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    assert (run_dir / "results" / "good" / "scene.ply").stat().st_size > 0


@pytest.mark.parametrize("args,needles", [
    (["-n", "--config", "scenes_dir=no/such/folder"], ["scenes_dir", "does not exist"]),
    (["-n", "--config", "scenes_dir=tests"], ["scenes_dir", "holds no scene file"]),
    (["-n", "results/bear/ablations/nope/video.mp4"], ["unknown ablation 'nope'", "no_bgdo, no_ipf"]),
    (["-n", "results/nosuch/video.mp4"], ["unknown scene 'nosuch'", "known scenes: ball_jelly, basket_mat, bear"]),
    (["-n", "--config", "device=gpu"], ["'device' (in --config)", "valid choices: auto, cpu, cuda"]),
    (["-n", "--config", "sim={n_grid: 3"], ["'sim' (in --config)", "mapping is expected"]),
    (["-n", "--config", "sim={n_grid: many}"], ["sim.n_grid", "'many' is not of type 'integer'"]),
])
def test_one_line_messages(run_dir, args, needles):
    msg = one_line_error(smk(run_dir, *args))
    for n in needles:
        assert n in msg, msg


def test_config_numbers_from_the_command_line(run_dir):
    p = smk(run_dir, "-n", "--config", "sim={n_grid: 32, domain_size: 1.0e0}", "bgdo={forward_frames: 1.5e2}")
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]


# ---------------------------------------------------------------------------- physgs check
def test_physgs_check_lists_every_problem(tmp_path, scenes):
    (scenes / "bad name.yaml").write_text("source: builtin:bear\n")
    (scenes / "many.yaml").write_text(
        "source: missing/file.ply\ninstances:\n  - {name: y, material: unobtainium}\n"
        "camera: {mode: cameras_json, cameras_json: no/cameras.json}\nconfig: {sim: {n_grid: 4}}\n")
    cfg = tmp_path / "config.yaml"
    cfg.write_text(yaml.safe_dump({"scenes_dir": str(scenes)}))
    p = subprocess.run([sys.executable, "-m", "physgs_steps.cli", "--config", str(cfg), "check"], capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 1, p.stdout + p.stderr
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith(str(scenes))]
    text = "\n".join(lines)
    for needle in ("bad name.yaml: 'bad name' is not a valid scene name", "wrongtype.yaml: instances.0.E",
                   "syntax.yaml: not valid YAML", "unknownkey.yaml: <root>: Additional properties",
                   "many.yaml: config.sim.n_grid: 4 is less than the minimum of 8", "many.yaml: source:",
                   "many.yaml: scene.instances[0].material: unknown material 'unobtainium'",
                   "many.yaml: camera.cameras_json:"):
        assert needle in text, text
    assert not any("good.yaml" in ln for ln in lines), text
    assert "problem(s) in 5 file(s)" in p.stderr
    p = subprocess.run([sys.executable, "-m", "physgs_steps.cli", "check"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "no problems" in p.stdout, p.stdout + p.stderr


# ---------------------------------------------------------------------------- artifacts
@pytest.mark.parametrize("umask,mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_artifacts_honour_the_umask(tmp_path, umask, mode):
    from physgs_steps import runtime

    old = __import__("os").umask(umask)
    try:
        runtime.write_json(tmp_path / "a.json", {"x": 1})
        with runtime.atomic_path(tmp_path / "b.h5") as tmp:
            import h5py

            with h5py.File(tmp, "w") as f:
                f["x"] = [1, 2]
    finally:
        __import__("os").umask(old)
    for name in ("a.json", "b.h5"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode, name


def test_stale_part_files_of_a_killed_stage_are_cleaned(tmp_path):
    """A stage killed while writing leaves its temporary file; the next run of the stage removes it
    (and leaves the part files of other outputs, and of a live writer, alone)."""
    import os
    import signal
    import time

    from physgs_steps import runtime

    out = tmp_path / "final.h5"
    code = ("import sys, time; from physgs_steps.runtime import atomic_path\n"
            f"with atomic_path({str(out)!r}) as t:\n    open(t, 'wb').write(b'x' * 100); print(t, flush=True); time.sleep(60)\n")
    writer = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    part = Path(writer.stdout.readline().strip())
    assert part.exists() and runtime.part_pattern(out).match(part.name), part
    os.kill(writer.pid, signal.SIGKILL)
    writer.wait()
    assert part.exists()  # the kill left it
    old_style = tmp_path / ".final.h5.k2j3h4l5.part.h5"   # the name format before the host-pid tag
    other = tmp_path / ".final_other.h5.ab12cd34.part.h5"
    live = tmp_path / f".final.h5.{runtime._host_tag()}-{os.getppid()}.zz99zz99.part.h5"
    for p in (old_style, other, live):
        p.write_bytes(b"x")

    def stage(inputs, outputs, cfg, log):
        with runtime.atomic_path(outputs["frames"]) as t:
            Path(t).write_bytes(b"done")
        return {}

    t0 = time.time()
    runtime.run_stage("final_sim", stage, {}, {"frames": str(out)}, {}, str(tmp_path / "log.txt"))
    assert time.time() - t0 < 30
    assert out.read_bytes() == b"done"
    assert not part.exists() and not old_style.exists()
    assert other.exists() and live.exists()
    assert "earlier run of this stage" in (tmp_path / "log.txt").read_text()


def _strict_load(text: str):
    import json

    def no_constant(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=no_constant)


def test_json_outputs_are_strict(tmp_path):
    import numpy as np

    from physgs_steps import runtime

    doc = {"E": 5e4, "g_tilde": float("inf"), "frames": [{"delta": float("nan")}, {"delta": 0.1}],
           "arr": np.array([1.0, -np.inf], np.float32), "n": np.int64(3)}
    runtime.write_json(tmp_path / "p.json", doc)
    back = _strict_load((tmp_path / "p.json").read_text())
    assert back["g_tilde"] is None and back["frames"][0]["delta"] is None and back["arr"] == [1.0, None]
    assert back["nonfinite"]["values"] == {"/g_tilde": "inf", "/frames/0/delta": "nan", "/arr/1": "-inf"}
    assert back["E"] == 5e4 and back["n"] == 3 and back["frames"][1]["delta"] == 0.1
    assert _strict_load(runtime.json_text({"speed_max": float("inf")}))["speed_max"] is None


# ---------------------------------------------------------------------------- openai deadline
def test_openai_timeout_is_a_deadline_against_a_trickling_server():
    """A server that sends a valid answer one byte every 0.2 s (about a minute in all) is cut off
    at materials.openai.timeout_s, not held for the whole answer (urllib's timeout is per read)."""
    import json
    import logging
    import threading
    import time
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    from physgs_steps.params.openai_backend import OpenAIBackend
    from physgs_steps.params.prompt import BackendError

    answer = json.dumps({"choices": [{"message": {"role": "assistant", "content": '{"material": "jelly"}'}}]})
    answer = answer + " " * max(0, 300 - len(answer))  # 300 bytes at 5 bytes/s: 60 s
    hits = []

    class Trickle(BaseHTTPRequestHandler):
        def do_POST(self):  # noqa: N802 - http.server API
            self.rfile.read(int(self.headers["Content-Length"]))
            hits.append(time.monotonic())
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(answer)))
            self.end_headers()
            try:
                for ch in answer.encode():
                    self.wfile.write(bytes([ch]))
                    self.wfile.flush()
                    time.sleep(0.2)
            except OSError:  # the client hung up
                pass

        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Trickle)
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        be = OpenAIBackend({"base_url": f"http://127.0.0.1:{httpd.server_address[1]}/v1", "model": "m",
                            "timeout_s": 1.5, "retries": 1, "backoff_s": 0.1}, logging.getLogger("test"))
        t0 = time.monotonic()
        with pytest.raises(BackendError, match=r"timeout_s = 1\.5 s.*gave up after 2 attempts"):
            be.send([{"role": "user", "content": "hi"}])
        took = time.monotonic() - t0
    finally:
        httpd.shutdown()
        httpd.server_close()
    assert len(hits) == 2
    assert took < 6.0, f"two attempts of 1.5 s took {took:.1f} s"


# ---------------------------------------------------------------------------- cluster fragments
def _two_blobs(n_big=1950, n_small=203, gap=0.06, seed=0):
    import numpy as np

    rng = np.random.default_rng(seed)
    big = rng.uniform([0.3, 0.3, 0.3], [0.6, 0.6, 0.5], (n_big, 3))
    small = rng.uniform([0.3, 0.6 + gap, 0.3], [0.4, 0.65 + gap, 0.35], (n_small, 3))
    return np.concatenate([big, small])


def test_a_fragment_joins_its_nearest_listed_instance_and_pins_name_the_scene_file(tmp_path):
    import logging

    from physgs_steps.cluster import cluster_config, compute_labels
    from physgs_steps.params.stage import pinned_params

    pts = _two_blobs()
    scene = {"instances": [{"name": "udon", "material": "plasticine"}], "_path": "config/scenes/udon.yaml"}
    log = logging.getLogger("test")
    labels, rec = compute_labels(pts, scene, cluster_config({}), None, log)
    assert rec["n_instances"] == 1 and (labels == 0).all()
    assert rec["fragments"][0]["count"] == 203 and rec["fragments"][0]["joined_name"] == "udon"
    assert any("joined instance 'udon'" in w for w in rec["warnings"])
    assert pinned_params(scene, rec)["instances"][0]["material"] == "plasticine"
    # a fragment larger than cluster.fragment_fraction of its neighbour stays; the pins then say what to do
    labels, rec = compute_labels(pts, scene, cluster_config({"cluster": {"fragment_fraction": 0.05}}), None, log)
    assert rec["n_instances"] == 2 and rec["instances"][1]["unmatched"]["nearest_label"] == 0
    with pytest.raises(ConfigError) as e:
        pinned_params(scene, rec)
    msg = str(e.value)
    assert "config/scenes/udon.yaml" in msg and "cluster label 1 (203 gaussians" in msg
    assert "cluster.merge: [[0, 1]]" in msg and "cluster.fragment_fraction above 0.104" in msg
    # without listed instances every cluster is an instance
    labels, rec = compute_labels(pts, {"instances": []}, cluster_config({}), None, log)
    assert rec["n_instances"] == 2 and not rec["fragments"]


# ---------------------------------------------------------------------------- units and appearance
def _blob(unit: float, offset: float = 0.0, n: int = 500):
    """A sphere of gaussians 0.2 units across (x ``unit``) centred at ``offset`` (source frame)."""
    import numpy as np

    from physgs_steps.gaussians import GaussianScene

    rng = np.random.default_rng(1)
    pts = rng.normal(size=(n, 3))
    pts = 0.1 * pts / np.linalg.norm(pts, axis=1, keepdims=True) * rng.uniform(0.8, 1.0, (n, 1))
    sh = np.zeros((n, 1, 3))
    sh[:, 0] = [1.5, -1.5, -1.5]
    return GaussianScene(means=pts * unit + offset, log_scales=np.log(np.full((n, 3), 0.02 * unit)),
                         quats=np.tile([1.0, 0, 0, 0], (n, 1)), opacity_logits=np.full(n, 3.0), sh=sh)


def _prepare(tmp_path, scene, name="src.ply"):
    import logging

    from physgs_steps import prepare
    from physgs_steps.scene_io import save_gaussians

    save_gaussians(scene, tmp_path / name)
    out = {"scene": str(tmp_path / "scene.ply"), "transform": str(tmp_path / "transform.json")}
    cfg = {"scene": {"source": str(tmp_path / name), "_path": "s.yaml"}, "prepare": {}}
    return prepare.run({"source": str(tmp_path / name)}, out, cfg, logging.getLogger("test")), out


@pytest.mark.parametrize("unit,offset", [(1e-4, 0.0), (1.0, 0.0), (1e4, 0.0), (1.0, 1e4)])
def test_tiny_and_huge_unit_captures_render(tmp_path, unit, offset):
    """render.near/far follow the scene's size: a capture 2e-5 or 2e3 units across renders like one
    in metres (they were absolute source units: 0.01 clipped a 1e-4 capture, 1000 a 1e4 one)."""
    import json
    import logging

    import h5py
    import numpy as np

    from physgs_steps.carrier import build_carrier, write_carrier
    from physgs_steps.config import section_defaults
    from physgs_steps.final_frames import FinalWriter
    from physgs_steps.render.stage import run
    from physgs_steps.scene_io import load_gaussians

    _, out = _prepare(tmp_path, _blob(unit, offset))
    sim = load_gaussians(out["scene"])
    x = np.stack([sim.means, sim.means - [0, 0, 0.01]]).astype(np.float32)  # [2, N, 3]
    with h5py.File(tmp_path / "final.h5", "w") as f:
        w = FinalWriter(f, np.arange(sim.n), np.arange(2) / 30.0)
        for k in range(2):
            w.frame(k, x[k], np.tile(np.eye(3, dtype=np.float32), (sim.n, 1, 1)))
        w.finish({"stats": {"test": True}})
    labels = np.zeros(sim.n, np.int32)  # every gaussian is its own particle: identity carrier
    write_carrier(tmp_path / "carrier.h5", build_carrier(sim.means, labels, sim.means, labels, np.arange(sim.n),
                                                         "gaussians", 1, 0.01))
    r = section_defaults("render")
    r.update({"backend": "cpu", "width": 48, "height": 48, "contact_sheet": {"frames": 2, "columns": 2, "tile_width": 32}})
    outputs = {k: str(tmp_path / "out" / v) for k, v in
               (("video", "video.mp4"), ("contact_sheet", "sheet.png"), ("report", "render.json"))}
    run({"frames": str(tmp_path / "final.h5"), "scene": out["scene"], "transform": out["transform"],
         "carrier": str(tmp_path / "carrier.h5")}, outputs,
        {"render": r, "scene": {"camera": {"elevation_deg": 10.0}}, "device": "cpu"}, logging.getLogger("test"))
    rep = json.loads((tmp_path / "out" / "render.json").read_text())
    assert rep["coverage"]["min"] > 0.05, rep["coverage"]
    size = rep["clip"]["scene_size"]
    assert size == pytest.approx(0.2 * unit, rel=0.1)
    assert rep["clip"]["near"] == pytest.approx(1e-3 * size) and rep["clip"]["far"] > 1e3 * size


def test_prepare_checks_opacity_scale_and_float32_resolution(tmp_path):
    import numpy as np

    from physgs_steps.errors import InputError

    s = _blob(1.0)
    s.opacity_logits[:] = -20.0  # opacity 2e-9
    with pytest.raises(InputError, match="opacity below 1/255.*logits"):
        _prepare(tmp_path, s)
    s = _blob(1.0)
    s.log_scales[:] = np.log(1e30)
    with pytest.raises(InputError, match="larger than the whole scene.*natural log"):
        _prepare(tmp_path, s)
    s = _blob(1.0)
    s.log_scales[:7] = np.log(1e30)  # a few absurd gaussians are dropped, the rest goes on
    summary, _ = _prepare(tmp_path, s)
    assert summary["dropped"]["oversized"] == 7 and summary["n_kept"] == s.n - 7
    with pytest.raises(InputError, match="no spatial extent.*resolve only 64 units: re-export the capture centred"):
        _prepare(tmp_path, _blob(1.0, offset=1e9))  # a capture 1e9 units away: float32 collapses it to a point
    with pytest.raises(InputError, match="resolve only 0.0625 units.*quantised.*Re-export the capture centred"):
        _prepare(tmp_path, _blob(1.0, offset=1e6))


# ---------------------------------------------------------------------------- BGDO without load
def test_key_frames_before_contact_leave_E_unchanged_with_a_warning(tmp_path):
    """bgdo.forward_frames: 3: the block is still falling in every key frame (the forward.h5 of a
    3-frame run: free fall, F = I); BGDO must not read its zero deformation as 'far too stiff'
    (it took 5e4 -> 34 Pa), but keep E, say why and how many forward frames reach the contact."""
    import json
    import logging

    import h5py
    import numpy as np

    from physgs_steps.bgdo import run as bgdo_run
    from physgs_steps.config import section_defaults

    rng = np.random.default_rng(0)
    x0 = np.asarray([0.42, 0.42, 0.45]) + 0.16 * rng.random((1500, 3))  # bottom 0.35 m above the ground (0.1)
    P = len(x0)
    params = {"instances": [{"label": 0, "name": "block", "material": "jelly", "elasticity": "fixed_corotated",
                             "plasticity": "identity", "E": 5.0e4, "nu": 0.3, "density": 1000.0,
                             "plasticity_params": {}, "velocity": [0.0, 0.0, 0.0]}], "backend": "prior", "history": []}
    with h5py.File(tmp_path / "forward.h5", "w") as f:
        f["particles/label"] = np.zeros(P, np.int32)
        f["particles/filled"] = np.zeros(P, bool)
        f["particles/vol"] = np.full(P, 0.16 ** 3 / P, np.float32)
        for k in (0, 1, 2):
            t = k / 30.0
            g = f.create_group(f"keyframes/{k}")
            g["x"] = (x0 - [0, 0, 4.9 * t * t]).astype(np.float32)
            g["v"] = np.tile([0.0, 0.0, -9.8 * t], (P, 1)).astype(np.float32)
            g["C"] = np.zeros((P, 3, 3), np.float32)
            g["F"] = np.tile(np.eye(3, dtype=np.float32), (P, 1, 1))
            g.attrs.update(frame=k, time=t, dt=1e-3)
        f.attrs["params"] = json.dumps(params)
        f.attrs["sim_config"] = json.dumps({"sim": {"n_grid": 32, "domain_size": 1.0, "fps": 30.0},
                                            "dynamics": {"gravity": [0.0, 0.0, -9.8]}, "dx": 1 / 32})
        f.attrs["stats"] = json.dumps({"stable": True, "key_frames_requested": [0, 1, 2], "forward_frames": 3})
    (tmp_path / "params.json").write_text(json.dumps(params))
    bgdo = section_defaults("bgdo")
    bgdo.update(forward_frames=3)
    sim = section_defaults("sim")
    log = logging.getLogger("test.bgdo.nosignal")
    records = []
    handler = logging.Handler()
    handler.emit = records.append
    log.addHandler(handler)
    bgdo_run({"keyframes": str(tmp_path / "forward.h5"), "params": str(tmp_path / "params.json")},
             {"params": str(tmp_path / "out.json")}, {"bgdo": bgdo, "sim": sim, "scene": {}, "device": "cpu"}, log)
    out = json.loads((tmp_path / "out.json").read_text())
    assert out["instances"][0]["E"] == 5.0e4
    rec = out["bgdo"]["instances"][0]
    assert rec["rule"] == "no_signal" and "carries a load" in rec["note"]
    assert all(fr.get("unloaded") for fr in rec["frames"] if fr["frame"] > 0)
    info = out["bgdo"]["no_signal"]["0"]
    c = info["contact"]
    assert c["support"] == "the floor" and c["height_m"] == pytest.approx(0.35, abs=0.01)
    assert c["time_s"] == pytest.approx((2 * c["height_m"] / 9.8) ** 0.5, rel=1e-6)
    assert info["forward_frames_needed"] == int(np.ceil((c["time_s"] + 0.05) * 30 / 0.5)) + 1
    warn = [r.getMessage() for r in records if r.levelno == logging.WARNING]
    assert any("no key frame after frame 0" in w and f"at least {info['forward_frames_needed']} (now 3)" in w
               for w in warn), warn


def test_unloaded_key_frames_are_left_out_of_the_update():
    """A key frame before contact is dropped from the update; a loaded one still counts."""
    import numpy as np

    from physgs_steps.bgdo.update import Scales, bgdo_update, mark_unloaded

    sc = Scales(np.array([5e3]), np.array([5e4]), np.array([0.04]), ["t"], [None], np.array([0.04]))
    row = lambda fr, tau, delta: {"frame": fr, "g_tilde": 0.1, "stress_grad_hat": 0.1, "delta": delta,  # noqa: E731
                                  "tau_norm": tau, "n_exploded": 0, "weight": 1}
    static = np.array([5e3])
    falling = [[row(0, 0.0, 0.0)], [row(1, 3e-3, 1e-10)], [row(2, 3e-3, 1e-8)]]
    assert mark_unloaded(falling, static, sc, 0.01) == [0]
    _, rec = bgdo_update(np.log([5e4]), falling, sc, {"eta_rule": "paper", "eta_coefficient": 0.1, "variant": "algorithm1",
                                                        "max_step": 9.2})
    assert rec[0]["E_after"] == pytest.approx(5e4) and rec[0]["rule"] == "no_signal"
    mixed = [[row(0, 0.0, 0.0)], [row(1, 3e-3, 1e-10)], [row(2, 5e3, 0.04)]]
    assert mark_unloaded(mixed, static, sc, 0.01) == []
    _, rec = bgdo_update(np.log([5e4]), mixed, sc, {"eta_rule": "paper", "eta_coefficient": 0.1, "variant": "algorithm1",
                                                      "max_step": 9.2})
    # only the loaded frame enters the deformation term: delta = target -> log ratio 0, no collapse to ~30 Pa
    assert rec[0]["rule"] == "signals" and 1e4 < rec[0]["E_after"] < 1e5


# ---------------------------------------------------------------------------- resources
def _dry_resources(run_dir, *args) -> dict:
    """rule -> resources of its first job in a dry run (forced)."""
    import re

    p = smk(run_dir, "-n", "--forceall", "results/bear/video.mp4", *args)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    out, rule = {}, None
    for line in p.stdout.splitlines():
        m = re.match(r"^rule (\w+):$", line)
        if m:
            rule = m.group(1)
        elif rule and line.strip().startswith("resources:"):
            out.setdefault(rule, dict(kv.strip().split("=", 1) for kv in line.split(":", 1)[1].split(", ")))
            rule = None
    return out


def test_resource_requests_follow_backend_and_scene_size(run_dir):
    from physgs_steps import config as C
    from physgs_steps import resources as R

    qwen = _dry_resources(run_dir, "--config", "materials={backend: qwen3vl}")
    assert int(qwen["vlm_params"]["mem_mb"]) == 24100 and int(qwen["vlm_params"]["runtime"]) == 60
    res = C.load_config()["resources"]
    assert R.request(res, "vlm_params", 20_000, "prior")["mem_mb"] == 1100  # 1000 + 500 MB per million
    small, big = R.request(res, "bgdo_update", 20_000), R.request(res, "bgdo_update", 1_000_000)
    assert big["mem_mb"] - small["mem_mb"] == pytest.approx(0.98 * 6000, abs=100)
    assert R.request(res, "vlm_params", 0, "prior")["mem_mb"] == 1000
    # a config that sets one entry keeps the others' defaults
    over = {**res, "backends": {"qwen3vl": {"runtime": 90}}, "stages": {"fill": {"mem_mb": 2000}}}
    assert R.request(over, "vlm_params", 0, "qwen3vl") == {"mem_mb": 24000, "runtime": 90}
    assert R.request(over, "final_sim", 0)["runtime"] == 60 and R.request(over, "fill", 0)["mem_mb"] == 2000


def test_scene_size_from_the_file_header(splats_dir):
    from physgs_steps import resources as R

    assert R.scene_gaussians({"source": str(splats_dir / "ranrandy_udon_point_cloud4.ply")}) == 2153
    assert R.scene_gaussians({"source": str(splats_dir / "swiftgraphics_lastchance.splat")}) == 14831
    assert R.scene_gaussians({"source": "builtin:bear", "builtin": {"n_gaussians": 5000}}) == 5000
    assert R.scene_gaussians({"source": "no/such/file.ply"}) is None


# ---------------------------------------------------------------------------- extreme geometry
def test_a_tenth_of_a_millimetre_object_ends_stable_or_says_what_to_change(tmp_path):
    """sim.domain_size 2e-4 m: the jelly needs ~40k substeps per frame. The forward run explodes
    with a message naming the substeps, dx and the fix; BGDO lowers E to what the solver can
    integrate and warns that it left the material's range. With sim.max_substeps 32 that E
    (0.03 Pa) cannot carry the speck's weight, and falling it crosses 27 cells per substep: the final
    run stops saying to raise sim.max_substeps (with 256 it ends stable at 1.8 Pa)."""
    import json
    import logging

    import h5py
    import numpy as np

    from physgs_steps import simulate
    from physgs_steps.bgdo import run as bgdo_run
    from physgs_steps.config import section_defaults
    from physgs_steps.runtime import write_json

    rng = np.random.default_rng(0)
    x = np.asarray([0.42, 0.42, 0.3]) + 0.16 * rng.random((800, 3))
    with h5py.File(tmp_path / "particles.h5", "w") as f:
        f["x"], f["label"] = x.astype(np.float32), np.zeros(len(x), np.int32)
        f["filled"], f["vol"] = np.zeros(len(x), bool), np.full(len(x), 0.16 ** 3 / len(x), np.float32)
        f.attrs["n_gaussians"], f.attrs["n_instances"] = len(x), 1
    params = {"instances": [{"label": 0, "name": "speck", "material": "jelly", "elasticity": "fixed_corotated",
                             "plasticity": "identity", "E": 5.0e4, "nu": 0.3, "density": 1000.0,
                             "plasticity_params": {}, "velocity": [0.0, 0.0, 0.0]}], "backend": "prior", "history": []}
    write_json(tmp_path / "params.json", params)
    sim = section_defaults("sim")
    sim.update(n_grid=16, n_frames=4, backend="cpu", domain_size=2e-4, max_substeps=32)
    bgdo = section_defaults("bgdo")
    cfg = {"sim": sim, "scene": {"dynamics": {}}, "bgdo": {"key_frames": bgdo["key_frames"], "forward_frames": 3},
           "device": "cpu"}
    log = logging.getLogger("test.tiny")
    records = []
    handler = logging.Handler()
    handler.emit = records.append
    log.addHandler(handler)
    ins = {"particles": str(tmp_path / "particles.h5"), "params": str(tmp_path / "params.json")}
    res = simulate.run_forward(ins, {"keyframes": str(tmp_path / "forward.h5")}, cfg, log)
    assert not res["stable"]
    msg = " ".join(r.getMessage() for r in records if r.levelno == logging.WARNING)
    assert "dx = sim.domain_size / n_grid = 1.25e-05 m" in msg and "raise sim.max_substeps" in msg, msg
    bgdo_run({"keyframes": str(tmp_path / "forward.h5"), "params": ins["params"]}, {"params": str(tmp_path / "p1.json")},
             {"bgdo": bgdo, "sim": sim, "scene": {}, "device": "cpu"}, log)
    p1 = json.loads((tmp_path / "p1.json").read_text())
    assert p1["instances"][0]["E"] < 1e4 and p1["bgdo"]["instances"][0]["in_band_after"] is False
    msg = " ".join(r.getMessage() for r in records if r.levelno == logging.WARNING)
    assert "leaves jelly's range" in msg and "raise sim.max_substeps or lower sim.n_grid" in msg, msg
    from physgs_steps.errors import SimulationError

    # the speck collapses, leaves the domain or (falling 27 cells per substep onto the floor) blows up:
    # each names the cap
    with pytest.raises(SimulationError, match=r"(cannot carry the load.*But sim\.max_substeps = 32 integrates 'speck' "
                                              r"only up to E = |(left the simulation domain|NaN).*"
                                              r"sim\.max_substeps = 32 lets a particle move at most ).*"
                                              r"raise sim\.max_substeps"):
        simulate.run_final({**ins, "params": str(tmp_path / "p1.json")}, {"frames": str(tmp_path / "final.h5")},
                           cfg, log)


def test_stage_profile_folder(tmp_path, monkeypatch):
    """PHYSGS_PROFILE_DIR: each run of a stage leaves its cProfile statistics (numbered) and logs
    the costliest functions; a failing stage still leaves its profile."""
    import pstats

    from physgs_steps import runtime

    prof_dir = tmp_path / "prof"
    monkeypatch.setenv(runtime.PROFILE_ENV, str(prof_dir))

    def busy_part():
        return sum(i * i for i in range(20000))

    def stage(inputs, outputs, cfg, log):
        return {"value": busy_part()}

    log = tmp_path / "log.txt"
    for _ in range(2):
        runtime.run_stage("cluster", stage, {}, {}, {}, str(log))
    files = sorted(p.name for p in prof_dir.iterdir())
    assert files == ["cluster-0.prof", "cluster-1.prof"]
    names = {f[2] for f in pstats.Stats(str(prof_dir / "cluster-1.prof")).stats}
    assert "busy_part" in names
    assert "profile of stage cluster" in log.read_text()

    def broken(inputs, outputs, cfg, log):
        raise ValueError("boom")

    with pytest.raises(SystemExit):
        runtime.run_stage("fill", broken, {}, {}, {}, str(log))
    assert (prof_dir / "fill-0.prof").is_file()
