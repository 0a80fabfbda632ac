"""Tests of the experiment scripts and the NumPy SGM reference at tiny sizes (the heavy ones are
marked slow: run with ``pytest -m slow``)."""

import ast
import dataclasses
import importlib.util
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

import jstarid as js
from jstarid import Finishing
from jstarid.config_tree import with_fields

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


# the scripts and the one-off probes (experiments/probes/), by path without ".py"
SCRIPTS = sorted(str(p.relative_to(EXPERIMENTS).with_suffix("")) for p in EXPERIMENTS.rglob("*.py"))


def _load(name):
    """The script ``experiments/<name>.py`` as a module named after its file."""
    spec = importlib.util.spec_from_file_location(Path(name).name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[Path(name).name] = module  # dataclasses look their module up while the class is created
    spec.loader.exec_module(module)
    return module


def test_scripts_never_import_each_other():
    for name in SCRIPTS:
        for node in ast.walk(ast.parse((EXPERIMENTS / f"{name}.py").read_text())):
            if isinstance(node, ast.Import | ast.ImportFrom):
                names = [a.name for a in node.names] + [getattr(node, "module", None) or ""]
                assert not set(names) & {Path(n).name for n in SCRIPTS}, (name, names)
                assert "importlib" not in names, name


@pytest.mark.parametrize("name", SCRIPTS)
def test_scripts_share_the_harness_options(name, tmp_path):
    """Every script's parser comes from ``experiment.parser``: --out, --seed and --set."""
    args = _load(name).parse_args(["--out", str(tmp_path), "--seed", "3"])
    assert args.out == tmp_path and args.seed == 3 and args.set == []


@pytest.mark.slow
def test_tune_sgm_tiny(tmp_path):
    _load("tune_sgm").main(["--scenes", "4", "--cs", "1.0", "1.74", "--eps", "0.2", "0.4",
                            "--out", str(tmp_path)])
    res = json.loads((tmp_path / "results.json").read_text())
    assert len(res["grid"]) == 4 and len(res["fig11"]) == 7
    assert (tmp_path / "fig12_13_eps.png").exists() and (tmp_path / "table.md").exists()


@pytest.mark.slow
def test_reproduce_sgm_tiny_resumes(tmp_path):
    """Levels are stored as they finish; a rerun with the same settings reuses them."""
    module = _load("reproduce_sgm")
    args = ["--n-stars", "3", "--sigmas", "0", "2", "--experiments", "position", "--out", str(tmp_path)]
    first = module.main(args)
    stored = sorted(p.name for p in (tmp_path / "levels").iterdir())
    assert stored == ["position_0.00", "position_2.00"]
    assert js.load_sweep(tmp_path / "levels" / "position_2.00").rows()[0]["scenes"] == 3
    second = module.main(args)
    assert second["levels"] == first["levels"]  # reused, not recomputed (timings included)
    one = module.main(["--n-stars", "3", "--sigmas", "2", "--experiments", "position",
                       "--out", str(tmp_path)])
    assert one["levels"][0] == first["levels"][1]  # a level's scenes do not depend on the others
    other = module.main(args + ["--seed", "1"])
    assert other["levels"][1]["seconds"] != first["levels"][1]["seconds"]  # new settings: recomputed
    level = first["levels"][0]
    assert level["ceiling_rate"] == 1.0 and level["accuracy"] == 1.0  # noise-free
    assert "ceiling (%)" in (tmp_path / "table.md").read_text()


def test_code_fingerprint_ignores_documentation_not_code(tmp_path):
    """A docstring or comment edit keeps stored levels valid; a changed constant does not."""
    fingerprint = _load("reproduce_sgm")._code_fingerprint
    package = tmp_path / "pkg"
    package.mkdir()
    source = package / "mod.py"
    source.write_text('"""Module."""\n\n\ndef f(x):\n    """Doc."""\n    return x * 2  # why\n')
    base = fingerprint(package)
    source.write_text('"""Module, reworded."""\n\n\ndef f(x):\n    """Other doc."""\n'
                      '    return x * 2  # another why\n')
    assert fingerprint(package) == base
    source.write_text('"""Module."""\n\n\ndef f(x):\n    """Doc."""\n    return x * 3\n')
    assert fingerprint(package) != base
    source.write_text('"""Module."""\n\n\ndef f(x):\n    """Doc."""\n    return x * 2\n')
    (package / "algorithms" / "rpnet").mkdir(parents=True)
    (package / "algorithms" / "rpnet" / "model.py").write_text("Z = 1\n")
    assert fingerprint(package) == base  # another algorithm's code does not count
    (package / "papers").mkdir()
    (package / "papers" / "mlv.py").write_text("SWEEPS = {}\n")
    assert fingerprint(package) == base  # nor its paper's definitions
    (package / "other.py").write_text("Y = 1\n")
    assert fingerprint(package) != base  # a new module counts


def test_sgm_code_never_imports_the_fingerprint_s_left_out_algorithms():
    """The fingerprint leaves MLV and RpNet out because nothing else in jstarid imports them."""
    import ast

    import jstarid

    module = _load("reproduce_sgm")
    root = Path(jstarid.__file__).parent
    left_out = [f"jstarid.algorithms.{name}" for name in module.OTHER_ALGORITHMS]
    for path in root.rglob("*.py"):
        if any(path.is_relative_to(root / "algorithms" / n) for n in module.OTHER_ALGORITHMS):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):  # `from jstarid.algorithms import rpnet` too
                names = [f"{node.module or ''}.{a.name}" for a in node.names]
            else:
                continue
            assert not any(n.startswith(m) for n in names for m in left_out), (path, names)


@pytest.mark.slow
def test_diagnose_sgm_tiny(tmp_path):
    """The diagnosis sees the reproduction's scenes and accounts for every one of them."""
    out = _load("probes/diagnose_sgm").main(["--experiment", "lost", "--sigma", "3", "--n-stars", "6",
                                      "--out", str(tmp_path)])
    assert sum(out["outcomes"].values()) == 6
    assert sum(out["failure_causes"].values()) == out["outcomes"].get("fail", 0)
    assert len(out["mis_identified"]) == out["outcomes"].get("wrong", 0)


def test_program_memory_tiny(tmp_path):
    """Calling every shape again after the release stages nothing: the executables are reused."""
    row = _load("probes/program_memory").main(["--sizes", "16", "--pairs", "64", "128",
                                               "--out", str(tmp_path)])
    assert row["programs"] == 2 and row["staged_on_rerun"] == 0
    assert (tmp_path / "table.md").exists()


@pytest.mark.slow
def test_bench_sgm_tiny_with_overrides():
    """``--set`` reaches the SGM config; noise-free scenes are all named, as by the NumPy version."""
    bench = _load("bench_sgm")
    args = bench.parse_args(["--batch", "64", "--sigmas", "0", "--numpy-scenes", "2",
                             "--set", "size_bucket=16"])
    (row,) = bench.run(args)
    assert row["batch"] == 64 and row["scenes_per_s"] > 0
    assert row["accuracy"] == 1.0 and row["misid_rate"] == 0.0 and row["numpy_ids_agree"] == 1.0
    # an override that changes the outcome: no main star has 1,000 neighbours, so every scene fails
    (starved,) = bench.run(bench.parse_args(["--batch", "64", "--sigmas", "0", "--numpy-scenes", "0",
                                             "--set", "min_stars=1000"]))
    assert starved["failure_rate"] == 1.0 and starved["misid_rate"] == 0.0
    with pytest.raises(ValueError, match="no field 'no_such_field'"):
        bench.run(bench.parse_args(["--batch", "64", "--set", "no_such_field=1"]))


def test_benchmark_tables_reach_the_report(tmp_path):
    """The benchmark's saved tables (steady rates apart from the compile budget) are a section of
    ``jstarid report``'s page, with the command and commit that made them."""
    from jstarid import cli
    from jstarid import experiment as ex

    bench = _load("benchmark")
    rows = [{"benchmark": "simulate", "camera": "sgm2022", "batch": 10_000, "devices": 2,
             "noise": "pos 1 px", "compile_s": 1.5, "scenes_per_s": 250_000, "peak_rss_mb": 900},
            {"benchmark": "sgm", "sigma_px": 3.0, "batch": 1000, "compile_s": 40.0, "scenes_per_s": 67.1,
             "peak_rss_mb": 2000},
            {"benchmark": "compile mlv", "camera": "mlv2021", "batch": 100, "first_call_s": 30.0,
             "programs": 20, "compile_s": 25.0, "later_programs": 0, "scenes_per_s": 900.0,
             "identified": 0.995, "peak_rss_mb": 2100}]
    table = bench.benchmark_tables(rows, note="2 × cpu")
    steady, budget = table.split("**Compile budget**")
    assert "| simulate | sgm2022 | 10,000 | 2 | pos 1 px | 250,000 | 1.5 | 900 |" in steady
    assert "| sgm | sgm2022 | 1,000 | – | sigma_px 3.0 | 67.1 | 40.0 |" in steady and "mlv" not in steady
    assert "| mlv | mlv2021 | 100 | 30.0 | 20 | 25.0 | 0 | 900.0 | 99.5% |" in budget
    ex.write(tmp_path / "benchmark", config={}, results={"rows": rows}, table=table)
    page = tmp_path / "report.md"
    assert cli.main(["report", "--reproduce", str(tmp_path / "none"), "--sweeps", str(tmp_path / "none"),
                     "--benchmark", str(tmp_path / "benchmark"), "--out", str(page)]) == 0
    text = page.read_text()
    assert "## Throughput" in text and table.strip() in text and "commit" in text.split("## Throughput")[1]


def test_sgm_paper_equals_the_numpy_reference_on_noisy_scenes():
    """``Config.paper`` gives the ids of the plain NumPy SGM (bench_sgm's baseline) under noise;
    the leftover naming (an extension) would not: it also names stars a smaller J* leaves out."""
    import jax

    import jstarid as js
    from jstarid.algorithms import sgm
    from jstarid.algorithms.sgm import reference as ref
    cat = js.load_catalog(5.0)  # small graphs: the reference's per-candidate eig stays cheap
    cam = js.camera_preset("sgm2022", mag_limit=5.0)
    cfg = sgm.Config()
    db = sgm.build_database(cat, cam, cfg, progress=False)
    rows = np.random.default_rng(0).choice(len(cat), 8, replace=False)
    scenes = js.simulate(jax.random.key(0), cat, cam, js.NoiseConfig(position_sigma_px=2.0),
                         capacity=128, boresight_ids=rows)
    xy, valid = np.asarray(scenes.xy, np.float64), np.asarray(scenes.valid)
    want = np.stack([ref.identify_scene(db, xy[s], valid[s], cfg)[0] for s in range(len(rows))])
    paper = np.asarray(sgm.identify(db, scenes, sgm.Config.paper(), with_attitude=False).ids)
    np.testing.assert_array_equal(paper, want)
    assert np.all((paper >= 0).sum(axis=1) >= cfg.min_matched)
    leftover_only = with_fields(cfg, {"verify": False, "finishing": Finishing.off()})
    leftover = np.asarray(sgm.identify(db, scenes, leftover_only, with_attitude=False).ids)
    differs = np.any(leftover != paper, axis=1)
    assert 0 < differs.sum() < len(rows)  # the case that made bench_sgm's comparison disagree
    assert np.all((leftover >= 0).sum(axis=1) >= (paper >= 0).sum(axis=1))


def test_bench_sgm_matching_tail():
    """The tail figures of the matchings per scene, checked on a hand-made batch."""
    bench = _load("bench_sgm")
    counts = np.array([1] * 95 + [100] * 5)  # 5 scenes (the top 5 %) hold 500 of 595 matchings
    tail = bench.matching_tail(counts[::-1])
    assert tail["matched_median"] == 1.0 and tail["matched_top5_share"] == round(500 / 595, 3)
    assert tail["matched_p99"] == 100.0 and tail["matched_p90"] == 1.0
    # 7 scenes: the top 5 % is one scene (rounded up); nothing matched gives a share of 0
    assert bench.matching_tail([0, 0, 0, 0, 0, 0, 6])["matched_top5_share"] == 1.0
    assert bench.matching_tail(np.zeros(10))["matched_top5_share"] == 0.0


REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


@pytest.mark.slow
@pytest.mark.skipif(not (REAL / "reference.json").exists(), reason="shared/data/real not present")
def test_real_images_mlv(tmp_path):
    _load("real_images").main(["--algorithms", "mlv", "--out", str(tmp_path)])
    res = json.loads((tmp_path / "results.json").read_text())
    assert len(res["images"]) == 4
    for im in res["images"]:
        e = im["algorithms"]["mlv"]
        assert e["ok"] and e["own"]["wrong"] == 0 and e["all"]["wrong"] == 0
        assert e["all"]["named"] > e["own"]["named"] and e["all"]["boresight_error_arcsec"] < 60
    assert "| Azi45 |" in (tmp_path / "table.md").read_text()
    assert len(list(tmp_path.glob("*.png"))) == 4


@pytest.mark.slow
@pytest.mark.skipif(not (REAL / "reference.json").exists(), reason="shared/data/real not present")
def test_real_images_sgm_subgraph(tmp_path):
    """SGM's magnitude-robust search (on for real frames) names every frame with no wrong name and
    the boresight within 10″ of the independent solve (issue goal)."""
    _load("real_images").main(["--algorithms", "sgm", "--out", str(tmp_path)])
    res = json.loads((tmp_path / "results.json").read_text())
    for im in res["images"]:
        e = im["algorithms"]["sgm"]
        assert e["ok"] and e["own"]["wrong"] == 0 and e["all"]["wrong"] == 0
        assert e["own"]["named"] >= 8 and e["own"]["boresight_error_arcsec"] < 10


@pytest.mark.slow
def test_tune_rpnet_training_tiny(tmp_path):
    rows = _load("tune_rpnet_training").main(["--quick", "--dae-lrs", "1e-3", "3e-3", "--scenes", "8",
                                              "--out", str(tmp_path)])
    assert len(rows) == 2 and {r["dae_lr"] for r in rows} == {1e-3, 3e-3}
    assert all(r["end_to_end"]["misid_rate"] == 0.0 for r in rows)
    assert (tmp_path / "held_out.png").exists() and "| identified % |" in (tmp_path / "table.md").read_text()


@pytest.mark.slow
def test_camera_range_measures_a_build_in_its_own_process(tmp_path):
    """One build through ``jstarid train`` in a fresh process: its first line, peak and cache bytes."""
    mod = _load("camera_range")
    mod.main(["--algorithms", "sgm", "--only", "2deg_512", "--out", str(tmp_path)])
    res = json.loads((tmp_path / "results.json").read_text())
    (rec,) = res["records"]
    assert rec["camera"] == "2deg_512" and rec["returncode"] == 0, rec
    assert rec["first_line"].startswith("Building SGM") and 50 < rec["peak_mb"] < 4000
    assert 0 < rec["cache_mb"] < 100
    assert "| built |" in (tmp_path / "table.md").read_text()
    assert not (tmp_path / "cache").exists()  # the build cache is the run's own, and goes
    assert mod.cameras(mod.parse_args(["--only", "40deg_4096"]))[0][1].width == 4096


def test_bench_compile_compares_two_runs_scene_by_scene(tmp_path, capsys):
    """``bench_compile.py --compare``: the scenes whose ids or ``ok`` differ, per call, and the
    largest attitude difference of the scenes both solved."""
    bench = _load("bench_compile")
    ids = np.array([[3, -1], [5, 6]], np.int32)
    att = np.stack([np.eye(3), np.eye(3)]).astype(np.float32)
    a = {"mlv/2/0/ids": ids, "mlv/2/0/ok": np.array([True, True]), "mlv/2/0/attitude": att}
    b = dict(a, **{"mlv/2/0/ids": np.array([[3, -1], [5, 7]], np.int32), "mlv/2/0/attitude": att * 1.5})
    np.savez(tmp_path / "a.npz", **a)
    np.savez(tmp_path / "b.npz", **b)
    assert bench.compare_outcomes(str(tmp_path / "a.npz"), str(tmp_path / "a.npz")) == 0
    assert bench.compare_outcomes(str(tmp_path / "a.npz"), str(tmp_path / "b.npz")) == 1
    out = capsys.readouterr().out
    assert "mlv/2/0: 1 of 2 scenes differ" in out and "within 5.00e-01" in out


def test_design_notes_name_no_commits():
    """docs/design records why, not when: figures with their commits live in experiments/RESULTS.md
    (a hex word of 7+ characters with a digit and a letter reads as a commit)."""
    commit = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
    design = Path(__file__).resolve().parents[1] / "docs" / "design"
    found = {p.name: commit.findall(p.read_text()) for p in sorted(design.glob("*.md"))}
    assert found and not any(found.values()), {k: v for k, v in found.items() if v}


def test_clutter_and_random_sets_hold_what_they_name():
    """The false-match experiments' sets: each clutter level has that many false detections (truth −1)
    beside the stars; random points hold no star and no truth; the same seed draws the same sets."""
    from jstarid import experiment as ex

    cat, cam = js.load_catalog(5.5), js.camera_preset("mlv2021")

    def draw():
        return list(ex.clutter_and_random_sets(cat, cam, seed=3, scenes=4, false_counts=[0, 10], points=[8]))

    sets = draw()
    assert [name for name, _, _ in sets] == ["0 false", "10 false", "8 random points"]
    assert [known for *_, known in sets] == [True, True, False]
    false_counts = [np.sum(np.asarray(s.valid) & (np.asarray(s.truth) < 0), axis=1) for _, s, _ in sets]
    cut = np.asarray(sets[1][1].overflow)  # a full scene keeps its brightest 64 detections
    assert np.all(false_counts[0] == 0) and np.all(false_counts[1] <= 10)
    assert np.all(false_counts[1][~cut] == 10) and cut.sum() < 4
    assert np.all(np.asarray(sets[2][1].valid).sum(axis=1) == 8) and np.all(false_counts[2] == 8)
    assert np.array_equal(np.asarray(draw()[1][1].xy), np.asarray(sets[1][1].xy))
    narrow = ex.clutter_and_random_sets(cat, cam, seed=3, scenes=4, false_counts=[10], points=[8],
                                        capacity=16)
    assert [np.asarray(s.valid).shape for _, s, _ in narrow] == [(4, 16), (4, 16)]


def test_own_sky_judges_only_the_plate_solutions_tight_matches():
    """A matched star the plate solver itself fits worse than ``match_px`` is ``loose``, not judged;
    the others are right, a blend, wrong or unnamed by the nearest named detection within ``match_px``."""
    judge = _load("own_sky").judge
    star = js.solution.Star
    solution = dataclasses.make_dataclass("Sol", ["stars"])(
        [star(hip=1, x=10.0, y=10.0, v=5.0, detection=0), star(hip=2, x=50.0, y=50.0, v=5.0, detection=1,
                                                             blend=(2, 3)),
         star(hip=4, x=90.0, y=90.0, v=5.0, detection=2)])
    truth = [(10.5, 10.0, 1, 0.4, 0.0, 0.0),  # right
             (50.0, 51.0, 3, 0.4, 0.0, 0.0),  # in the blend
             (90.0, 91.0, 5, 0.4, 0.0, 0.0),  # wrong
             (200.0, 200.0, 6, 0.4, 0.0, 0.0),  # unnamed
             (10.0, 10.5, 1, 4.6, 0.0, 0.0),  # the plate solution's own residual 4.6 px: loose
             (0.0, 0.0, -1, 0.1, 0.0, 0.0)]  # no Hipparcos number: skipped
    assert judge(solution, truth, 3.0) == {"right": 1, "blend": 1, "wrong": 1, "unnamed": 1, "loose": 1}
