"""Centroid files (:mod:`jstarid.centroid_files`): the tables, line layout and JSON a user writes."""

import json
from pathlib import Path

import numpy as np
import pytest

from jstarid.centroid_files import read_centroid_set, read_centroids


def test_csv_scene_column_header_and_comments(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text("scene,x,y,mag  # my tracker\n0,1,2,3.5\n1,5,6,4\n0,3,4,2.5\n")
    xy, mag = read_centroids(path)
    np.testing.assert_array_equal(xy[0], [[1, 2], [3, 4]])
    np.testing.assert_array_equal(mag[0], [3.5, 2.5])
    np.testing.assert_array_equal(xy[1], [[5, 6]])


def test_text_without_magnitudes_split_by_blank_lines(tmp_path):
    path = tmp_path / "c.txt"
    path.write_text("1 2\n3 4\n\n\n5 6\n")
    xy, mag = read_centroids(path)
    assert len(xy) == 2 and mag == [None, None]
    np.testing.assert_array_equal(xy[1], [[5, 6]])


@pytest.mark.parametrize("data", [
    [[1, 2, 3], [4, 5, 6]],
    {"x": [1, 4], "y": [2, 5], "mag": [3, 6]},
    {"scenes": [[[1, 2, 3], [4, 5, 6]]]},
])
def test_json_forms(tmp_path, data):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(data))
    xy, mag = read_centroids(path)
    np.testing.assert_array_equal(xy[0], [[1, 2], [4, 5]])
    np.testing.assert_array_equal(mag[0], [3, 6])


@pytest.mark.parametrize("name, text, match", [
    ("a.csv", "  \n", "empty"), ("b.csv", "1,2,3\n1,2\n", "line 2"),
    ("c.csv", "1,2,nan\n", "finite"), ("d.json", "[[]]", "scene 0"),
    ("e.json", '{"x": [1], "y": [1, 2]}', "equal lengths"), ("f.json", "[]", "no centroids"),
])
def test_malformed_files(tmp_path, name, text, match):
    (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=match):
        read_centroids(tmp_path / name)


ORESAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "oresat"
ORESAT_EXTRA = ("ra_deg_j2000", "dec_deg_j2000", "hip_sep_arcsec", "anet_flux", "anet_resid_px")


def _write(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    return tmp_path / name


def test_columns_read_by_name_in_any_order_and_case(tmp_path):
    a = read_centroid_set(_write(tmp_path, "a.csv", "image,x,y,mag,hip\nf1,1,2,3.5,10\nf2,5,6,4,-1\n"
                                                    "f1,3,4,2.5,11\n"))
    b = read_centroid_set(_write(tmp_path, "b.tsv", "HIP\tVmag\tY\tX\tFrame\n10\t3.5\t2\t1\tf1\n"
                                                    "-1\t4\t6\t5\tf2\n11\t2.5\t4\t3\tf1\n"))
    for found in (a, b):
        assert found.labels == ("f1", "f2") and found.labelled
        np.testing.assert_array_equal(found.xy[0], [[1, 2], [3, 4]])
        np.testing.assert_array_equal(found.mag[0], [3.5, 2.5])
        np.testing.assert_array_equal(found.hip[0], [10, 11])
        np.testing.assert_array_equal(found.hip[1], [-1])


def test_y_x_order_and_a_hip_column_that_is_not_a_magnitude(tmp_path):
    found = read_centroid_set(_write(tmp_path, "yx.csv", "y,x,mag\n2,1,3\n"))
    np.testing.assert_array_equal(found.xy[0], [[1, 2]])
    found = read_centroid_set(_write(tmp_path, "hip.csv", "x y hip\n1 2 32349\n3 4 -1\n"))
    assert found.mag == (None,)
    np.testing.assert_array_equal(found.hip[0], [32349, -1])


def test_flux_becomes_a_relative_magnitude(tmp_path):
    found = read_centroid_set(_write(tmp_path, "f.csv", "x,y,flux\n0,0,100\n1,1,10\n2,2,0\n3,3,\n"))
    np.testing.assert_allclose(found.mag[0], [-5, -2.5, -1.5, -1.5])  # not measured: faintest + 1
    both = read_centroid_set(_write(tmp_path, "g.csv", "x,y,flux,mag\n0,0,100,7\n"))
    np.testing.assert_array_equal(both.mag[0], [7])  # the magnitude wins


@pytest.mark.parametrize("text, match", [
    ("x,y,mag,ra\n1,2,3,4\n", "unknown column 'ra'.*hpmag"),
    ("x,mag\n1,2\n", "no 'y' column"),
    ("x,y,mag,vmag\n1,2,3,4\n", "'mag' and 'vmag' both"),
    ("x,y,hip\n1,2,3.5\n", "line 2: a true id"),
    ("x,y,flux\n1,2,0\n", "no positive flux"),
    ("x,y\n1,2,3\n", "line 2: expected 2 values"),
    ("1,2,3,4\n", "line 1: expected x, y"),
])
def test_bad_tables(tmp_path, text, match):
    with pytest.raises(ValueError, match=match):
        read_centroid_set(_write(tmp_path, "bad.csv", text))


def test_ignored_columns(tmp_path):
    path = _write(tmp_path, "c.csv", "x,y,RA,dec\n1,2,3,4\n")
    np.testing.assert_array_equal(read_centroid_set(path, ignore=("ra", "DEC")).xy[0], [[1, 2]])


def test_the_line_layout(tmp_path):
    path = _write(tmp_path, "set.txt", "1 2 3.5 4 5 6.5\n10 -1\n\n7,8,1.0,9,10,2.0,11,12,3.0\n1,2,3\n")
    found = read_centroid_set(path)
    assert found.labels == ("0", "1")
    np.testing.assert_array_equal(found.xy[0], [[1, 2], [4, 5]])
    np.testing.assert_array_equal(found.mag[1], [1, 2, 3])
    np.testing.assert_array_equal(found.hip[0], [10, -1])
    one = read_centroid_set(_write(tmp_path, "one.txt", "1 2 3\n42\n"), format="lines")
    np.testing.assert_array_equal(one.hip[0], [42])
    with pytest.raises(ValueError, match="lines 1–2: .* got 6 values, then 3"):
        read_centroid_set(_write(tmp_path, "bad.txt", "1 2 3 4 5 6\n1 2 3\n"))
    with pytest.raises(ValueError, match="without its line of true ids"):
        read_centroid_set(_write(tmp_path, "odd.txt", "1 2 3 4 5 6\n"))


def test_json_true_ids(tmp_path):
    path = _write(tmp_path, "c.json", json.dumps({"x": [1, 4], "y": [2, 5], "mag": [3, 6], "hip": [7, -1]}))
    np.testing.assert_array_equal(read_centroid_set(path).hip[0], [7, -1])
    with pytest.raises(ValueError, match="Hipparcos numbers"):
        read_centroid_set(_write(tmp_path, "d.json", json.dumps({"x": [1], "y": [2], "hip": [1.5]})))


def test_scenes_brightest_first_with_truth_rows(tmp_path):
    import jstarid as js

    cat = js.load_catalog(5.5)
    hips = cat.hip[:2]
    found = read_centroid_set(_write(tmp_path, "c.csv", f"x,y,mag,hip\n1,2,5,{hips[1]}\n3,4,1,{hips[0]}\n"
                                                        "5,6,3,-1\n"))
    np.testing.assert_array_equal(found.brightest_first().hip[0], [hips[0], -1, hips[1]])
    scenes = found.scenes(capacity=2, catalog=cat)
    np.testing.assert_array_equal(np.asarray(scenes.xy[0]), [[3, 4], [5, 6]])
    np.testing.assert_array_equal(np.asarray(scenes.truth[0]), [0, -1])
    assert bool(scenes.overflow[0])
    np.testing.assert_array_equal(np.asarray(found.scenes().truth), -1)


@pytest.mark.skipif(not (ORESAT / "exp1000" / "truth" / "stars.csv").exists(), reason="no OreSat data")
def test_a_real_labelled_file():
    path = ORESAT / "exp1000" / "truth" / "stars.csv"
    with pytest.raises(ValueError, match="unknown column 'ra_deg_j2000'"):
        read_centroid_set(path)
    found = read_centroid_set(path, ignore=ORESAT_EXTRA)
    assert found.labels == tuple(f"{k}.png" for k in range(1, 9)) and found.labelled
    assert sum(len(x) for x in found.xy) == 150 and all(np.isfinite(m).all() for m in found.mag)
