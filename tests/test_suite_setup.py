"""The suite's own set-up (``tests/conftest.py``): which XLA emitter a test's programs are built with."""

import os

import pytest
from conftest import CLASSIC_EMITTER


@pytest.mark.production_numerics
def test_a_production_numerics_test_is_built_with_the_default_emitter():
    assert CLASSIC_EMITTER not in os.environ["XLA_FLAGS"].split()
