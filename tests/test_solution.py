"""The one-call path (:func:`jstarid.solve`), catalog depths that follow the field, blends."""

import json
import math

import numpy as np
import pytest
from labelled_scenes import catalog_star_scenes

import jstarid as js
from jstarid import cli
from jstarid.scene import brightest
from jstarid.sky_depth import identification_depth, naming_depth, stars_brighter_than

NU_DRACONIS = (85819, 85829)  # 62″ apart, V 4.9 both


@pytest.mark.parametrize("fov, size, expected", [
    (20.0, (1024, 1024), 6.0),  # the papers' field: their V 6.0
    (11.4243, (1024, 768), 7.1),  # tetra3_test: the depth chosen by hand for it was 7.0
    (6.1, (1392, 1040), 8.5),  # 1–3 stars at V 6.0; the rule makes it 40
    (40.0, (512, 512), 6.0),  # never shallower than the papers'
])
def test_identification_depth_follows_the_field(fov, size, expected):
    camera = js.Camera.from_fov(*size, fov)
    depth = identification_depth(camera)
    assert depth == pytest.approx(expected)
    if depth > 6.0:  # independently: the mean field holds ≥ 40 stars at the depth, < 40 0.1 mag above
        area = math.radians(fov) * math.radians(camera.fov_y_deg)  # small-field rectangle (sr)
        per_field = [stars_brighter_than(v) * area / (4 * math.pi) for v in (depth, depth - 0.1)]
        assert per_field[0] >= 40 * 0.98 and per_field[1] < 40 * 1.02


def test_naming_depth_stops_where_random_neighbours_begin():
    fine = js.Camera.from_fov(1280, 960, 17.06)  # 48″/px: the whole of Hipparcos
    assert naming_depth(fine, 2.0) == 12.5
    coarse = js.Camera.from_fov(512, 512, 40.0)  # 290″/px
    assert naming_depth(coarse, 2.0, at_least=5.0) < 7.0
    radius = math.radians(2.0 * 290 / 3600)
    chance = stars_brighter_than(naming_depth(coarse, 2.0, at_least=5.0)) * radius**2 / 4
    assert chance <= 0.0101  # π r² · N / 4π
    assert naming_depth(coarse, 2.0, at_least=6.5) == 6.5  # never shallower than identification


def test_a_camera_described_by_size_and_field_gets_its_depth(tmp_path):
    path = tmp_path / "narrow.toml"
    path.write_text("width = 1392\nheight = 1040\nfov_deg = 6.1\n")
    assert js.load_camera(path).mag_limit == 8.5
    assert js.load_camera("tetra3_test", size=(1392, 1040), fov_deg=6.1).mag_limit == 8.5
    path.write_text("width = 1392\nheight = 1040\nfov_deg = 6.1\nmag_limit = 7.25\n")
    assert js.load_camera(path).mag_limit == 7.25  # given: kept
    assert js.load_camera("tetra3_test").mag_limit == 7.0  # a preset keeps its own


def test_brightest_keeps_the_first_and_flags_the_rest():
    scenes = js.scenes_from_centroids([np.arange(10.0).reshape(5, 2), np.ones((2, 2))],
                                      [np.arange(5.0), np.arange(2.0)], capacity=8)
    few = brightest(scenes, 3)
    assert few.capacity == 3 and np.asarray(few.mag)[0].tolist() == [0, 1, 2]
    assert np.asarray(few.overflow).tolist() == [True, False]
    assert brightest(scenes, 8) is scenes


def _scene_arrays(n_scenes=2, camera_limit=6.5):
    """mlv2021 scenes whose stars reach V ``camera_limit`` (deeper than the V 5.5 identification
    catalog), as (n, 3) arrays and the true HIP numbers."""
    return [(np.column_stack([xy, mag]).astype(np.float64), hip) for xy, mag, hip in catalog_star_scenes(
        11, n_scenes, camera_limit=camera_limit, position_sigma_px=0.2, capacity=256)]


# slow (issue 69's 10-minute suite): js.solve and the CLI stay covered by the other
# test_solution and test_cli tests
@pytest.mark.slow
def test_solve_names_the_deeper_stars_and_matches_the_cli(tmp_path):
    """Identified against V 5.5, named against the naming catalog: ≥ 95 % of the stars (to V 6.5)
    named, none wrong; ``jstarid identify`` on the same centroids gives the same names."""
    scenes = _scene_arrays()
    solutions = js.solve([a for a, _ in scenes], "mlv2021", mag_limit=5.5)
    assert len(solutions) == 2
    for sol, (arr, hip) in zip(solutions, scenes, strict=True):
        assert sol.solved and sol.detections == len(arr)
        truth = {(round(x, 3), round(y, 3)): h for (x, y, _), h in zip(arr, hip, strict=True)}
        names = {(round(s.x, 3), round(s.y, 3)): s.hip for s in sol.stars}
        assert all(truth[k] == v for k, v in names.items())  # no wrong name
        assert len(names) >= 0.95 * len(truth)
        assert sol.false_match_probability < 1e-6  # dozens of stars: no coincidence
        deeper = cat_mag(hip) > 5.5  # named only through the naming catalog
        assert deeper.sum() > 20 and np.isin(hip[deeper], list(names.values())).mean() >= 0.95
        wcs = sol.wcs()  # the WCS maps every named star back to its pixel
        cat = js.load_catalog(12.5)
        rows = cat.row_of_hip([s.hip for s in sol.stars])
        px = wcs.all_world2pix(np.degrees(cat.ra[rows]), np.degrees(cat.dec[rows]), 0)
        assert np.max(np.hypot(px[0] - [s.x for s in sol.stars], px[1] - [s.y for s in sol.stars])) < 1.0
    path = tmp_path / "frame.csv"
    arr = scenes[0][0]
    path.write_text("mag,x,y\n" + "".join(f"{float(m)!r},{float(x)!r},{float(y)!r}\n" for x, y, m in arr))
    out = tmp_path / "ids.json"
    assert cli.main(["identify", str(path), "--camera", "mlv2021", "--mag-limit", "5.5",
                     "--out", str(out)]) == 0
    entry = json.loads(out.read_text())["scenes"][0]
    assert [s["hip"] for s in entry["stars"]] == [s.hip for s in solutions[0].stars]
    assert entry["ra_deg"] == pytest.approx(solutions[0].ra_deg, abs=1e-9)
    assert entry["false_match_probability"] == pytest.approx(solutions[0].false_match_probability)


def cat_mag(hip):
    cat = js.load_catalog(12.5)
    return cat.mag[cat.row_of_hip(hip)]


def test_solve_refuses_bad_input():
    with pytest.raises(ValueError, match="at least one frame"):
        js.solve([], "mlv2021")
    with pytest.raises(ValueError, match="1024×1024"):
        js.solve(np.zeros((10, 12), np.float32), "mlv2021")
    with pytest.raises(ValueError, match="not both"):
        js.solve([np.zeros((5, 3)), np.zeros((1024, 1024))], "mlv2021")


def test_a_close_pair_is_reported_as_a_blend():
    from jstarid.solution import _blend_finder

    cat = js.load_catalog(6.0)
    camera = js.Camera.from_fov(1280, 960, 17.06)  # 48″/px: ν Dra's 62″ is 1.3 px
    blend = _blend_finder(cat, camera, 2.0)
    row = int(cat.row_of_hip([NU_DRACONIS[0]])[0])
    if row < 0:  # merged into its companion's entry
        row = int(cat.row_of_hip([NU_DRACONIS[1]])[0])
    assert set(blend(row)) == set(NU_DRACONIS)
    lone = int(cat.row_of_hip([32349])[0])  # Sirius: nothing within 2 px at 2.5 mag
    assert blend(lone) == ()


def test_the_ladder_reaches_the_field_of_view_error():
    finishing = js.algorithms.get("mlv").Config().finishing
    wide = finishing.reaching(0.1)
    assert wide.focal_search[:4] == finishing.focal_search  # the default first
    assert wide.focal_search[4:8] == (0.97, 1.03, 0.96, 1.04)  # then outward, nearest first
    assert min(wide.focal_search) == 0.9 and max(wide.focal_search) == 1.1
    assert len(set(wide.focal_search)) == 20 and wide.max_focal_error >= 0.1
    assert finishing.reaching(0.02) is finishing  # within the default ladder
    off = js.Finishing.off()
    assert off.reaching(0.1) is off  # the paper's algorithm: no ladder added


def test_a_field_of_view_off_by_seven_percent_is_solved():
    """Centroids spread 7 % wider than the camera says (its focal length 7 % too short) are solved,
    the fitted focal scale says by how much, and no name is wrong."""
    cam = js.camera_preset("mlv2021")
    arr, hip = _scene_arrays()[0]
    wide = arr.copy()
    wide[:, :2] = (arr[:, :2] - [cam.cx, cam.cy]) * 1.07 + [cam.cx, cam.cy]
    inside = (wide[:, 0] >= 0) & (wide[:, 0] <= 1023) & (wide[:, 1] >= 0) & (wide[:, 1] <= 1023)
    sol = js.solve(wide[inside], cam, mag_limit=5.5, fov_max_error=0.1)
    assert sol.solved and sol.focal_scale == pytest.approx(1.07, abs=0.003)
    xy, truth = wide[inside, :2], hip[inside]
    nearest = [int(np.argmin(np.hypot(*(xy - [s.x, s.y]).T))) for s in sol.stars]
    assert len(sol.stars) >= 20 and [s.hip for s in sol.stars] == truth[nearest].tolist()
    assert sol.residual_arcsec < 0.5 * cam.pixel_scale_arcsec  # 0.2 px noise per axis, 89″/px


# slow (issue 69's 10-minute suite): random points under the defaults stay in test_contract
@pytest.mark.slow
def test_random_points_are_not_claimed_under_the_wide_ladder():
    """Twenty focal-length retries are twenty more chances of a chance match: frames of random
    points (no star among them) still come back unsolved, none named."""
    rng = np.random.default_rng(4)
    frames = [np.column_stack([rng.uniform(0, 1023, (30, 2)), np.sort(rng.uniform(2, 6, 30))])
              for _ in range(16)]
    solutions = js.solve(frames, "mlv2021", mag_limit=5.5, fov_max_error=0.1)
    assert not any(s.solved or s.stars for s in solutions)
