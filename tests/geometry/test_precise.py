"""Geometric products run at full float32 precision on every backend (jstarid.geometry.precise).

On CPU every float32 product is already exact float32, so a numerical test here cannot show a GPU's
TensorFloat-32 default; these tests check the structure instead: (1) no library code outside the RpNet
network spells a product in a way that leaves its precision to the backend, and (2) the traced kernels
carry ``Precision.HIGHEST`` on every ``dot_general``.
"""

import ast
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.algorithms.sgm.matching import principal_eigenvector
from jstarid.geometry import precise

PACKAGE = Path(js.__file__).resolve().parent
# the network's dense layers (trained and folded for inference) keep the default (or bfloat16)
# products on purpose (precise.py docstring)
NETWORK = {PACKAGE / "algorithms" / "rpnet" / "model.py", PACKAGE / "algorithms" / "rpnet" / "inference.py",
           PACKAGE / "geometry" / "precise.py"}
PRODUCTS = {"matmul", "einsum", "dot", "tensordot", "inner", "vdot", "dot_general"}
JAX = {"jnp", "lax", "jax.numpy", "jax.lax"}


def _default_precision_products(source: str) -> list[str]:
    """``@`` operators and ``jnp.<product>`` / ``lax.<product>`` references in a module's source."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.BinOp | ast.AugAssign) and isinstance(node.op, ast.MatMult):
            found.append(f"line {node.lineno}: @")
        if isinstance(node, ast.Attribute) and node.attr in PRODUCTS and ast.unparse(node.value) in JAX:
            found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


def test_library_products_go_through_precise():
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        if path in NETWORK:
            continue
        found = _default_precision_products(path.read_text())
        if found:
            offenders[str(path.relative_to(PACKAGE))] = found
    assert not offenders, f"use jstarid.geometry.precise (or np.matmul on the host): {offenders}"


def test_the_source_check_finds_each_spelling():
    src = "a @ b\nx @= y\njnp.einsum('ij,jk', a, b)\nf = jnp.matmul\njax.lax.dot_general(a, b, d)\n"
    assert len(_default_precision_products(src)) == 5
    assert _default_precision_products("np.matmul(a, b)\nprecise.einsum('i,i', a, b)\n") == []


def _dot_precisions(closed_jaxpr) -> list:
    """The ``precision`` parameter of every dot_general in a jaxpr, sub-jaxprs (loops, conds) included."""
    out = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                out.append(eqn.params["precision"])
            for value in eqn.params.values():
                for sub in value if isinstance(value, tuple | list) else (value,):
                    if hasattr(sub, "eqns"):
                        walk(sub)
                    elif hasattr(sub, "jaxpr") and hasattr(sub.jaxpr, "eqns"):
                        walk(sub.jaxpr)

    walk(closed_jaxpr.jaxpr)
    return out


def _all_highest(precisions) -> bool:
    return bool(precisions) and all(
        p is not None and all(q == jax.lax.Precision.HIGHEST for q in p) for p in precisions)


def test_traced_kernels_request_float32_products():
    rng = np.random.default_rng(0)
    vec = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
    c = jnp.eye(3, dtype=jnp.float32)
    assert _all_highest(_dot_precisions(jax.make_jaxpr(js.solve_wahba)(vec, vec, jnp.ones(5))))
    assert _all_highest(_dot_precisions(jax.make_jaxpr(js.attitude_errors_arcsec)(c, c)))
    k = jnp.asarray(rng.uniform(size=(12, 12)), jnp.float32)
    power = jax.make_jaxpr(lambda m: principal_eigenvector(m, 20, 1e-4))(k)
    assert _all_highest(_dot_precisions(power))
    # and the check itself can fail: a plain product leaves the precision to the backend
    assert not _all_highest(_dot_precisions(jax.make_jaxpr(jnp.matmul)(k, k)))
    assert _all_highest(_dot_precisions(jax.make_jaxpr(precise.matmul)(k, k)))


def test_small_matmul_is_the_product_without_a_dot():
    rng = np.random.default_rng(3)
    for shape_a, shape_b in [((7, 3), (3, 11)), ((2, 5, 3), (3, 4)), ((6, 2), (2, 3)), ((4, 1), (1, 5))]:
        a, b = rng.normal(size=shape_a), rng.normal(size=shape_b)
        got = precise.small_matmul(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32))
        assert got.shape == np.matmul(a, b).shape and got.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(got), a @ b, rtol=0, atol=1e-6 * np.abs(a @ b).max())
    jaxpr = jax.make_jaxpr(precise.small_matmul)(jnp.ones((5, 3)), jnp.ones((3, 9)))
    assert _dot_precisions(jaxpr) == []  # products and sums: exact float32 on any backend
    for bad_a, bad_b in [((5, 4), (4, 2)), ((5, 3), (2, 2)), ((5, 3), (3,))]:
        with pytest.raises(ValueError, match="small_matmul"):
            precise.small_matmul(jnp.ones(bad_a), jnp.ones(bad_b))
