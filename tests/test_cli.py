import json
import math

import numpy as np
import pytest
from labelled_scenes import catalog_star_scenes

import jstarid as js
from jstarid import cli


def test_demo_runs_the_engine_and_writes_results(tmp_path, capsys):
    out = tmp_path / "demo"
    assert cli.main(["demo", "--algorithms", "oracle", "--scenes", "6", "--levels", "0,2",
                     "--stars", "0-1000", "--out", str(out), "--quiet"]) == 0
    for name in ("config.json", "results.json", "table.md", "rates.png", "scenes.npz", "table_stars.md"):
        assert (out / name).exists(), name
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [(r["label"], r["position_sigma_px"], r["scenes"]) for r in rows] == [
        ("oracle", 0.0, 6), ("oracle", 2.0, 6)]
    text = capsys.readouterr().out
    assert text.startswith("jstarid demo: oracle on 2 levels × 6 scenes")
    assert "| oracle | 2 | 6 |" in text and "wrote" in text
    assert "scenes with 0–1000 true stars" in text and "| oracle | 2 | 0–1000 | 6 |" in text


@pytest.mark.slow
def test_demo_adds_the_baselines_on_request(tmp_path):
    out = tmp_path / "baselines"
    assert cli.main(["demo", "--algorithms", "oracle", "--baselines", "--scenes", "4", "--levels", "0",
                     "--out", str(out), "--quiet"]) == 0
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["oracle", *js.algorithms.BASELINES]
    assert all(r["identification_rate"] == 1.0 for r in rows)  # noise-free scenes


# slow (issue 69's 10-minute suite): grids and --set stay covered by test_engine and test_cli's other sweeps
@pytest.mark.slow
def test_sweep_with_a_grid_and_overrides(tmp_path):
    out = tmp_path / "grid"
    assert cli.main(["sweep", "--algorithms", "mlv", "--camera", "mlv2021", "--mag-limit", "5.5",
                     "--axis", "magnitude", "--levels", "0.3", "--fixed", "position_sigma_px=2.5",
                     "--grid", "th1=0,2", "--set", "mlv.n_boresights=20000", "--scenes", "8",
                     "--out", str(out), "--quiet"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert [e["label"] for e in config["entries"]] == ["mlv th1=0", "mlv th1=2"]
    assert {e["config"]["n_boresights"] for e in config["entries"]} == {20000}
    assert config["settings"]["fixed"] == {"position_sigma_px": 2.5}


def test_sweep_from_pixels_over_a_sensor_axis(tmp_path):
    out = tmp_path / "pixels"
    assert cli.main(["sweep", "--algorithms", "oracle", "--camera", "sgm2022", "--size", "256x256",
                     "--pixels", "--axis", "exposure", "--levels", "0.0003,0.1", "--sensor",
                     "read_noise_e=5", "--centroid", "threshold_sigma=6", "--scenes", "4",
                     "--out", str(out), "--quiet"]) == 0
    config = json.loads((out / "config.json").read_text())["settings"]
    assert [s["exposure_s"] for s in config["sensors"]] == [0.0003, 0.1]
    assert {s["read_noise_e"] for s in config["sensors"]} == {5.0}
    assert config["centroid"]["threshold_sigma"] == 6
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert rows[0]["identification_rate"] < rows[1]["identification_rate"] == 1.0


def test_report_collects_saved_sweeps(tmp_path):
    demo = tmp_path / "demo"
    assert cli.main(["demo", "--algorithms", "oracle", "--scenes", "3", "--levels", "1",
                     "--out", str(demo), "--quiet"]) == 0
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\nkept by hand\n")
    args = ["report", "--reproduce", str(tmp_path / "none"), "--sweeps", str(demo),
            "--out", str(tmp_path / "report.md"), "--update", str(results)]
    assert cli.main(args) == 0 and cli.main(args) == 0  # updating twice replaces, not appends
    page = (tmp_path / "report.md").read_text()
    assert "| oracle | 1 | 3 |" in page and "commit" in page
    text = results.read_text()
    assert text.startswith("# Results\n\nkept by hand") and text.count("jstarid report: start") == 1


@pytest.mark.slow
def test_reproduce_quick_experiment(tmp_path, capsys):
    assert cli.main(["reproduce", "mlv", "--experiments", "fig8", "--scenes", "3", "--out",
                     str(tmp_path), "--quiet", "--baselines"]) == 0
    rows = json.loads((tmp_path / "mlv" / "fig8" / "results.json").read_text())["rows"]
    assert [r["n_false"] for r in rows if r["label"] == "mlv"] == [0, 1, 2, 3, 4, 5, 6]
    assert {r["label"] for r in rows} == {"mlv", *js.algorithms.BASELINES}
    out = capsys.readouterr().out
    assert "93.25" in out  # the paper's quoted value beside ours
    assert "Baselines on the same scenes" in out and "| pyramid | voting | grid |" in out


def test_reproduce_runs_the_papers_algorithm_with_settings():
    """``--paper-algorithm`` turns off what ``Config.paper()`` turns off and keeps what the engine
    chose for the paper's camera and network; ``--set`` applies on top; a bad setting fails before
    any experiment runs."""
    from jstarid.cli.papers import _config
    from jstarid.papers import reproduction as rp

    parser = cli.build_parser()
    fig8 = next(e for e in rp.experiments("mlv") if e.name == "fig8")
    assert _config(fig8, parser.parse_args(["reproduce", "mlv"])) is None  # the engine's default
    default = js.engine.default_config("mlv", camera=js.camera_preset(fig8.camera))
    config = _config(fig8, parser.parse_args(["reproduce", "mlv", "--paper-algorithm", "--set", "th1=2"]))
    paper = js.algorithms.get("mlv").Config.paper()
    assert config.th1 == 2 and config.finishing == paper.finishing and not config.attitude_check
    assert config.eps_deg == default.eps_deg  # a setting the paper's algorithm shares is kept
    fig11 = next(e for e in rp.experiments("rpnet") if e.name == "fig11")
    network = js.engine.default_config("rpnet", rpnet_network="quick",
                                      camera=js.camera_preset(fig11.camera)).training
    config = _config(fig11, parser.parse_args(["reproduce", "rpnet", "--paper-algorithm"]))
    assert config.training == network and config.n_pool_pairs == 0  # the quick network, paper's rules
    with pytest.raises(ValueError, match="no field 'nope'"):
        _config(fig8, parser.parse_args(["reproduce", "mlv", "--set", "nope=1"]))


@pytest.mark.parametrize("argv, message", [
    (["demo", "--algorithms", "nope"], "unknown algorithm"),
    (["demo", "--peer", "nope"], "invalid choice"),
    (["demo", "--camera", "nope"], "unknown camera 'nope'"),
    (["demo", "--size", "12by3"], "--size must be WIDTHxHEIGHT"),
    (["sweep", "--algorithms", "sgm,mlv", "--camera", "narrow_twin"], "sgm: SGM's database for camera"),
    (["train", "sgm", "--camera", "tetra3_test", "--set", "radius_deg=6"],
     "does not fit the 4.28° half field"),
    (["identify", "x.csv", "--fov", "-3"], "field of view"),
    (["demo", "--scenes", "0"], "must be ≥ 1"),
    (["reproduce", "mlv", "--set", "nope=1"], "Config has no field 'nope'"),
    (["demo", "--levels", "-1"], "position_sigma_px"),
    (["demo", "--levels", "a,b"], "comma-separated numbers"),
    (["sweep", "--axis", "wobble"], "unknown axis"),
    (["sweep", "--axis", "exposure", "--levels", "0.1"], "sensor axis needs a sweep from pixels"),
    (["sweep", "--sensor", "exposure_s=0.1"], "--sensor and --centroid need --pixels"),
    (["sweep", "--pixels", "--sensor", "exposure=0.1"], "SensorConfig has no field 'exposure'"),
    (["sweep", "--pixels", "--sensor", "exposure_s=-1"], "exposure_s must be a positive"),
    (["sweep", "--algorithms", "mlv,sgm", "--grid", "th1=0,1"], "exactly one algorithm"),
    (["sweep", "--set", "no_such_field=1"], "no algorithm in the run has"),
    (["sweep", "--stars", "6-5"], "--stars takes LO-HI"),
    (["demo", "--stars", "five"], "--stars takes LO-HI"),
    (["demo", "--bogus"], "unrecognized arguments"),
    (["reproduce", "moon"], "invalid choice"),
    (["report", "--reproduce", "/nonexistent", "--sweeps", "/nonexistent", "--benchmark", "/nonexistent"],
     "no saved results"),
])
def test_bad_arguments_give_one_line_and_status_2(argv, message, capsys):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_list_and_catalog(capsys):
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    assert "oracle" in out and "baselines:  pyramid, voting, grid" in out
    assert cli.main(["catalog", "--mag-limit", "4.0"]) == 0
    out = capsys.readouterr().out
    counts = [int(line.rsplit(":", 1)[1]) for line in out.splitlines() if line.startswith("  V")]
    assert "V   3.5 –  4.5" in out and sum(counts) == len(js.load_catalog(4.0))  # every star binned


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


@pytest.mark.slow
def test_solve_identifies_a_rendered_image(tmp_path, capsys):
    """Simulated sky → rendered 16-bit FITS frame (stored with BZERO) → `jstarid solve` → the true
    attitude and names, and a WCS that puts every named star on its detection."""
    import jax
    from astropy.io import fits
    from astropy.wcs import WCS

    import jstarid as js

    cat = js.load_catalog(7.0)
    cam = js.camera_preset("tetra3_test")
    row = int(np.nonzero(cat.mag < 3.0)[0][5])  # a bright star at the boresight
    scene = js.simulate(jax.random.key(3), cat, cam, capacity=64, boresight_ids=np.array([row]))
    valid = np.asarray(scene.valid[0])
    xy, mag, truth = (np.asarray(a[0])[valid] for a in (scene.xy, scene.mag, scene.truth))
    path = tmp_path / "frame.fits"
    fits.PrimaryHDU(_render(xy, mag, cam.height, cam.width)).writeto(path)  # uint16: BZERO = 32768
    out = tmp_path / "out"
    assert cli.main(["solve", str(path), "--out", str(out), "--annotate"]) == 0
    saved = json.loads((out / "solutions.json").read_text())
    assert "func" not in saved["args"]  # the settings a run used, not the handler's address
    sol = saved["solutions"][0]
    assert sol["solved"] and "boresight RA" in capsys.readouterr().out
    c_true = np.asarray(scene.attitude[0], np.float64)
    c = np.asarray(sol["attitude"])
    sep = np.arctan2(np.linalg.norm(np.cross(c[2], c_true[2])), c[2] @ c_true[2])
    assert np.degrees(sep) * 3600 < 30
    assert len(sol["stars"]) >= 5
    for star in sol["stars"]:  # every name is the rendered star's
        j = np.argmin(np.linalg.norm(xy - [star["x"], star["y"]], axis=1))
        assert cat.hip[truth[j]] == star["hip"]
    assert abs(sol["focal_scale"] - 1.0) < 2e-3  # the camera fit finds the preset's focal length
    # the standard outputs: the .wcs, the image with the WCS in its header, the annotated PNG
    assert sol["wcs"] == str(out / "frame.wcs") and (out / "frame.png").exists()
    assert fits.getheader(out / "frame.fits")["BZERO"] == 32768
    rows = cat.row_of_hip([star["hip"] for star in sol["stars"]])
    radec = np.degrees(np.stack([cat.ra[rows], cat.dec[rows]], axis=1))
    for header in (fits.getheader(out / "frame.wcs"), fits.getheader(out / "frame.fits")):
        px = WCS(header).all_world2pix(radec, 0)
        assert np.abs(px - [[star["x"], star["y"]] for star in sol["stars"]]).max() < 0.5


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
    # a directory and a truncated image: one line, status 2 (not a traceback, not "unsolved")
    assert cli.main(["solve", str(tmp_path)]) == 2
    assert "cannot read an image" in capsys.readouterr().err
    Image.fromarray(np.arange(768 * 1024, dtype=np.uint32).reshape(768, 1024).astype(np.uint16)).save(
        tmp_path / "whole.png")
    data = (tmp_path / "whole.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    assert cli.main(["solve", str(tmp_path / "cut.png")]) == 2
    err = capsys.readouterr().err
    assert "cannot read an image" in err and err.count("\n") == 1


def test_solve_takes_epoch_and_focal_length_from_fits_headers(capsys):
    """DATE-OBS sets the epoch without --epoch; FOCALLEN / XPIXSZ the focal length (and the image its
    size) only when neither --camera nor --fov is given; output names stay apart."""
    from jstarid.cli import frames
    from jstarid.cli.cameras import camera_from_args
    from jstarid.image_files import ImageFile

    files = [ImageFile(np.zeros((480, 640), np.float32), header={}, epoch=e, focal_px=2000.0)
             for e in (2018.2, 2018.4)]

    def parsed(*extra):
        return cli.build_parser().parse_args(["solve", "a.fits", *extra])

    args = parsed()
    frames._camera_from_headers(args, files)
    assert frames._epoch_from_headers(args, files) and args.epoch == pytest.approx(2018.3)
    cam = camera_from_args(args)
    assert (cam.width, cam.height, cam.f_px) == (640, 480, pytest.approx(2000.0))
    assert "FOCALLEN" in capsys.readouterr().err
    for extra, f_px in [(["--fov", "20"], 320 / math.tan(math.radians(10))),
                        (["--camera", "tetra3_test"], js.load_camera("tetra3_test", size=(640, 480)).f_px)]:
        args = parsed(*extra, "--size", "640x480", "--epoch", "2019.5")
        frames._camera_from_headers(args, files)
        assert not frames._epoch_from_headers(args, files) and args.epoch == 2019.5
        assert camera_from_args(args).f_px == pytest.approx(f_px)
    args = parsed()  # no header focal length: the default preset
    frames._camera_from_headers(args, [ImageFile(np.zeros((2, 2), np.float32))])
    assert args.camera == "tetra3_test" and args.fov is None
    assert frames._stems(["a/1.png", "b/1.fits.gz", "c/x.fit"]) == ["1", "1-2", "x"]


def _scene_rows(n_scenes=2):
    """Simulated mlv2021 scenes as (xy, mag, hip) per scene (catalog stars only)."""
    return catalog_star_scenes(7, n_scenes)


@pytest.mark.slow
def test_identify_centroid_files(tmp_path, capsys):
    """CSV (columns in any order, scenes split by a blank line, true ids passed through) and JSON
    in, names that are the simulated stars' out."""
    scenes = _scene_rows()
    csv = tmp_path / "frames.csv"
    csv.write_text("HIP, y, x, magnitude\n" + "\n\n".join(
        "\n".join(f"{h}, {y:.3f}, {x:.3f}, {m:.2f}" for (x, y), m, h in zip(xy, mag, hip, strict=True))
        for xy, mag, hip in scenes) + "\n")
    js_file = tmp_path / "one.json"
    js_file.write_text(json.dumps([[float(x), float(y), float(m)] for (x, y), m
                                   in zip(scenes[0][0], scenes[0][1], strict=True)]))
    out = tmp_path / "ids.json"
    assert cli.main(["identify", str(csv), str(js_file), "--camera", "mlv2021", "--mag-limit", "5.5",
                     "--out", str(out)]) == 0
    solved = json.loads(out.read_text())["scenes"]
    assert [s["scene"] for s in solved] == [f"{csv}#0", f"{csv}#1", str(js_file)]
    for entry, (xy, _, hip) in zip(solved, [*scenes, scenes[0]], strict=True):
        assert entry["solved"] and len(entry["stars"]) >= 5 and len(entry["quaternion"]) == 4
        assert abs(entry["focal_scale"] - 1.0) < 2e-3 and entry["f_px_fitted"] > 0
        for star in entry["stars"]:
            j = np.argmin(np.linalg.norm(xy - [star["x"], star["y"]], axis=1))
            assert hip[j] == star["hip"] == star.get("true_hip", hip[j])
    assert all("true_hip" in star for entry in solved[:2] for star in entry["stars"])
    assert not any("true_hip" in star for star in solved[2]["stars"])
    assert "boresight RA" in capsys.readouterr().err

    # a camera file with a distorting lens: centroids measured through it are named the same
    lens = js.Camera(**{**js.camera_files.camera_to_dict(js.camera_preset("mlv2021")),
                        "distortion": (0.08,)})
    camera_file = js.save_camera(lens, tmp_path / "lens.toml")
    measured = np.asarray(lens.distort(scenes[0][0]))
    csv.write_text("\n".join(f"{x:.3f}, {y:.3f}, {m:.2f}" for (x, y), m
                             in zip(measured, scenes[0][1], strict=True)) + "\n")
    assert cli.main(["identify", str(csv), "--camera", str(camera_file), "--mag-limit", "5.5",
                     "--out", str(out)]) == 0
    written = json.loads(out.read_text())
    assert written["camera"]["distortion"] == [0.08] and written["epoch_source"].startswith("catalog")
    entry = written["scenes"][0]
    assert entry["solved"] and len(entry["stars"]) >= 5
    for star in entry["stars"]:  # reported where they were measured, named as without the lens
        j = np.argmin(np.linalg.norm(measured - [star["x"], star["y"]], axis=1))
        assert np.linalg.norm(measured[j] - [star["x"], star["y"]]) < 1e-2
        assert scenes[0][2][j] == star["hip"]
    assert "no --epoch given" in capsys.readouterr().err


@pytest.mark.parametrize("name, text, message", [
    ("empty.csv", "", "is empty"),
    ("words.csv", "x,y,mag\n1,2,3\nfoo,bar,baz\n", "line 3"),
    ("short.csv", "1,2,3\n4\n", "line 2"),
    ("bad.json", "{not json", "not valid JSON"),
    ("shape.json", '[[1, 2, 3, 4, 5]]', "scene 0"),
])
def test_identify_bad_centroid_files(tmp_path, capsys, name, text, message):
    (tmp_path / name).write_text(text)
    assert cli.main(["identify", str(tmp_path / name)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert cli.main(["identify", str(tmp_path / "missing.csv")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_train_builds_ahead_and_says_so(tmp_path, capsys, monkeypatch):
    """`jstarid train` says what it builds before building it, then finds it built."""
    monkeypatch.setenv("JSTARID_CACHE", str(tmp_path))  # nothing built yet
    argv = ["train", "mlv", "--camera", "mlv2021", "--mag-limit", "5.5", "--set", "n_boresights=3000"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("Building MLV triangle database for mlv2021") and "built for camera" in out
    assert cli.main(argv) == 0
    assert "already built" in capsys.readouterr().out
    # RpNet: the estimate comes first and the network is built for the camera of the options
    from jstarid.algorithms import rpnet

    calls = []

    def build_database(catalog, camera, config=None, *, use_cache=True, progress=True):
        calls.append((camera, catalog, config))

    monkeypatch.setattr(rpnet, "build_database", build_database)
    assert cli.main(["train", "rpnet", "--camera", "sgm2022", "--size", "640x480", "--fov", "9",
                     "--epoch", "2019.57"]) == 0
    assert "min on 2 CPU cores" in capsys.readouterr().out.splitlines()[0]
    camera, catalog, config = calls[0]
    assert (camera.width, camera.height) == (640, 480) and abs(camera.fov_x_deg - 9) < 1e-9
    # the catalog `solve --epoch 2019.57` will load, as deep as the 9° field needs (not the preset's
    # V 6.0); the pattern radius fits the 3.4° half field
    assert camera.mag_limit == js.sky_depth.identification_depth(camera) == 7.6
    assert catalog.fingerprint == js.load_catalog(7.6, epoch=2019.57).fingerprint
    assert config == rpnet.Config.for_camera(camera, training=rpnet.Training.quick())
    assert config.rho_deg == 3.0
    assert cli.main(["train", "nope"]) == 2
