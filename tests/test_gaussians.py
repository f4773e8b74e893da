import numpy as np
import pytest

from physgs_steps.gaussians import GaussianScene, quat_to_rotmat, rotmat_to_quat


def _scene(n=10, k=4, seed=0):
    rng = np.random.default_rng(seed)
    return GaussianScene(
        means=rng.normal(size=(n, 3)),
        log_scales=rng.normal(size=(n, 3)) - 3,
        quats=rng.normal(size=(n, 4)),
        opacity_logits=rng.normal(size=n),
        sh=rng.normal(size=(n, k, 3)),
        extras={"label": np.arange(n, dtype=np.int32)},
    )


def test_quat_rotmat_roundtrip():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    r = quat_to_rotmat(q)
    assert np.allclose(r @ np.swapaxes(r, 1, 2), np.eye(3), atol=1e-5)
    assert np.allclose(np.linalg.det(r), 1, atol=1e-5)
    assert np.allclose(rotmat_to_quat(r), q, atol=1e-5)


def test_covariance_is_rsrt():
    s = _scene()
    cov = s.covariances()
    r = s.rotation_matrices()
    d = np.einsum("nij,nj,nkj->nik", r, s.scales**2, r)
    assert np.allclose(cov, d, rtol=1e-4, atol=1e-8)
    assert np.all(np.linalg.eigvalsh(cov.astype(np.float64)) > 0)


def test_shape_checks_and_sh_degree():
    s = _scene(k=16)
    assert s.sh_degree == 3
    with pytest.raises(ValueError, match="sh"):
        GaussianScene(s.means, s.log_scales, s.quats, s.opacity_logits, np.zeros((10, 5, 3)))
    with pytest.raises(ValueError, match="quats"):
        GaussianScene(s.means, s.log_scales, s.quats[:, :3], s.opacity_logits, s.sh)
    with pytest.raises(ValueError, match="extras"):
        GaussianScene(s.means, s.log_scales, s.quats, s.opacity_logits, s.sh, {"label": np.zeros(3)})


def test_subset_and_concat_pad_sh():
    a, b = _scene(5, k=1), _scene(7, k=9, seed=2)
    c = GaussianScene.concat([a, b])
    assert c.n == 12 and c.sh.shape == (12, 9, 3)
    assert np.array_equal(c.sh[:5, 1:], np.zeros((5, 8, 3), np.float32))
    sub = c.subset(np.arange(12) >= 5)
    assert np.array_equal(sub.means, b.means) and np.array_equal(sub.extras["label"], b.extras["label"])
