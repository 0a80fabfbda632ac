import ast
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid.geometry.small_linalg import cholesky_solve, nearest_rotation, svd3

PACKAGE = Path(js.__file__).resolve().parent


def _nearest_rotation_f64(a):
    """Reference: Markley's U diag(1, 1, det U det V) Vᵀ by NumPy's float64 SVD."""
    u, _, vt = np.linalg.svd(a.astype(np.float64))
    d = np.linalg.det(u) * np.linalg.det(vt)
    return np.einsum("...ij,...j,...jk->...ik", u, np.stack([np.ones_like(d), np.ones_like(d), d], -1), vt)


def _gram(m):
    """Mᵀ M of (B, 3, 3) matrices: the identity where the columns are orthonormal."""
    return np.einsum("bji,bjk->bik", m, m)


def test_svd3_matches_numpy():
    a = np.random.default_rng(0).normal(size=(2000, 3, 3)).astype(np.float32)
    u, s, v = (np.asarray(x, np.float64) for x in svd3(jnp.asarray(a)))
    np.testing.assert_allclose(np.einsum("bij,bj,bkj->bik", u, s, v), a, atol=5e-6)
    np.testing.assert_allclose(np.sort(s)[:, ::-1], np.linalg.svd(a.astype(np.float64), compute_uv=False),
                               atol=5e-6)
    np.testing.assert_allclose(_gram(v), np.broadcast_to(np.eye(3), v.shape), atol=2e-6)
    np.testing.assert_allclose(_gram(u), np.broadcast_to(np.eye(3), u.shape), atol=2e-5)


def test_nearest_rotation_matches_float64_svd_and_is_proper():
    a = np.random.default_rng(1).normal(size=(2000, 3, 3)).astype(np.float32)  # half have det < 0
    r = np.asarray(nearest_rotation(jnp.asarray(a)), np.float64)
    np.testing.assert_allclose(r, _nearest_rotation_f64(a), atol=1e-4)  # ill-conditioned ones included
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-5)
    np.testing.assert_allclose(_gram(np.swapaxes(r, 1, 2)), np.broadcast_to(np.eye(3), r.shape), atol=1e-5)


def test_nearest_rotation_of_rank_deficient_matrices():
    # rank 2 (Wahba with two stars): unique, and the same as the float64 reference
    x = np.random.default_rng(2).normal(size=(2, 3))
    a = np.outer(x[0], [1.0, 0, 0]) + np.outer(x[1], [0, 0.5, 0])
    r2 = np.asarray(nearest_rotation(jnp.asarray(a, jnp.float32)))
    np.testing.assert_allclose(r2, _nearest_rotation_f64(a), atol=1e-5)
    # rank 0 and 1: not unique, but a finite proper rotation (the identity for 0)
    np.testing.assert_allclose(np.asarray(nearest_rotation(jnp.zeros((3, 3)))), np.eye(3))
    rank1 = jnp.outer(jnp.array([0.0, 0.6, 0.8]), jnp.array([1.0, 0, 0]))
    r1 = np.asarray(nearest_rotation(rank1), np.float64)
    np.testing.assert_allclose(np.linalg.det(r1), 1.0, atol=1e-6)
    np.testing.assert_allclose(r1 @ [1.0, 0, 0], [0.0, 0.6, 0.8], atol=1e-6)


def test_wahba_in_a_narrow_field_is_accurate_in_float32():
    # 10 stars within ≈ 5° of the boresight, 4″ of noise: float32 error against SciPy's float64 fit
    rng = np.random.default_rng(3)
    bodies, refs, truth = [], [], []
    for _ in range(200):
        bore = rng.normal(size=3)
        ref = bore / np.linalg.norm(bore) + np.radians(5.0) * rng.normal(size=(10, 3))
        ref /= np.linalg.norm(ref, axis=1, keepdims=True)
        body = Rotation.random(random_state=rng).apply(ref) + 2e-5 * rng.normal(size=ref.shape)
        body /= np.linalg.norm(body, axis=1, keepdims=True)
        bodies.append(body)
        refs.append(ref)
        truth.append(Rotation.align_vectors(body, ref)[0].as_matrix())
    body, ref = (jnp.asarray(np.array(x), jnp.float32) for x in (bodies, refs))
    c = np.asarray(js.solve_wahba(body, ref, jnp.ones((200, 10), jnp.float32)), np.float64)
    err = np.degrees(Rotation.from_matrix(np.einsum("bij,bkj->bik", c, np.array(truth))).magnitude()) * 3600
    # 0.08″ measured; a plain float32 SVD of B = Σ w b rᵀ reaches 0.65″ on these
    assert err.max() < 0.3


def test_cholesky_solve_matches_numpy():
    rng = np.random.default_rng(4)
    for n in (4, 5):
        jac = rng.normal(size=(500, 12, n))
        a = np.einsum("bki,bkj->bij", jac, jac) + 1e-3 * np.eye(n)
        b = rng.normal(size=(500, n))
        x = np.asarray(cholesky_solve(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)), np.float64)
        want = np.linalg.solve(a, b[..., None])[..., 0]
        assert np.max(np.abs(x - want) / np.abs(want).max(axis=1, keepdims=True)) < 1e-3
    # a held parameter (a stiff prior, as the camera fit's) does not spoil the others
    a = np.diag([2.0, 3.0, 1e6]) + 0.1
    x = np.asarray(cholesky_solve(jnp.asarray(a, jnp.float32), jnp.asarray([1.0, 1.0, 1.0], jnp.float32)))
    np.testing.assert_allclose(x, np.linalg.solve(a, [1.0, 1.0, 1.0]), rtol=1e-4, atol=1e-9)
    assert not np.all(np.isfinite(np.asarray(cholesky_solve(-jnp.eye(3), jnp.ones(3)))))


LAPACK = {"svd", "solve", "inv", "det", "slogdet", "eig", "eigh", "eigvals", "eigvalsh", "qr", "cholesky",
          "lstsq", "pinv", "matrix_rank", "lu", "lu_factor", "cho_factor", "cho_solve", "solve_triangular",
          "tridiagonal_solve", "schur", "hessenberg"}


def _lapack_calls(source: str) -> list[str]:
    """``jnp.linalg.<f>``, ``jax.scipy.linalg.<f>`` and ``lax.linalg.<f>`` references in a module."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr in LAPACK:
            owner = ast.unparse(node.value)
            if owner.endswith("linalg") and not owner.startswith(("np.", "numpy.", "scipy.")):
                found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


def test_library_kernels_call_no_lapack():
    # LAPACK's batched calls on XLA:CPU wait for chunks on the pool their caller may occupy: with
    # several host devices every pool thread can wait, a hang (jstarid.geometry.small_linalg)
    assert len(_lapack_calls("jnp.linalg.svd(a)\njax.scipy.linalg.solve(a, b)\nlax.linalg.eigh(a)\n")) == 3
    assert _lapack_calls("np.linalg.svd(a)\njnp.linalg.norm(a)\nscipy.linalg.eigh(a)\n") == []
    offenders = {str(p.relative_to(PACKAGE)): f for p in sorted(PACKAGE.rglob("*.py"))
                 if (f := _lapack_calls(p.read_text()))}
    assert not offenders, f"use jstarid.geometry.small_linalg (or NumPy on the host): {offenders}"
    b = jnp.ones((64, 8, 3), jnp.float32)
    hlo = jax.jit(js.solve_wahba).lower(b, b, jnp.ones((64, 8))).as_text()
    assert "custom_call" not in hlo
