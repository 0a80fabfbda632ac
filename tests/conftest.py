"""Shared fixtures. Several host devices are forced so sharding code paths are exercised on CPU."""

import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=4")

import jax  # noqa: E402
import pytest  # noqa: E402

import jstarid as js  # noqa: E402


@pytest.fixture(scope="session")
def catalog6():
    """Hipparcos V ≤ 6.0 with the default close-pair handling."""
    return js.load_catalog(6.0)


@pytest.fixture(scope="session")
def sgm_camera():
    return js.camera_preset("sgm2022")


@pytest.fixture
def key():
    return jax.random.key(0)
