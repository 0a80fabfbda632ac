"""The suite's own set-up (``tests/conftest.py``): which XLA emitter a test's programs are built with."""

import os

import pytest
from conftest import CLASSIC_EMITTER


@pytest.mark.production_numerics
def test_a_production_numerics_test_is_built_with_the_default_emitter():
    assert CLASSIC_EMITTER not in os.environ["XLA_FLAGS"].split()


def test_files_that_share_programs_are_one_unit_of_work():
    """Under ``--dist loadfile`` the files of one ``SHARED_PROGRAMS`` group go to one worker; every
    other file is its own unit."""
    from conftest import SHARED_PROGRAMS, unit_of_work

    groups = {}
    for path, group in SHARED_PROGRAMS.items():
        groups.setdefault(group, set()).add(unit_of_work(f"{path}::test_one[a-b]"))
    assert groups and all(len(units) == 1 for units in groups.values())
    assert unit_of_work("tests/test_wcs.py::test_two[x::y]") == "tests/test_wcs.py"
