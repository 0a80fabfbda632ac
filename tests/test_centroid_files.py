"""Centroid files (:mod:`jstarid.centroid_files`): the CSV and JSON forms a user writes."""

import json

import numpy as np
import pytest

from jstarid.centroid_files import read_centroids


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
