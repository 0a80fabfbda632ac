import json

import numpy as np

from jstarid import cli


def test_demo_writes_picture_and_stats(tmp_path, capsys):
    assert cli.main(["demo", "--batch", "20", "--out", str(tmp_path), "--false", "1"]) == 0
    stats = json.loads((tmp_path / "scene_stats.json").read_text())
    assert stats["scenes"] == 20 and stats["stars_per_scene_mean"] > 3
    assert (tmp_path / "scene.png").stat().st_size > 10_000
    assert "simulated 20 scenes" in capsys.readouterr().out


def test_compare_runs_registered_algorithms(tmp_path, capsys):
    assert cli.main(["compare", "--algorithms", "oracle", "--batch", "30", "--out",
                     str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert rows[0]["algorithm"] == "oracle" and rows[0]["misid"] == 0.0
    assert "| oracle |" in capsys.readouterr().out


def test_bad_input_is_a_clear_error(capsys):
    assert cli.main(["demo", "--camera", "nope"]) == 2
    assert "unknown camera preset" in capsys.readouterr().err
    assert cli.main(["compare", "--algorithms", "nope", "--batch", "5"]) == 2
    assert cli.main(["demo", "--sigma", "-1", "--batch", "5"]) == 2


def test_list(capsys):
    assert cli.main(["list"]) == 0
    assert "oracle" in capsys.readouterr().out


def _render(xy, mag, height, width, *, zero_point=16.7, psf_sigma=0.8, seed=0):
    """A 16-bit star image: integrated Gaussian PSFs, sky 1000, read noise 10 (counts)."""
    from scipy import special

    img = np.full((height, width), 1000.0)
    for (x, y), m in zip(xy, mag, strict=True):
        x0, y0 = int(round(x)) - 7, int(round(y)) - 7
        ey = (np.arange(y0, y0 + 16) - 0.5 - y) / (np.sqrt(2) * psf_sigma)
        ex = (np.arange(x0, x0 + 16) - 0.5 - x) / (np.sqrt(2) * psf_sigma)
        stamp = 10 ** (-0.4 * (m - zero_point)) * np.outer(0.5 * np.diff(special.erf(ey)),
                                                           0.5 * np.diff(special.erf(ex)))
        ys, xs = slice(max(y0, 0), min(y0 + 15, height)), slice(max(x0, 0), min(x0 + 15, width))
        img[ys, xs] += stamp[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]
    img += np.random.default_rng(seed).normal(0.0, 10.0, img.shape)
    return np.clip(img, 0, 65535).astype(np.uint16)


def test_solve_identifies_a_rendered_image(tmp_path, capsys):
    """Simulated sky → rendered 16-bit TIFF → `jstarid solve` → the true attitude and names."""
    import jax
    from PIL import Image

    import jstarid as js

    cat = js.load_catalog(7.0)
    cam = js.camera_preset("tetra3_test")
    row = int(np.nonzero(cat.mag < 3.0)[0][5])  # a bright star at the boresight
    scene = js.simulate(jax.random.key(3), cat, cam, capacity=64, boresight_ids=np.array([row]))
    valid = np.asarray(scene.valid[0])
    xy, mag, truth = (np.asarray(a[0])[valid] for a in (scene.xy, scene.mag, scene.truth))
    path = tmp_path / "frame.tiff"
    Image.fromarray(_render(xy, mag, cam.height, cam.width)).save(path)
    assert cli.main(["solve", str(path), "--out", str(tmp_path)]) == 0
    sol = json.loads((tmp_path / "solutions.json").read_text())["solutions"][0]
    assert sol["solved"] and "boresight RA" in capsys.readouterr().out
    c_true = np.asarray(scene.attitude[0], np.float64)
    c = np.asarray(sol["attitude"])
    sep = np.arctan2(np.linalg.norm(np.cross(c[2], c_true[2])), c[2] @ c_true[2])
    assert np.degrees(sep) * 3600 < 30
    assert len(sol["stars"]) >= 5
    for star in sol["stars"]:  # every name is the rendered star's
        j = np.argmin(np.linalg.norm(xy - [star["x"], star["y"]], axis=1))
        assert cat.hip[truth[j]] == star["hip"]


def test_solve_bad_input(tmp_path, capsys):
    assert cli.main(["solve", str(tmp_path / "missing.tiff")]) == 2
    assert "cannot read an image" in capsys.readouterr().err
    (tmp_path / "notes.tiff").write_text("not an image")
    assert cli.main(["solve", str(tmp_path / "notes.tiff")]) == 2
    assert "cannot read an image" in capsys.readouterr().err
    from PIL import Image

    Image.fromarray(np.zeros((40, 50), np.uint16)).save(tmp_path / "small.tiff")
    assert cli.main(["solve", str(tmp_path / "small.tiff")]) == 2
    assert "768×1024" in capsys.readouterr().err
