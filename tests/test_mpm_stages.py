"""Stages forward_sim and final_sim on a tiny two-instance scene: artifact formats
(docs/CONTRACTS.md), stability handling, input errors."""
from __future__ import annotations

import copy
import json
import logging

import h5py
import numpy as np
import pytest

from physgs_steps import simulate
from physgs_steps.errors import InputError, SimulationError
from physgs_steps.runtime import write_json

LOG = logging.getLogger("test.mpm.stages")


def _sim_defaults() -> dict:
    try:
        from physgs_steps.config import section_defaults

        return section_defaults("sim")
    except Exception:  # schema loader unavailable: the documented defaults
        return {"backend": "auto", "n_grid": 32, "domain_size": 1.0, "fps": 30.0, "n_frames": 150,
                "dt_mode": "adaptive", "cfl": 0.5, "substep_dt": 1e-4, "dt_min": 1e-6, "max_substeps": 200,
                "sort_particles": True, "stability": {"j_min": 0.05, "j_max": 20.0, "max_speed": 100.0},
                "compression": "none", "compression_level": 1, "rest": {"enabled": True, "speed": 0.01, "duration": 0.5}}


def _scene(tmp_path, E_can: float = 2.0e5):
    """Two blocks (a 'bear' of gaussians + filled particles, a 'can'), particles.h5 + params.json."""
    rng = np.random.default_rng(0)
    xs, labels, filled = [], [], []
    for lab, (lo, hi), n_g in ((0, ((0.35, 0.4, 0.3), (0.5, 0.6, 0.45)), 900), (1, ((0.55, 0.45, 0.3), (0.65, 0.55, 0.4)), 300)):
        lo, hi = np.asarray(lo), np.asarray(hi)
        surf = lo + (hi - lo) * rng.random((n_g, 3))
        inner = lo + (hi - lo) * rng.random((n_g // 2, 3))
        xs += [surf, inner]
        labels += [np.full(n_g, lab), np.full(n_g // 2, lab)]
        filled += [np.zeros(n_g, bool), np.ones(n_g // 2, bool)]
    x = np.concatenate(xs)
    label = np.concatenate(labels).astype(np.int32)
    fl = np.concatenate(filled)
    order = np.r_[np.flatnonzero(~fl), np.flatnonzero(fl)]  # gaussians first (rows of scene.ply)
    x, label, fl = x[order], label[order], fl[order]
    vol = np.full(len(x), 0.15 * 0.2 * 0.15 / 1350, np.float32)
    parts = tmp_path / "particles.h5"
    with h5py.File(parts, "w") as f:
        f["x"] = x.astype(np.float32)
        f["label"] = label
        f["filled"] = fl
        f["vol"] = vol
        f.attrs["n_gaussians"] = int((~fl).sum())
        f.attrs["n_instances"] = 2
    params = {"instances": [
        {"label": 0, "name": "bear", "material": "jelly", "elasticity": "fixed_corotated", "plasticity": "identity",
         "E": 5.0e4, "nu": 0.3, "density": 1050.0, "plasticity_params": {}, "velocity": [0.5, 0.0, 0.0]},
        {"label": 1, "name": "can", "material": "metal", "elasticity": "fixed_corotated", "plasticity": "identity",
         "E": E_can, "nu": 0.3, "density": 2700.0, "plasticity_params": {}, "velocity": [0.0, 0.0, 0.0]},
    ], "backend": "prior", "prompt": "test", "history": []}
    pj = tmp_path / "params.json"
    write_json(pj, params)
    return {"particles": str(parts), "params": str(pj)}


def _cfg(**sim) -> dict:
    s = copy.deepcopy(_sim_defaults())
    s.update({"n_grid": 16, "n_frames": 7, "backend": "cpu"}, **sim)
    return {"sim": s, "scene": {"dynamics": {"ground": None}}, "bgdo": {"key_frames": [0.0, 0.5, 1.0],
                                                                      "forward_frames": None}, "device": "cpu"}


def test_forward_writes_key_frames(tmp_path):
    inputs = _scene(tmp_path)
    out = tmp_path / "forward.h5"
    summary = simulate.run_forward(inputs, {"keyframes": str(out)}, _cfg(), LOG)
    assert summary["stable"] and summary["key_frames"] == [0, 3, 6]
    with h5py.File(out) as f:
        P = len(f["particles/label"])
        assert set(f["keyframes"]) == {"0", "3", "6"}
        for k in ("0", "3", "6"):
            g = f["keyframes"][k]
            assert g["x"].shape == (P, 3) and g["v"].shape == (P, 3)
            assert g["C"].shape == (P, 3, 3) and g["F"].shape == (P, 3, 3)
            assert g["x"].dtype == np.float32
            assert g.attrs["frame"] == int(k) and g.attrs["time"] == pytest.approx(int(k) / 30.0)
            assert 0 < g.attrs["dt"] <= 1 / 30
        x0 = f["keyframes/0/x"][()]
        with h5py.File(inputs["particles"]) as p:
            assert np.allclose(x0, p["x"][()], atol=1e-6)  # domain units, input row order
        v0 = f["keyframes/0/v"][()]
        assert np.allclose(v0[f["particles/label"][()] == 0], [0.5, 0, 0], atol=1e-6)  # params velocity, domain units/s
        assert np.all(f["keyframes/6/x"][()][:, 2] < x0[:, 2])  # everything fell
        stats = json.loads(f.attrs["stats"])
        assert stats["stable"] and len(stats["substeps_per_frame"]) == 6
        assert json.loads(f.attrs["params"])["instances"][0]["name"] == "bear"
        assert json.loads(f.attrs["sim_config"])["sim"]["n_grid"] == 16


def test_forward_keeps_last_stable_state_when_unstable(tmp_path):
    inputs = _scene(tmp_path, E_can=3.0e9)
    out = tmp_path / "forward.h5"
    summary = simulate.run_forward(inputs, {"keyframes": str(out)}, _cfg(max_substeps=30), LOG)
    assert not summary["stable"]
    with h5py.File(out) as f:
        stats = json.loads(f.attrs["stats"])
        assert not stats["stable"] and "in instance 'can'" in stats["failure"] and "max_substeps" in stats["failure"]
        info = stats["failure_info"]
        assert info["over_cfl"] and info["over_cfl_instances"] == ["can"]
        assert info["cfl_per_instance"]["can"] > 1.0 > info["cfl_per_instance"]["bear"]
        frames = sorted(int(k) for k in f["keyframes"])
        last = f["keyframes"][str(frames[-1])]
        assert frames[-1] == stats["last_stable_frame"] < 6
        assert list(last.attrs["substitute_for"]) == [k for k in (0, 3, 6) if k > frames[-1]]
        for k in frames:
            for name in ("x", "v", "C", "F"):
                assert np.isfinite(f["keyframes"][str(k)][name][()]).all()


def test_final_writes_carrier_particles_per_frame(tmp_path):
    from physgs_steps.final_frames import FORMAT, FinalFrames
    from physgs_steps.metrics import physical_figures
    from physgs_steps.physical import figures_from_file

    inputs = _scene(tmp_path)
    out = tmp_path / "final.h5"
    simulate.run_final(inputs, {"frames": str(out)}, _cfg(), LOG)
    with h5py.File(inputs["particles"]) as p:
        n_g = int(p.attrs["n_gaussians"])
        x_in = p["x"][:n_g]
    with h5py.File(out) as f:  # no 'driver' in this particles.h5: the non-filled rows are stored
        assert f.attrs["format"] == FORMAT
        assert f["x"].shape == (7, n_g, 3) and f["F_minus_I"].shape == (7, n_g, 3, 3)
        assert f["x"].chunks == (1, n_g, 3) and f["x"].compression is None and f["F_minus_I"].dtype == np.float16
        assert np.array_equal(f["particle_index"][()], np.arange(n_g))
        assert np.array_equal(f["frame_row"][()], np.arange(7))  # nothing rests while falling
        stats = json.loads(f.attrs["stats"])
        for key in ("substeps_per_frame", "simulate_seconds", "peak_rss_mb", "stable", "max_cfl", "cfl_capped_frames",
                    "rest", "held_frames"):
            assert key in stats
    with FinalFrames(out) as fr:
        assert np.allclose(fr.time, np.arange(7) / 30.0)
        assert np.allclose(fr.x(0), x_in, atol=1e-6)
        assert all(np.isfinite(fr.x(t)).all() and np.isfinite(fr.F(t)).all() for t in range(7))
        frame, lo, hi = fr.motion_box  # no transform.json given: the sim frame
        assert frame == "sim"
        assert (lo <= x_in.min(0) + 0.02).all() and (hi >= x_in.max(0) - 0.02).all()
    # the figures accumulated while simulating are those of the stored frames (up to float16 F)
    stored, again = physical_figures(str(out)), figures_from_file(str(out))
    assert stored["checks"] == again["checks"] and stored["checks"]["moved"]
    assert stored["max_displacement"]["value"] == pytest.approx(again["max_displacement"]["value"], rel=1e-6)
    assert stored["det_F_max"]["value"] == pytest.approx(again["det_F_max"]["value"], abs=3e-3)


def test_final_fails_clearly_and_writes_nothing(tmp_path):
    inputs = _scene(tmp_path, E_can=3.0e9)
    out = tmp_path / "final.h5"
    with pytest.raises(SimulationError, match=r"'can'.*E=3e\+09 Pa.*Lower its E to at most"):
        simulate.run_final(inputs, {"frames": str(out)}, _cfg(max_substeps=30), LOG)
    assert not out.exists() and not list(tmp_path.glob(".final.h5*"))


def test_final_writer_error_fails_the_stage_and_writes_nothing(tmp_path, monkeypatch):
    """A float16 overflow of F - I at frame 3 (an exploded run the stability check let through)
    raised by the writer fails final_sim with the writer's message and leaves no final.h5 and
    no temporary file."""
    from physgs_steps.mpm.solver import MPMSolver

    real = MPMSolver.gather_rows
    calls = []

    def exploding(self, rows):
        xs, Fs = real(self, rows)
        calls.append(1)
        if len(calls) == 4:
            Fs[0] *= 1e6
        return xs, Fs

    monkeypatch.setattr(MPMSolver, "gather_rows", exploding)
    inputs = _scene(tmp_path)
    out = tmp_path / "final.h5"
    with pytest.raises(SimulationError, match=r"frame 3: 1 particles have \|F - I\| >= 65504"):
        simulate.run_final(inputs, {"frames": str(out)}, _cfg(n_frames=6), LOG)
    assert not out.exists() and not list(tmp_path.glob(".final.h5*"))


def test_bad_inputs_name_the_file(tmp_path):
    inputs = _scene(tmp_path)
    params = json.loads(open(inputs["params"]).read())
    params["instances"] = params["instances"][:1]
    write_json(inputs["params"], params)
    with pytest.raises(InputError, match=r"params.json.*label\(s\) \[1\]"):
        simulate.run_final(inputs, {"frames": str(tmp_path / "f.h5")}, _cfg(), LOG)
    params["instances"][0]["nu"] = 0.7
    write_json(inputs["params"], params)
    inputs = _scene(tmp_path)
    p2 = json.loads(open(inputs["params"]).read())
    p2["instances"][1]["E"] = "stiff"
    write_json(inputs["params"], p2)
    with pytest.raises(InputError, match=r"instances\[1\]"):
        simulate.run_final(inputs, {"frames": str(tmp_path / "f.h5")}, _cfg(), LOG)
    inputs = _scene(tmp_path)
    with h5py.File(inputs["particles"], "a") as f:
        x = f["x"][()]
        x[3] = np.nan
        f["x"][...] = x
    with pytest.raises(InputError, match=r"particles.h5.*non-finite"):
        simulate.run_forward(inputs, {"keyframes": str(tmp_path / "k.h5")}, _cfg(), LOG)


def test_load_run_takes_the_highest_bgdo_iteration_and_names_a_missing_run(tmp_path, monkeypatch):
    """simulate.load_run (the micro-benchmarks' loader of a finished run): BGDO's iteration 10
    comes after iteration 2 (numeric, not string order), and a run without outputs is an
    InputError naming the folder."""
    import shutil
    from pathlib import Path

    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # config/ of the repository
    with pytest.raises(InputError, match=r"results/bear.*run the pipeline"):
        simulate.load_run(tmp_path, "bear")
    src = _scene(tmp_path)
    res = tmp_path / "results" / "bear"
    (res / "fill" / "f1").mkdir(parents=True)
    shutil.copy(src["particles"], res / "fill" / "f1" / "particles.h5")
    for it, E in (("it2-aa", 7.0e4), ("it10-bb", 9.0e4), ("it0", 5.0e4)):
        d = res / "sim" / "mpm-x" / it
        d.mkdir(parents=True)
        p = json.loads(open(src["params"]).read())
        p["instances"][0]["E"] = E
        write_json(d / "params.json", p)
    run = simulate.load_run(tmp_path, "bear")
    assert run["materials"][0].E == 9.0e4
    assert run["labels"] == [0, 1] and len(run["parts"]["x"]) == 1800
    assert run["sim"]["n_grid"] > 0 and "dynamics" in run["scene"]
