"""The persistent compilation cache helper (an edge utility: scripts and the CLI call it)."""

import jax
import jax.numpy as jnp
import pytest

import jstarid as js


@pytest.fixture
def restore_jax_cache_config(monkeypatch):
    monkeypatch.delenv("JSTARID_COMPILATION_CACHE", raising=False)  # the suite turns it off (conftest)
    saved = (jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)
    yield
    from jax.experimental.compilation_cache import compilation_cache
    compilation_cache.reset_cache()  # later tests must not write into this test's directory
    js.runtime.program_store.disable_program_store()  # turned on beside the cache
    jax.config.update("jax_compilation_cache_dir", saved[0])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", saved[1])


def test_cache_dir_from_jstarid_cache(tmp_path, monkeypatch, restore_jax_cache_config):
    monkeypatch.setenv("JSTARID_CACHE", str(tmp_path))
    jax.config.update("jax_compilation_cache_dir", None)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)  # JAX's own default
    path = js.enable_compilation_cache()  # by default every executable is kept, the small ones too
    assert path == tmp_path / "xla" and path.is_dir()
    assert jax.config.jax_compilation_cache_dir == str(path)
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0
    assert js.runtime.program_store.program_store_dir() == tmp_path / "programs"


def test_existing_choice_kept_unless_path_given(tmp_path, restore_jax_cache_config):
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
    assert js.enable_compilation_cache() == tmp_path / "mine"
    assert js.enable_compilation_cache(tmp_path / "other") == tmp_path / "other"
    with pytest.raises(ValueError, match="min_compile_time_s"):
        js.enable_compilation_cache(min_compile_time_s=-1.0)


def test_executables_written(tmp_path, restore_jax_cache_config):
    """Compiled functions land in the cache directory, also after a switch to another directory."""
    for name, scale in (("first", 3.0), ("second", 5.0)):
        path = js.enable_compilation_cache(tmp_path / name, min_compile_time_s=0.0)
        jax.jit(lambda x, s=scale: jnp.sin(x) * s + 1.25)(jnp.arange(7.0)).block_until_ready()
        assert any(path.iterdir()), name


def test_environment_turns_it_off(tmp_path, monkeypatch, restore_jax_cache_config):
    jax.config.update("jax_compilation_cache_dir", None)
    js.runtime.program_store.disable_program_store()  # the suite's own store (tests/conftest.py)
    monkeypatch.setenv("JSTARID_COMPILATION_CACHE", "off")
    js.enable_compilation_cache(tmp_path / "never")
    assert jax.config.jax_compilation_cache_dir is None and not (tmp_path / "never").exists()
    assert js.runtime.program_store.program_store_dir() is None
