import ast
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid.geometry.small_linalg import cholesky_solve, largest_singular_value, nearest_rotation

PACKAGE = Path(js.__file__).resolve().parent


def _nearest_rotation_f64(a):
    """Reference: Markley's U diag(1, 1, det U det V) Vᵀ by NumPy's float64 SVD."""
    u, _, vt = np.linalg.svd(a.astype(np.float64))
    d = np.linalg.det(u) * np.linalg.det(vt)
    return np.einsum("...ij,...j,...jk->...ik", u, np.stack([np.ones_like(d), np.ones_like(d), d], -1), vt)


def test_largest_singular_value_matches_numpy():
    a = np.random.default_rng(0).normal(size=(2000, 3, 3)).astype(np.float32)
    want = np.linalg.svd(a.astype(np.float64), compute_uv=False)[:, 0]
    np.testing.assert_allclose(np.asarray(largest_singular_value(jnp.asarray(a))), want, rtol=1e-5)
    assert float(largest_singular_value(jnp.zeros((3, 3)))) == 0.0


def test_nearest_rotation_matches_float64_svd_and_is_proper():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(20000, 3, 3)).astype(np.float32)  # half have det < 0
    # and badly conditioned ones: singular values 1, 10⁻², 10⁻⁴ (det > 0)
    u, v = (Rotation.random(200, random_state=rng).as_matrix() for _ in range(2))
    a = np.concatenate([a, np.einsum("bij,j,bkj->bik", u, [1.0, 1e-2, 1e-4], v).astype(np.float32)])
    r = np.asarray(nearest_rotation(jnp.asarray(a)), np.float64)
    np.testing.assert_allclose(r, _nearest_rotation_f64(a), atol=5e-5)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-5)
    gram = np.einsum("bij,bkj->bik", r, r)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), r.shape), atol=1e-5)


def test_nearest_rotation_of_rank_deficient_matrices():
    # rank 2 (Wahba with two stars): unique, and the same as the float64 reference
    x = np.random.default_rng(2).normal(size=(2, 3))
    a = np.outer(x[0], [1.0, 0, 0]) + np.outer(x[1], [0, 0.5, 0])
    r2 = np.asarray(nearest_rotation(jnp.asarray(a, jnp.float32)))
    np.testing.assert_allclose(r2, _nearest_rotation_f64(a), atol=1e-5)
    # rank 0 and 1: not unique; the identity
    np.testing.assert_allclose(np.asarray(nearest_rotation(jnp.zeros((3, 3)))), np.eye(3))
    rank1 = jnp.outer(jnp.array([0.0, 0.6, 0.8]), jnp.array([1.0, 0, 0]))
    np.testing.assert_allclose(np.asarray(nearest_rotation(rank1)), np.eye(3))


def test_wahba_with_one_star_maps_it_exactly():
    # one pair: B has rank 1, and the turn of both mean directions onto +z alone maps it
    ref = jnp.asarray([[0.6, 0.0, 0.8]])
    body = jnp.asarray([[0.0, -0.28, 0.96]])
    c = np.asarray(js.solve_wahba(body, ref, jnp.ones(1)), np.float64)
    np.testing.assert_allclose(c @ np.asarray(ref[0]), np.asarray(body[0]), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(c), 1.0, atol=1e-6)


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
    # 0.07″ measured; the float32 LAPACK SVD of B = Σ w b rᵀ (before the turn onto +z) reaches 0.53″
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


@pytest.mark.production_numerics
def test_results_do_not_depend_on_the_batch():
    # a grid point run in one batch must equal the same point run alone (tests/test_engine.py): bit
    # for bit, whatever the batch shape, as LAPACK's per-matrix kernels were
    rng = np.random.default_rng(6)
    b = 1000
    a = jnp.asarray(rng.normal(size=(b, 3, 3)), jnp.float32)
    body, ref = (jnp.asarray(rng.normal(size=(b, 12, 3)), jnp.float32) for _ in range(2))
    jac = rng.normal(size=(b, 12, 5))
    normal = jnp.asarray(np.einsum("bki,bkj->bij", jac, jac) + 1e-3 * np.eye(5), jnp.float32)
    rhs = jnp.asarray(rng.normal(size=(b, 5)), jnp.float32)
    for fn, args in ((nearest_rotation, (a,)), (js.solve_wahba, (body, ref, jnp.ones((b, 12)))),
                     (cholesky_solve, (normal, rhs))):
        whole = np.asarray(jax.jit(fn)(*args))
        for size in (1, 3, 16, 33):
            parts = [np.asarray(jax.jit(fn)(*(x[s:s + size] for x in args))) for s in range(0, 198, size)]
            np.testing.assert_array_equal(np.concatenate(parts)[:198], whole[:198])
        nested = jax.jit(jax.vmap(jax.vmap(fn)))(*(x.reshape(10, b // 10, *x.shape[1:]) for x in args))
        np.testing.assert_array_equal(np.asarray(nested).reshape(whole.shape), whole)
