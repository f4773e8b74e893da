"""Tests of physgs_steps.scene_io: INRIA .ply read/write, antimatter15 .splat read, bad input."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from physgs_steps import load_gaussians, save_gaussians
from physgs_steps.errors import InputError
from physgs_steps.gaussians import SH_C0, GaussianScene
from physgs_steps.scene_io import load_gaussians as load_with_log

DATA = Path(__file__).resolve().parent / "data"
CORE = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
        "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


# ---------------------------------------------------------------------------- helpers
def random_scene(n: int, degree: int, extras: bool, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    ex = {}
    if extras:
        ex = {"label": rng.integers(-1, 7, n).astype(np.int32),
              "filled": rng.random(n) < 0.3,
              "gt_label": rng.integers(0, 3, n).astype(np.int32),
              "weight": rng.random(n).astype(np.float32)}
    return GaussianScene(means=rng.normal(size=(n, 3)), log_scales=rng.normal(size=(n, 3)) - 3,
                         quats=q, opacity_logits=rng.normal(size=n) * 3,
                         sh=rng.normal(size=(n, (degree + 1) ** 2, 3)), extras=ex)


def write_ply(path: Path, fields: dict, fmt: str = "binary_little_endian", count: int | None = None,
              extra_props: list[str] = (), truncate: int = 0) -> Path:
    """Write a PLY by hand: fields {name: [N] array} in order, written in their dtypes."""
    names = list(fields)
    n = len(fields[names[0]]) if names else 0
    end = ">" if fmt == "binary_big_endian" else "<"
    dtype = np.dtype([(k, end + np.asarray(v).dtype.str[1:]) for k, v in fields.items()])
    ply_names = {"f4": "float", "f8": "double", "i4": "int", "u1": "uchar", "i2": "short"}
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {n if count is None else count}"]
    lines += [f"property {ply_names[dtype[k].str[1:]]} {k}" for k in names] + list(extra_props)
    lines.append("end_header")
    data = np.empty(n, dtype)
    for k in names:
        data[k] = fields[k]
    raw = ("\n".join(lines) + "\n").encode() + data.tobytes()
    path.write_bytes(raw[: len(raw) - truncate])
    return path


def core_fields(n: int = 5, rest: int = 0, seed: int = 1) -> dict:
    rng = np.random.default_rng(seed)
    f = {k: rng.normal(size=n).astype(np.float32) for k in CORE[:10]}
    q = rng.normal(size=(n, 4)).astype(np.float32)
    f.update({f"rot_{i}": q[:, i] for i in range(4)})
    for i in range(rest):
        f[f"f_rest_{i}"] = rng.normal(size=n).astype(np.float32)
    return f


def assert_same(a: GaussianScene, b: GaussianScene) -> None:
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x.view(np.uint32), y.view(np.uint32)), f"{name} not bit-exact"
    assert list(a.extras) == list(b.extras)
    for k in a.extras:
        assert a.extras[k].dtype == b.extras[k].dtype, k
        assert np.array_equal(a.extras[k], b.extras[k]), k


# ---------------------------------------------------------------------------- round trip
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("extras", [False, True])
def test_roundtrip_bit_exact(tmp_path, degree, extras):
    scene = random_scene(257, degree, extras, seed=degree)
    p = tmp_path / "s.ply"
    save_gaussians(scene, p)
    back = load_gaussians(p)
    assert back.sh_degree == degree
    assert_same(scene, back)
    p2 = tmp_path / "s2.ply"
    save_gaussians(back, p2)
    assert p.read_bytes() == p2.read_bytes()


def test_written_header_is_inria_layout(tmp_path):
    scene = random_scene(4, 3, True)
    p = tmp_path / "s.ply"
    save_gaussians(scene, p)
    header = p.read_bytes().split(b"end_header\n")[0].decode()
    props = [line.split()[1:] for line in header.splitlines() if line.startswith("property")]
    names = [n for _, n in props]
    assert "format binary_little_endian 1.0" in header
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:62] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    types = dict((n, t) for t, n in props)
    assert (types["label"], types["filled"], types["gt_label"], types["weight"]) == ("int", "uchar", "int", "float")
    assert not list(tmp_path.glob(".*part*")), "atomic write left a temporary file"


def test_f_rest_is_channel_major(tmp_path):
    n, k = 3, 4  # degree 1: f_rest_0..2 red coefficients 1..3, 3..5 green, 6..8 blue
    f = core_fields(n, rest=9)
    p = write_ply(tmp_path / "a.ply", f)
    s = load_gaussians(p)
    for c in range(3):
        for j in range(1, k):
            assert np.array_equal(s.sh[:, j, c], f[f"f_rest_{c * (k - 1) + j - 1}"])
        assert np.array_equal(s.sh[:, 0, c], f[f"f_dc_{c}"])


def test_extras_types_and_normals_dropped(tmp_path):
    f = core_fields(4)
    f = {"x": f.pop("x"), "y": f.pop("y"), "z": f.pop("z"), "nx": np.zeros(4, np.float32), **f}
    f["label"] = np.array([0, 1, -1, 2], np.int32)
    f["filled"] = np.array([0, 1, 1, 0], np.uint8)
    f["red"] = np.array([0, 200, 255, 3], np.uint8)
    f["conf"] = np.array([0.5, 1, 2, 3], np.float64)
    f["part"] = np.array([1, 2, 3, 4], np.int16)
    s = load_gaussians(write_ply(tmp_path / "e.ply", f))
    assert list(s.extras) == ["label", "filled", "red", "conf", "part"]
    assert s.extras["label"].dtype == np.int32 and s.extras["label"].tolist() == [0, 1, -1, 2]
    assert s.extras["filled"].dtype == np.bool_ and s.extras["filled"].tolist() == [False, True, True, False]
    assert s.extras["red"].dtype == np.int32 and s.extras["red"].tolist() == [0, 200, 255, 3]
    assert s.extras["conf"].dtype == np.float32 and s.extras["part"].dtype == np.int32


def test_save_rejects_non_scalar_extra(tmp_path):
    scene = random_scene(3, 0, False)
    scene.extras["normal"] = np.zeros((3, 3), np.float32)
    with pytest.raises(InputError, match="normal.*shape"):
        save_gaussians(scene, tmp_path / "x.ply")
    assert not (tmp_path / "x.ply").exists()


# ---------------------------------------------------------------------------- shared data
SHARED_COUNTS = {
    "gshairlod_donut_fused.ply": (45624, 0),
    "ranrandy_udon_point_cloud4.ply": (2153, 3),
    "loadersgl_train-1000.ply": (1000, 3),
    "swiftgraphics_winter_fountain.splat": (93713, 0),
    "swiftgraphics_lastchance.splat": (14831, 0),
}


@pytest.mark.parametrize("name", sorted(SHARED_COUNTS))
def test_shared_files_load(splats_dir, name):
    s = load_gaussians(splats_dir / name)
    n, degree = SHARED_COUNTS[name]
    assert s.n == n and s.sh_degree == degree
    for arr in (s.means, s.log_scales, s.quats, s.opacity_logits, s.sh):
        assert np.isfinite(arr).all()
    assert np.allclose(np.linalg.norm(s.quats, axis=1), 1.0, atol=1e-5)
    lo, hi = s.bounds()
    assert (hi - lo).min() > 0 and (hi - lo).max() < 100
    assert s.scales.max() < 10 and 0 < s.opacities.min() and s.opacities.max() <= 1
    colors = s.base_colors()
    assert colors.std() > 0.01  # not all one colour


def test_shared_bounds_match_sources(splats_dir):
    # SOURCES.md: donut bbox ~0.21 x 0.21 x 0.095; lastchance bbox ~0.7 x 1.0 x 0.9
    for name, size in [("gshairlod_donut_fused.ply", [0.21, 0.21, 0.095]),
                       ("swiftgraphics_lastchance.splat", [0.7, 1.0, 0.9])]:
        lo, hi = load_gaussians(splats_dir / name).bounds()
        np.testing.assert_allclose(hi - lo, size, rtol=0.06, err_msg=name)


# ---------------------------------------------------------------------------- .splat
def write_splat(path: Path, pos, scale, rgba, rot) -> Path:
    rec = np.zeros(len(pos), dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("r", "u1", 4)])
    rec["p"], rec["s"], rec["c"], rec["r"] = pos, scale, rgba, rot
    path.write_bytes(rec.tobytes())
    return path


def test_splat_conversion(tmp_path):
    p = write_splat(tmp_path / "a.splat",
                    pos=[[1, 2, 3], [0, 0, 0]], scale=[[2, 0.5, 1], [0.1, 0.1, 0.1]],
                    rgba=[[255, 0, 128, 255], [10, 20, 30, 0]], rot=[[255, 128, 128, 128], [128, 0, 128, 128]])
    s = load_gaussians(p)
    assert s.n == 2 and s.sh_degree == 0
    np.testing.assert_allclose(s.means[0], [1, 2, 3])
    np.testing.assert_allclose(s.log_scales[0], np.log([2, 0.5, 1]), rtol=1e-6)
    np.testing.assert_allclose(s.sh[0, 0], (np.array([255, 0, 128]) / 255 - 0.5) / SH_C0, atol=1e-6)
    np.testing.assert_allclose(s.base_colors()[0], [1, 0, 128 / 255], atol=1e-6)
    np.testing.assert_allclose(s.quats, [[1, 0, 0, 0], [0, -1, 0, 0]], atol=1e-7)
    assert np.isfinite(s.opacity_logits).all()
    assert s.opacities[1] < 0.01 and s.opacities[0] > 0.99


# ---------------------------------------------------------------------------- bad input
def expect_error(path: Path, *fragments: str) -> InputError:
    with pytest.raises(InputError) as info:
        load_gaussians(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"
    return info.value


def test_truncated_ply(tmp_path):
    expect_error(write_ply(tmp_path / "t.ply", core_fields(10), truncate=7), "truncated", "10 vertices")


def test_header_count_larger_than_data(tmp_path):
    expect_error(write_ply(tmp_path / "t.ply", core_fields(10), count=11), "truncated")


def test_header_count_smaller_than_data(tmp_path):
    """Loading only the declared vertices would silently drop the rest: an error (issue #19)."""
    expect_error(write_ply(tmp_path / "t.ply", core_fields(10), count=8), "2 more whole vertices",
                 "smaller than the data")


def test_double_positions_beyond_float32_are_an_error(tmp_path):
    """A double that overflows float32 is finite in the file but inf after the cast."""
    f = core_fields(6)
    f["x"] = f["x"].astype(np.float64)
    f["x"][4] = 1e39
    expect_error(write_ply(tmp_path / "t.ply", f), "'x': 1 values (first at index 4, 1e+39)", "float32 range")
    f["x"][4] = 3.0e38  # within float32: loads
    assert np.isfinite(load_gaussians(write_ply(tmp_path / "u.ply", f)).means).all()


def test_missing_opacity(tmp_path):
    f = core_fields(3)
    del f["opacity"]
    expect_error(write_ply(tmp_path / "m.ply", f), "['opacity']", "missing")


def test_list_property_rejected(tmp_path):
    p = write_ply(tmp_path / "l.ply", core_fields(0), extra_props=["property list uchar int vertex_indices"])
    expect_error(p, "list property", "vertex_indices")


def test_big_endian_rejected(tmp_path):
    expect_error(write_ply(tmp_path / "b.ply", core_fields(3), fmt="binary_big_endian"), "big-endian")


def test_ascii_mesh_rejected():
    expect_error(DATA / "cube_ascii.ply", "ASCII", "not a binary 3DGS file")


def test_bad_f_rest_count(tmp_path):
    expect_error(write_ply(tmp_path / "r.ply", core_fields(3, rest=5)), "5 f_rest_*", "SH degree")


def test_duplicate_property(tmp_path):
    p = write_ply(tmp_path / "d.ply", core_fields(2), extra_props=["property float x"])
    expect_error(p, "'x' appears twice")


def test_not_a_ply_and_no_header_end(tmp_path):
    p = tmp_path / "n.ply"
    p.write_bytes(b"solid cube\nendsolid\n")
    expect_error(p, "not a PLY file")
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n")
    expect_error(p, "end_header")


@pytest.mark.parametrize("field,value", [("opacity", np.nan), ("f_rest_3", np.inf), ("x", -np.inf)])
def test_non_finite_named(tmp_path, field, value):
    f = core_fields(20, rest=9)
    f[field][[4, 9, 11]] = value
    expect_error(write_ply(tmp_path / "nan.ply", f), "non-finite", f"'{field}': 3 values (first at index 4)")


def test_zero_gaussians(tmp_path):
    expect_error(write_ply(tmp_path / "z.ply", core_fields(0)), "zero gaussians")
    empty = tmp_path / "z.splat"
    empty.write_bytes(b"")
    expect_error(empty, "zero gaussians")


def test_zero_length_quaternion_is_error(tmp_path):
    f = core_fields(8)
    for i in range(4):
        f[f"rot_{i}"][[2, 5]] = 0.0
    expect_error(write_ply(tmp_path / "q.ply", f), "2 zero-length quaternions", "first at index 2")
    p = write_splat(tmp_path / "q.splat", pos=np.zeros((2, 3)), scale=np.ones((2, 3)),
                    rgba=np.full((2, 4), 100), rot=[[255, 128, 128, 128], [128, 128, 128, 128]])
    expect_error(p, "1 zero-length quaternions", "first at index 1")


def test_non_unit_quaternion_normalised_and_logged(tmp_path, caplog):
    f = core_fields(6)
    f["rot_0"][:] = np.float32(1.0)
    f["rot_1"][:], f["rot_2"][:], f["rot_3"][:] = 0.0, 0.0, 0.0
    f["rot_0"][1:3] = 3.0  # two non-unit quaternions, four unit ones
    log = logging.getLogger("test.scene_io")
    with caplog.at_level(logging.INFO, logger="test.scene_io"):
        s = load_with_log(write_ply(tmp_path / "u.ply", f), log=log)
    assert "normalised 2 of 6 quaternions" in caplog.text
    np.testing.assert_array_equal(s.quats, np.tile([1, 0, 0, 0], (6, 1)))


def test_unknown_extension(tmp_path):
    p = tmp_path / "scene.txt"
    p.write_bytes(b"ply\nformat ascii 1.0\n")
    expect_error(p, "unknown 3DGS file format '.txt'", "rename it to .ply")
    q = tmp_path / "scene.obj"
    q.write_bytes(b"v 0 0 0\n")
    expect_error(q, "unknown 3DGS file format '.obj'")


def test_missing_file(tmp_path):
    expect_error(tmp_path / "absent.ply", "file not found")


def test_splat_size_not_multiple_of_32(tmp_path):
    p = write_splat(tmp_path / "s.splat", pos=np.zeros((3, 3)), scale=np.ones((3, 3)),
                    rgba=np.full((3, 4), 100), rot=np.full((3, 4), 200))
    p.write_bytes(p.read_bytes()[:-5])
    expect_error(p, "91 bytes", "multiple of the 32-byte")


def test_splat_non_finite_and_ply_content(tmp_path):
    p = write_splat(tmp_path / "s.splat", pos=[[0, np.nan, 0], [0, 0, 0]], scale=np.ones((2, 3)),
                    rgba=np.full((2, 4), 100), rot=np.full((2, 4), 200))
    expect_error(p, "'pos': 1 values (first at index 0)")
    q = write_ply(tmp_path / "real.splat", core_fields(2))
    expect_error(q, "is a PLY file")


def test_splat_negative_scale(tmp_path):
    p = write_splat(tmp_path / "s.splat", pos=np.zeros((2, 3)), scale=[[1, 1, 1], [1, -1, 1]],
                    rgba=np.full((2, 4), 100), rot=np.full((2, 4), 200))
    expect_error(p, "negative scales", "first at index 1")
