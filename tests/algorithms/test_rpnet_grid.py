"""RpNet training grids (jstarid.algorithms.rpnet.grid): G models in one vmapped step."""

import dataclasses

import jax
import numpy as np
import pytest

import jstarid as js
from jstarid.algorithms import rpnet
from jstarid.algorithms.rpnet import data, train

SEEDS, DAE_LRS, CLF_LRS = [1, 1, 2], [3e-3, 1e-3, 3e-3], [3e-3, 1e-2, 3e-3]


@pytest.fixture(scope="module")
def setup():
    cat = js.load_catalog(3.0)
    cam = js.Camera.from_fov(1024, 1024, 60.0, mag_limit=3.0)
    training = rpnet.Training(dae_lr=3e-3, clf_lr=3e-3, dae_steps=40, clf_steps=40, batch_size=128,
                              eval_every=20, eval_size=128, sim_capacity=64, seed=1)
    cfg = rpnet.Config(rho_deg=20.0, e_deg=0.1, gen_widths=(64, 128), clf_width=64, training=training,
                       pair_tol_px=5.0, match_tol_px=5.0, batch_chunk=16)
    rows = rpnet.guide_rows(cat, cfg)
    grid = rpnet.train_grid(cat, cam, cfg, rows, seeds=SEEDS, dae_lrs=DAE_LRS, clf_lrs=CLF_LRS,
                            progress=False)
    return cat, cam, cfg, rows, grid


@pytest.mark.production_numerics
def test_a_member_is_the_single_training_run_at_its_rates(setup):
    """Member 1 shares train()'s data seed (seed 1) at rates other than the config's: it is train() at
    its own rates (to float32 rounding of the batched products; fc3's bias, which BatchNorm cancels,
    drifts freely and is left out)."""
    cat, cam, cfg, rows, grid = setup
    tables = data.build_tables(cat, cam, cfg, rows)
    g = 1
    t = dataclasses.replace(cfg.training, dae_lr=DAE_LRS[g], clf_lr=CLF_LRS[g])
    alone, history = train.train(cat, cam, dataclasses.replace(cfg, training=t), rows, progress=False)
    member = rpnet.member_variables(grid, g)
    np.testing.assert_allclose(grid.dae_eval[:, g], [e[1] for e in history["dae_eval"]], rtol=1e-4)
    np.testing.assert_allclose(grid.clf_eval[:, g], [e[1] for e in history["clf_eval"]],
                               atol=2.5 / cfg.training.eval_size)
    for name in ("generator", "decoder"):
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=0, atol=1e-4 * np.abs(b).max()),
                     member[name], alone[name])
    np.testing.assert_allclose(member["classifier"]["params"]["fc4"]["kernel"],
                               alone["classifier"]["params"]["fc4"]["kernel"], atol=1e-3)
    a, b = (np.asarray(train.predict_logits(v, tables.clean, config=cfg, n_classes=len(rows)))
            for v in (member, alone))
    np.testing.assert_allclose(a, b, rtol=0, atol=0.02 * np.abs(b).max())
    # another seed is another initialisation: the networks differ
    k0, k2 = (np.asarray(rpnet.member_variables(grid, g)["generator"]["fc1"]["kernel"]) for g in (0, 2))
    assert np.abs(k2 - k0).max() > 0.01


def test_grid_result_layout_and_learning(setup):
    _, _, cfg, rows, grid = setup
    assert grid.size == 3 and grid.best_accuracy.shape == (3,)
    assert grid.dae_eval.shape == (2, 3) and list(grid.dae_eval_steps) == [20, 40]
    assert grid.clf_eval.shape == (2, 3) and grid.clf_eval_family.shape == (2, 3, 4)
    np.testing.assert_allclose(grid.clf_eval_family.mean(-1), grid.clf_eval, atol=1e-6)  # equal quarters
    np.testing.assert_allclose(grid.best_accuracy, grid.clf_eval.max(0))  # early stop keeps the best
    assert np.all(grid.best_accuracy > 5.0 / len(rows))  # well above chance after 40 + 40 steps
    assert np.all(grid.dae_eval[-1] < grid.dae_eval[0])
    kernel = grid.variables["classifier"]["params"]["fc4"]["kernel"]
    assert kernel.shape == (3, cfg.clf_width, len(rows))


# Slow: it compiles the whole identification for this grid's network (≈ 35 s on 2 cores); the fast
# suite checks that a member is the single training run (above), whose databases identify elsewhere.
@pytest.mark.slow
def test_member_database_identifies(setup):
    cat, cam, cfg, rows, grid = setup
    db = rpnet.database_from_variables(cat, cam, cfg, rpnet.member_variables(grid, 1))
    scenes = js.simulate(jax.random.key(4), cat, cam, js.NoiseConfig(), capacity=48,
                         boresight_ids=np.asarray(rows[:32]))
    result = rpnet.identify(db, scenes)
    report = js.evaluate(scenes, result, "rpnet", camera=cam)
    assert report["misid_rate"] == 0.0


def test_member_database_refuses_wrong_shapes(setup):
    cat, cam, cfg, rows, grid = setup
    with pytest.raises(ValueError, match="shapes"):
        rpnet.database_from_variables(cat, cam, dataclasses.replace(cfg, clf_width=32),
                                      rpnet.member_variables(grid, 0))
    with pytest.raises(IndexError):
        rpnet.member_variables(grid, 3)


def test_grid_members_is_a_product_and_bad_settings_are_refused(setup):
    seeds, dae, clf = rpnet.grid_members(seeds=(0, 1), dae_lrs=(1e-3,), clf_lrs=(1e-3, 3e-3, 1e-2))
    assert seeds.tolist() == [0, 0, 0, 1, 1, 1]
    np.testing.assert_allclose(clf, [1e-3, 3e-3, 1e-2] * 2)
    np.testing.assert_allclose(dae, [1e-3] * 6)
    with pytest.raises(ValueError, match="empty"):
        rpnet.grid_members(seeds=())
    cat, cam, cfg, rows, _ = setup
    for kwargs in (dict(seeds=[0, 1], dae_lrs=[1e-3], clf_lrs=[1e-3]),
                   dict(seeds=[0], dae_lrs=[-1e-3], clf_lrs=[1e-3]),
                   dict(seeds=[0], dae_lrs=[1e-3], clf_lrs=[np.nan]),
                   dict(seeds=[0.5], dae_lrs=[1e-3], clf_lrs=[1e-3])):
        with pytest.raises(ValueError):
            rpnet.train_grid(cat, cam, cfg, rows, progress=False, **kwargs)
