"""The finishing stage (jstarid.finishing): its config, and the ladder + camera check it runs."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid import camera_fit
from jstarid.algorithms import mlv, rpnet, sgm
from jstarid.experiment import with_overrides
from jstarid.finishing import Finishing, finish

SCALE = 1.015  # the true focal length / the nominal one


@pytest.fixture(scope="module")
def world():
    """Catalog, nominal camera, scenes taken with a focal length 1.5 % off, and their true ids."""
    catalog, nominal = js.load_catalog(6.0), js.camera_preset("sgm2022")
    true = dataclasses.replace(nominal, f_px=nominal.f_px * SCALE)
    scenes = js.simulate(jax.random.key(3), catalog, true, js.NoiseConfig(position_sigma_px=0.5),
                         batch_size=12)
    truth = np.where(np.asarray(scenes.valid), np.asarray(scenes.truth), -1).astype(np.int32)
    return catalog, nominal, scenes, truth


def _first_pass(truth):
    """An algorithm's first answer: the even scenes named (true ids), the odd ones failed."""
    ok = np.arange(truth.shape[0]) % 2 == 0
    ids = np.where(ok[:, None], truth, -1)
    return js.Identification(ids=jnp.asarray(ids), ok=jnp.asarray(ok),
                             attitude=jnp.full((truth.shape[0], 3, 3), jnp.nan))


def _rerun_naming(truth, calls):
    """A rerun that names every scene it is given with its true ids, recording the rows."""
    def rerun(moved, rows):
        calls.append(np.asarray(rows))
        ids = truth[np.asarray(rows)]
        return js.Identification(ids=jnp.asarray(ids), ok=jnp.ones(len(rows), bool),
                                 attitude=jnp.full((len(rows), 3, 3), jnp.nan))
    return rerun


def test_finish_equals_the_ladder_then_the_check(world):
    """``finish`` is search_focal on the unsolved scenes, then check_identification with the stage's
    settings; ``laddered`` marks the scenes the ladder solved, and only unsolved scenes are rerun."""
    catalog, camera, scenes, truth = world
    first = _first_pass(truth)
    config = Finishing(studentized=True, max_focal_error=0.05, hypotheses=0)  # search: test_hypotheses
    calls = []
    got, laddered, *_ = finish(first, scenes, config, rerun=_rerun_naming(truth, calls), camera=camera,
                               star_vectors=catalog.unit_vectors, star_mags=catalog.mag, max_tol_px=12.0)
    unsolved = ~np.asarray(first.ok)
    assert calls and all(np.all(unsolved[rows]) for rows in calls)
    np.testing.assert_array_equal(laddered, unsolved)

    laddered_ref = camera_fit.search_focal(_rerun_naming(truth, []), first, scenes, camera,
                                           config.focal_search)
    want = camera_fit.check_identification(catalog.unit_vectors, camera, scenes, laddered_ref,
                                           max_scale_error=0.05, max_tol_px=12.0, star_mags=catalog.mag,
                                           studentized=True)
    np.testing.assert_array_equal(np.asarray(got.ids), np.asarray(want.ids))
    np.testing.assert_array_equal(np.asarray(got.ok), np.asarray(want.ok))
    np.testing.assert_allclose(np.asarray(got.focal_scale), np.asarray(want.focal_scale), equal_nan=True)
    # the check fits the true focal length from the names (the scenes' own 1.5 %)
    scale = np.asarray(got.focal_scale)[np.asarray(got.ok)]
    assert scale.size and np.all(np.abs(scale - SCALE) < 2e-3)


def test_finishing_off_returns_the_first_answer(world):
    catalog, camera, scenes, truth = world
    first = _first_pass(truth)
    calls = []
    got, laddered, searched, overflow, claimed = finish(first, scenes, Finishing.off(),
                                                        rerun=_rerun_naming(truth, calls), camera=camera,
                                                        star_vectors=catalog.unit_vectors)
    assert got is first and not calls and not laddered.any() and not searched.any() and not overflow.any()
    np.testing.assert_array_equal(claimed, np.asarray(first.ok))


def test_check_alone_sets_focal_scale_and_leaves_failures(world):
    """``focal_search=()``: no rerun; the claimed scenes are checked, the failed ones stay failed."""
    catalog, camera, scenes, truth = world
    first = _first_pass(truth)
    calls = []
    got, laddered, *_ = finish(first, scenes, Finishing(focal_search=(), hypotheses=0, max_false_match=1.0),
                              rerun=_rerun_naming(truth, calls), camera=camera,
                              star_vectors=catalog.unit_vectors)
    assert not calls and not laddered.any()
    ok = np.asarray(got.ok)
    assert not ok[1::2].any() and ok[::2].all()
    assert np.all(np.isfinite(np.asarray(got.focal_scale)[::2]))


@pytest.mark.parametrize("factors", [(0.4,), (1.0, float("nan")), (2.5,)])
def test_finishing_rejects_bad_factors(factors):
    with pytest.raises(ValueError, match="focal_search"):
        Finishing(focal_search=factors)


def test_finishing_rejects_a_bad_scale_error():
    with pytest.raises(ValueError, match="max_focal_error"):
        Finishing(max_focal_error=0.5)


def test_finishing_from_a_mapping():
    assert Finishing.coerce({"focal_search": [0.99], "fit_focal": False}) == Finishing(
        focal_search=(0.99,), fit_focal=False)
    with pytest.raises(TypeError, match="no field"):
        Finishing.coerce({"fit_focus": False})
    with pytest.raises(TypeError):
        Finishing.coerce(True)


@pytest.mark.parametrize("module", [mlv, rpnet, sgm], ids=["mlv", "rpnet", "sgm"])
def test_every_seed_config_holds_one_finishing_config(module):
    """One nested config in every seed algorithm: on by default, off in the paper's algorithm; a
    mapping (a config read from JSON) becomes a Finishing."""
    assert isinstance(module.Config().finishing, Finishing)
    assert module.Config().finishing.fit_focal and module.Config().finishing.focal_search
    assert module.Config.paper().finishing == Finishing.off()
    assert module.Config(finishing={"fit_focal": False}).finishing == Finishing(fit_focal=False)
    flat = {"fit_focal", "focal_search", "max_focal_error", "fit_focal_studentized", "max_false_match"}
    assert not flat & {f.name for f in dataclasses.fields(module.Config)}  # no copies of the stage's fields


def test_the_confirmation_needs_the_magnitudes(world):
    catalog, camera, scenes, truth = world
    with pytest.raises(ValueError, match="needs star_mags"):
        finish(_first_pass(truth), scenes, Finishing(focal_search=(), hypotheses=0), rerun=None,
               camera=camera, star_vectors=catalog.unit_vectors)


@pytest.mark.parametrize("value", [0.0, 1.5, float("nan")])
def test_finishing_rejects_a_bad_false_match_threshold(value):
    with pytest.raises(ValueError, match="max_false_match"):
        Finishing(max_false_match=value)


def test_one_false_match_threshold_decides_at_1e_2_and_at_1e_3_for_sgm():
    """Every seed algorithm's claims stand at false-match probability ≤ 1e-2 (SGM's ≤ 1e-3); the
    papers' report it and decide nothing by it."""
    assert mlv.Config().finishing.max_false_match == rpnet.Config().finishing.max_false_match == 1e-2
    assert sgm.Config().finishing.max_false_match == 1e-3
    assert Finishing.off().max_false_match == 1.0


def test_sgm_studentizes_its_check_mlv_and_rpnet_do_not():
    assert sgm.Config().finishing.studentized
    assert not mlv.Config().finishing.studentized and not rpnet.Config().finishing.studentized


def test_overrides_reach_the_nested_config():
    config = with_overrides(sgm.Config(), ["finishing.focal_search=[]", "finishing.fit_focal=false"])
    assert config.finishing == Finishing(focal_search=(), fit_focal=False, studentized=True,
                                         max_false_match=1e-3)
    with pytest.raises(ValueError, match="no field 'fit_focus'"):
        with_overrides(sgm.Config(), ["finishing.fit_focus=false"])
    with pytest.raises(ValueError, match="not a nested config"):
        with_overrides(sgm.Config(), ["c.x=1"])
