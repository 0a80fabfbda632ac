"""Fixtures shared by the algorithm tests."""

import pytest

import jstarid as js
from jstarid.algorithms import sgm


@pytest.fixture(scope="module")
def setup5():
    """SGM on a V ≤ 5 catalog: small graphs (≈ 6 vertices), so Algorithm 1 can be replayed quickly."""
    cat = js.load_catalog(5.0)
    cam = js.camera_preset("sgm2022", mag_limit=5.0)
    return cat, cam, sgm.build_database(cat, cam, sgm.Config(), progress=False)
