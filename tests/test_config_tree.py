"""Dotted names for nested configs (jstarid.config_tree), on SGM's grouped Config."""

from __future__ import annotations

import dataclasses

import pytest

import jstarid as js
from jstarid.algorithms import base, sgm
from jstarid.config_tree import differences, nested, replace_at, value_at, with_fields
from jstarid.experiment import with_overrides


def test_dotted_names_set_a_group_field_and_keep_the_rest():
    cfg = sgm.Config.for_camera(js.camera_preset("tetra3_test"))  # tolerances scaled off the defaults
    out = with_fields(cfg, {"verify.retries": 0, "screen.fraction": 0.5, "max_error_deg": 0.2})
    assert (out.verify.retries, out.screen.fraction, out.max_error_deg) == (0, 0.5, 0.2)
    assert out.verify == dataclasses.replace(cfg.verify, retries=0)
    assert out.screen == dataclasses.replace(cfg.screen, fraction=0.5)
    assert out.subgraph == cfg.subgraph and out.finishing == cfg.finishing
    assert replace_at(cfg, "verify.retries", 0).verify.retries == 0
    assert value_at(out, "screen.fraction") == 0.5


def test_a_bool_for_a_group_switches_it_and_keeps_its_scaled_tolerances():
    cfg = sgm.Config.for_camera(js.camera_preset("tetra3_test"))
    assert cfg.screen.tol_deg != sgm.Screen().tol_deg  # scaled with the pixel
    off = with_overrides(cfg, ["screen=false", "subgraph=true"])
    assert off.screen == dataclasses.replace(cfg.screen, on=False)
    assert off.subgraph == dataclasses.replace(cfg.subgraph, on=True)
    framed = js.engine.default_config("sgm", camera=js.camera_preset("tetra3_test"), frames=True)
    assert framed.subgraph.on and framed.subgraph.tol_deg == cfg.subgraph.tol_deg


def test_fields_of_one_group_are_validated_together():
    """A floor raised above the old cap and the cap raised with it is one valid change, in either order."""
    cfg = sgm.Config()
    for order in ({"verify.floor_deg": 0.5, "verify.cap_deg": 0.6},
                  {"verify.cap_deg": 0.6, "verify.floor_deg": 0.5}):
        out = with_fields(cfg, order)
        assert (out.verify.floor_deg, out.verify.cap_deg) == (0.5, 0.6)
    with pytest.raises(ValueError, match="floor_deg"):
        with_fields(cfg, {"verify.floor_deg": 0.5})


def test_unknown_names_are_refused_with_the_dotted_name_they_became():
    cfg = sgm.Config()
    with pytest.raises(ValueError, match=r"did you mean 'verify\.retries'"):
        with_overrides(cfg, ["verify_retries=0"])
    with pytest.raises(ValueError, match=r"did you mean 'matching\.prune'"):
        with_fields(cfg, {"prune": False})
    with pytest.raises(ValueError, match=r"did you mean 'ladder\.whole_circle'"):
        with_fields(cfg, {"focal_search_whole_circle": False})
    with pytest.raises(ValueError, match=r"did you mean 'subgraph\.tol_deg'"):  # not screen.tol_deg
        with_fields(cfg, {"subgraph_tol_deg": 0.1})
    with pytest.raises(ValueError, match="no field 'nope'"):
        with_fields(cfg, {"verify.nope": 1})
    with pytest.raises(ValueError, match="not a nested config"):
        with_fields(cfg, {"c.x": 1})
    with pytest.raises(TypeError, match=r"screen\.on"):
        sgm.Config(screen=False)
    with pytest.raises(TypeError, match="read its .on"):  # code written for the flat bool
        bool(cfg.verify)


def test_a_group_from_a_mapping_as_read_from_json():
    cfg = sgm.Config(verify={"retries": 1}, screen={"on": False})
    assert cfg.verify == sgm.Verify(retries=1) and cfg.screen == sgm.Screen(on=False)
    assert nested(sgm.Verify, cfg.verify, "verify") is cfg.verify
    with pytest.raises(TypeError, match="no field"):
        sgm.Config(verify={"retry": 1})
    assert with_overrides(cfg, ['verify={"k": 3.0}']).verify == sgm.Verify(k=3.0)


def test_paper_algorithm_turns_off_the_extensions_field_by_field():
    """``paper_algorithm`` sets the leaves ``Config.paper()`` changes and keeps what a camera chose."""
    cfg = sgm.Config.for_camera(js.camera_preset("tetra3_test"))
    paper = base.paper_algorithm(cfg)
    assert not (paper.verify.on or paper.screen.on or paper.subgraph.on)
    assert paper.leftover_tol_deg is None and paper.finishing == sgm.Config.paper().finishing
    assert paper.verify.cap_deg == cfg.verify.cap_deg and paper.radius_deg == cfg.radius_deg
    assert differences(sgm.Config(), sgm.Config.paper()) == {
        "screen.on": False, "leftover_tol_deg": None, "verify.on": False,
        **{f"finishing.{k}": v for k, v in differences(sgm.Config().finishing,
                                                          sgm.Config.paper().finishing).items()}}


def test_a_grid_over_a_group_field():
    entries = js.grid("sgm", **{"screen.fraction": [0.5, 0.7]})
    assert [e.config.screen.fraction for e in entries] == [0.5, 0.7]
    with pytest.raises(ValueError, match="did you mean"):
        js.grid("sgm", screen_fraction=[0.5])
