"""Strict scores of labelled sets (:mod:`jstarid.scoring`) and ``jstarid score``."""

import json
from pathlib import Path

import numpy as np
import pytest
from labelled_scenes import catalog_star_scenes

from jstarid import cli
from jstarid.scoring import close_pairs, score_scene, summarize

ORESAT_TRUTH = Path(__file__).resolve().parents[2] / "shared" / "data" / "oresat" / "exp1000" / "truth"
NU_DRACONIS = (85819, 85829)  # 62″ apart: one spot on most trackers


def test_the_strict_rules():
    def blends(named, true):
        return (named == 5) & (true == 6)  # HIP 5 and 6 make one spot

    right = score_scene([1, 2, -1, 5], [1, 2, 3, 6], True, blends=blends)
    assert (right["outcome"], right["correct_names"], right["blend_names"], right["wrong_names"]) == (
        "right", 2, 1, 0)
    assert right["blend_detections"] == [3]
    assert score_scene([1, 4], [1, -1], True)["outcome"] == "wrong"  # a false star named
    assert score_scene([1, 9], [1, 2], False)["wrong_detections"] == [1]  # wrong even when unsolved
    assert score_scene([-1, -1], [1, 2], True)["outcome"] == "failed"
    assert score_scene([1, 2], [1, 2], False)["outcome"] == "failed"
    assert score_scene([5], [6], True, blends=blends)["outcome"] == "failed"  # a blend alone
    total = summarize([right, score_scene([1, 4], [1, -1], True)])
    assert (total["right"], total["wrong"], total["failed"], total["true_stars"]) == (1, 1, 0, 5)
    assert total["recall"] == 3 / 5 and total["precision"] == 3 / 4  # blends in neither
    assert total["false_match_calibrated"] is None  # no score carries a probability


def test_the_false_match_probability_is_calibrated_on_labelled_scenes():
    """``summarize``: wrong scenes at most a share t of the solved scenes at P ≤ t, for every t
    (:func:`jstarid.false_match.calibrated`); unsolved scenes do not count as claims."""
    def scored(named, true, solved, p):
        return {**score_scene(named, true, solved), "false_match_probability": p}

    right = [scored([1, 2, 3], [1, 2, 3], True, 1e-12) for _ in range(200)]
    wrong_at_one = scored([4, 5, 6], [1, 2, 3], True, 1.0)
    assert summarize([*right, wrong_at_one])["false_match_calibrated"] is True
    # one wrong scene among 201 claims at P ≤ 1e-2: more than a share 1e-2 would allow at 1e-9
    wrong_sure = scored([4, 5, 6], [1, 2, 3], True, 1e-12)
    assert summarize([*right, wrong_sure])["false_match_calibrated"] is False
    unsolved = scored([4, 5, 6], [1, 2, 3], False, None)  # named but not claimed: no claim at any P
    assert summarize([*right, unsolved])["false_match_calibrated"] is True


def test_close_pairs_from_the_catalog():
    np.testing.assert_array_equal(
        close_pairs([NU_DRACONIS[0], NU_DRACONIS[0], 32349, 1], [NU_DRACONIS[1], 32349, 30438, 999999], 0.05),
        [True, False, False, False])
    assert not close_pairs(*NU_DRACONIS, 0.01)[0]


def _simulated_rows(n_scenes=3):
    """Simulated mlv2021 scenes (catalog stars only) as rows of scene, x, y, mag, true HIP."""
    return [(f"s{i}", x, y, m, h) for i, (xy, mag, hip) in enumerate(catalog_star_scenes(3, n_scenes))
            for (x, y), m, h in zip(xy, mag, hip, strict=True)]


def test_score_a_simulated_labelled_set(tmp_path, capsys):
    """The same set as a table, with its columns shuffled, in the line layout and with one true id
    changed: the first three score alike, with no wrong scene; the last has one."""
    rows = _simulated_rows()
    table = tmp_path / "set.csv"
    table.write_text("scene,x,y,mag,hip\n" + "".join(f"{s},{x:.3f},{y:.3f},{m:.3f},{h}\n"
                                                     for s, x, y, m, h in rows))
    shuffled = tmp_path / "shuffled.tsv"
    shuffled.write_text("True_HIP\tMagnitude\tY\tImage\tX\n" + "".join(
        f"{h}\t{m:.3f}\t{y:.3f}\t{s}\t{x:.3f}\n" for s, x, y, m, h in reversed(rows)))
    lines = tmp_path / "set.txt"
    labels = sorted({r[0] for r in rows})
    lines.write_text("".join(" ".join(f"{x:.3f} {y:.3f} {m:.3f}" for s, x, y, m, _ in rows if s == k) + "\n"
                             + " ".join(str(h) for s, *_, h in rows if s == k) + "\n" for k in labels))
    flipped = tmp_path / "flipped.csv"
    brightest = min(range(len(rows)), key=lambda k: rows[k][3] if rows[k][0] == "s0" else np.inf)
    flipped.write_text("scene,x,y,mag,hip\n" + "".join(
        f"{s},{x:.3f},{y:.3f},{m:.3f},{-1 if k == brightest else h}\n"
        for k, (s, x, y, m, h) in enumerate(rows)))
    out = tmp_path / "scores.json"
    assert cli.main(["score", str(table), str(shuffled), str(lines), str(flipped), "--camera", "mlv2021",
                     "--mag-limit", "5.5", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("| set | scenes | right |") and "| all | 12 |" in printed
    sets = json.loads(out.read_text())["sets"]
    keys = ("scenes", "right", "wrong", "failed", "true_stars", "correct_names", "wrong_names")
    first = {k: sets[0][k] for k in keys}
    solved = sum(s["solved"] for s in sets[0]["scenes_scored"])
    assert first["right"] == solved >= 2 and first["wrong"] == 0 and first["scenes"] == 3
    assert first["true_stars"] == len(rows) and sets[0]["precision"] == 1.0
    for other in sets[1:3]:
        assert {k: other[k] for k in keys} == first
    assert sets[1]["scenes_scored"][0]["scene"].endswith("#s2")  # the shuffled file's first scene
    assert sets[3]["wrong"] == 1 and sets[3]["scenes_scored"][0]["outcome"] == "wrong"
    [wrong] = sets[3]["scenes_scored"][0]["wrong_detections"]
    assert wrong["true_hip"] == -1 and wrong["hip"] == rows[brightest][4]


@pytest.mark.parametrize("text, message", [
    ("x,y,mag\n1,2,3\n", "has no true ids"),
    ("x,y,mag,hip,ra\n1,2,3,4,5\n", "unknown column 'ra'"),
])
def test_score_refuses_bad_files(tmp_path, capsys, text, message):
    (tmp_path / "bad.csv").write_text(text)
    assert cli.main(["score", str(tmp_path / "bad.csv")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


@pytest.mark.slow
@pytest.mark.skipif(not (ORESAT_TRUTH / "stars.csv").exists(), reason="no OreSat data")
def test_score_real_labelled_centroids(tmp_path, capsys):
    """The stars an independent plate solver matched on eight OreSat frames (17° field)."""
    out = tmp_path / "oresat.json"
    assert cli.main(["score", str(ORESAT_TRUTH / "stars.csv"), "--size", "1280x960", "--fov", "17.06",
                     "--ignore-columns", "ra_deg_j2000,dec_deg_j2000,hip_sep_arcsec,anet_flux,anet_resid_px",
                     "--out", str(out)]) == 0
    total = json.loads(out.read_text())["total"]
    assert total["wrong"] == 0 and total["right"] >= 7 and total["precision"] == 1.0
    assert total["recall"] > 0.7 and total["blend_names"] >= 1  # ν Draconis
