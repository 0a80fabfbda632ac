import numpy as np
import pytest

import jstarid as js
from jstarid import catalog as catalog_module


def test_star_count_before_double_removal():
    cat = js.load_catalog(6.0, double_mode="keep")
    assert 5000 <= len(cat) <= 5200  # docs/conventions.md §2: about 5,100 stars at V ≤ 6.0


def test_double_removal_drops_a_few_stars(catalog6):
    keep = js.load_catalog(6.0, double_mode="keep")
    assert 0 < len(keep) - len(catalog6) < 100
    # no two stars of the default catalog are closer than the threshold
    from scipy.spatial import cKDTree

    pairs = cKDTree(catalog6.unit_vectors).query_pairs(2 * np.sin(np.radians(0.05) / 2))
    assert not pairs


def test_merge_mode_combines_flux():
    keep = js.load_catalog(6.0, double_mode="keep", double_sep_deg=0.1)
    merged = js.load_catalog(6.0, double_mode="merge", double_sep_deg=0.1)
    dropped = js.load_catalog(6.0, double_mode="drop", double_sep_deg=0.1)
    assert len(merged) == len(dropped) < len(keep)
    # a merged pair is at least as bright as its brighter member
    common = np.intersect1d(merged.hip, dropped.hip)
    m = merged.mag[np.searchsorted(merged.hip[np.argsort(merged.hip)], common)]
    assert np.all(np.isfinite(m))
    assert merged.mag.sum() < dropped.mag.sum()


@pytest.mark.parametrize("hip,v_true", [(91262, 0.03), (11767, 1.98), (69673, -0.05),
                                        (37279, 0.34), (97649, 0.76), (24608, 0.08)])
def test_v_magnitudes_of_bright_stars(catalog6, hip, v_true):
    # Vega, Polaris, Arcturus, Procyon, Altair, Capella
    row = catalog6.row_of_hip(hip)[0]
    assert row >= 0
    assert abs(float(catalog6.mag[row]) - v_true) < 0.1


def test_v_from_hp_reference_points():
    # Bessell (2000) Table 2 values: V − Hp = −0.011 at B−V ≈ 0, −0.155 at B−V ≈ 0.88
    assert js.v_from_hp(5.0, -0.005) == pytest.approx(4.989, abs=1e-3)
    assert js.v_from_hp(5.0, 0.878) == pytest.approx(4.845, abs=1e-3)


def test_rows_consistent(catalog6):
    c = catalog6
    assert c.unit_vectors.shape == (len(c), 3)
    ref = np.stack([np.cos(c.ra) * np.cos(c.dec), np.sin(c.ra) * np.cos(c.dec), np.sin(c.dec)], -1)
    np.testing.assert_allclose(c.unit_vectors, ref, atol=1e-12)
    assert np.all(np.diff(c.mag) >= 0)  # brightest first
    assert np.all(c.mag <= 6.0)
    # simulation list: catalog rows first (same order), then fainter stars
    n = len(c)
    np.testing.assert_array_equal(c.sim_row[:n], np.arange(n))
    assert np.all(c.sim_row[n:] == -1)
    assert np.all(c.sim_mag[n:] > 6.0) and np.all(c.sim_mag <= 7.0)
    np.testing.assert_array_equal(c.row_of_hip(c.hip[[5, 17]]), [5, 17])
    assert c.row_of_hip(999_999_999)[0] == -1


def test_a_deeper_simulation_list_keeps_the_rows(catalog6):
    assert catalog_module.with_simulation_depth(catalog6, 6.5) is catalog6  # V 7.0 reaches it
    deep = catalog_module.with_simulation_depth(catalog6, 8.0)
    for name in ("hip", "mag", "unit_vectors"):
        np.testing.assert_array_equal(getattr(deep, name), getattr(catalog6, name))
    assert deep.sim_mag.max() <= 8.0 < deep.sim_mag.max() + 0.05 and len(deep.sim_mag) > len(catalog6.sim_mag)
    full = catalog_module.with_simulation_depth(catalog6, 20.0)  # capped at Hipparcos's depth
    assert full.settings["mag_limit"] + full.settings["sim_margin"] == catalog_module.FULL_DEPTH


def test_cache_written_and_invalidated(tmp_path, monkeypatch):
    monkeypatch.setenv("JSTARID_CACHE", str(tmp_path))
    a = js.load_catalog(4.0)
    files = sorted(tmp_path.glob("catalog-*.npz"))
    assert len(files) == 1
    b = js.load_catalog(4.0)  # from cache
    np.testing.assert_array_equal(a.hip, b.hip)
    c = js.load_catalog(4.0, double_sep_deg=0.2)  # another setting → another file
    assert len(sorted(tmp_path.glob("catalog-*.npz"))) == 2
    assert c.settings != a.settings
    # a corrupt cache file is rebuilt, not trusted
    files[0].write_bytes(b"not an npz")
    d = js.load_catalog(4.0)
    np.testing.assert_array_equal(a.hip, d.hip)


def test_proper_motion_moves_barnards_star():
    j1991 = js.load_catalog(10.0, double_mode="keep", sim_margin=0.0)
    j2026 = js.load_catalog(10.0, double_mode="keep", sim_margin=0.0, epoch=2026.25)
    r0, r1 = j1991.row_of_hip(87937)[0], j2026.row_of_hip(87937)[0]  # Barnard's star, 10.4″/yr
    sep = np.degrees(np.arccos(np.clip(j1991.unit_vectors[r0] @ j2026.unit_vectors[r1], -1, 1)))
    assert sep * 3600 == pytest.approx(10.39 * 35.0, rel=0.02)


def test_bad_catalog_settings():
    with pytest.raises(ValueError):
        js.load_catalog(np.nan)
    with pytest.raises(ValueError):
        js.load_catalog(6.0, double_mode="average")
    with pytest.raises(ValueError):
        js.load_catalog(6.0, double_sep_deg=-1)
    with pytest.raises(ValueError):
        js.load_catalog(6.0, epoch=26.0)


def test_v_transformation_table_monotone_pieces():
    # The table itself is the documented transformation: it must stay sorted for interpolation.
    assert np.all(np.diff(catalog_module._BV_TABLE) > 0)


def test_cache_files_are_written_through_private_temporary_names(tmp_path):
    """Concurrent builders of one cache file (xdist workers, distributed processes) never share a
    temporary file: each has its own, beside the target, with the target's suffix."""
    from jstarid.catalog import temporary_path

    target = tmp_path / "mlv-abc.npz"
    a, b = temporary_path(target), temporary_path(target)
    assert a != b and a.parent == b.parent == tmp_path and a.suffix == b.suffix == ".npz"
    assert a.name.startswith(".mlv-abc.")


def test_load_or_build_builds_once_then_loads(tmp_path):
    """The one cache rule of derived arrays: built and written once (no temporary file left), then
    read; ``path=None`` builds every time; ``load``/``save`` take other file formats."""
    calls = []

    def build():
        calls.append(1)
        return {"rows": np.arange(4, dtype=np.int32), "seconds": np.float64(0.5)}

    path = tmp_path / "sub" / "thing-0123.npz"  # a folder not there yet
    built, loaded = catalog_module.load_or_build(path, build)
    assert not loaded and calls == [1] and path.exists()
    again, loaded = catalog_module.load_or_build(path, build)
    assert loaded and calls == [1]
    assert set(again) == {"rows", "seconds"} and again["rows"].dtype == np.int32
    np.testing.assert_array_equal(again["rows"], built["rows"])
    assert [p.name for p in path.parent.iterdir()] == ["thing-0123.npz"]
    assert catalog_module.read_arrays(path, ["rows"]).keys() == {"rows"}
    _, loaded = catalog_module.load_or_build(None, build)
    assert not loaded and calls == [1, 1]
    text = tmp_path / "note.txt"
    value, loaded = catalog_module.load_or_build(text, lambda: "hello", load=lambda p: p.read_text(),
                                                 save=lambda p, v: p.write_text(v))
    assert (value, loaded) == ("hello", False) and text.read_text() == "hello"
    assert catalog_module.load_or_build(text, build, load=lambda p: p.read_text()) == ("hello", True)
