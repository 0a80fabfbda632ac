"""The twin check: a labelled set of real detections against its simulated twin, algorithm by algorithm.

A sweep is worth trusting when the simulator predicts the user's real detections. Given a labelled set
(centroids, measured magnitudes and each detection's true Hipparcos number, −1 for a false star:
:mod:`jstarid.centroid_files`) and the camera that took it:

1. **Fit** (:func:`fit_labelled`). Each scene's attitude is the Wahba fit of its labelled catalog stars
   (three or more); every catalog star that attitude puts in the field, to a magnitude past the
   faintest labelled star, is a star that could have been detected. Whether it was (its number among
   the labels), its measured − catalog magnitude and its position residual (undistorted pixels) feed
   :meth:`jstarid.DetectionModel.fit`; the detections that are no catalog star become the clutter.
2. **Twin** (:func:`twin_scenes`). As many simulated scenes as asked, drawn from the fitted model and
   noise by the sweep engine (:func:`jstarid.engine.simulate_levels`), on the real set's sky
   (:func:`near_attitudes`), at its scenes' attitudes exactly, or anywhere; their magnitudes carry
   the set's zero point.
3. **Compare** (:func:`twin_check`). Every algorithm runs on both through
   :func:`jstarid.engine.compare`, scored strictly; a rate's twin value agrees when it lies within the
   real set's 95 % Wilson interval. Where the twin's scenes are drawn from the real ones (sky
   ``"real"`` or ``"exact"``), :meth:`TwinCheck.scene_rows` sets each real scene's outcome beside the
   twin's rate on the scenes drawn from it: a gap the twin's sampling of the sky cannot explain shows
   in scenes the twin finds hard and the real set solved (or the reverse).

``jstarid twin LABELLED --camera …`` is the command line.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.catalog import FULL_DEPTH, load_catalog
from jstarid.metrics import CORRECT, OUTCOME_NAMES
from jstarid.scene import brightest

__all__ = ["LabelledFit", "TwinCheck", "fit_labelled", "near_attitudes", "source_scenes", "twin_check",
           "twin_scenes"]

MIN_LABELLED = 3  # labelled catalog stars that fix a scene's attitude
DEPTH_PAST_LABELS_MAG = 1.0  # records reach this far past the faintest labelled star (completeness)
SKIES = ("real", "exact", "random")  # twin_scenes' sky
DRAW_CAPACITY = 1024  # detections a twin scene is drawn with before the algorithms' cut
LEVELS = ({"twin": 0}, {"twin": 1})  # the engine's levels: the labelled set, its twin


class LabelledFit(NamedTuple):
    """A detection model fitted to a labelled set (:func:`fit_labelled`).

    Attributes:
        fit: :class:`jstarid.detection_fit.DetectionFit` (model, floors, magnitude offset, clutter).
        attitudes: (B, 3, 3) float64 rotation ICRS → camera of each scene, NaN where fewer than
            :data:`MIN_LABELLED` labelled catalog stars fixed it.
        solved: (B,) bool, the scenes whose attitude was fitted (the only ones in the fit).
        depth_mag: V of the faintest catalog star counted as one that could have been detected.
        residual_px: (B,) RMS position residual of each scene's labelled stars (px; NaN unsolved).
        detections: (B,) detections per scene (all, labelled or not).
    """

    fit: object
    attitudes: np.ndarray
    solved: np.ndarray
    depth_mag: float
    residual_px: np.ndarray
    detections: np.ndarray


def fit_labelled(found, camera, *, epoch: float | None = None, catalog=None) -> LabelledFit:
    """Fit the detection model of ``camera`` to a labelled set (module docstring, step 1).

    Args:
        found: a labelled :class:`~jstarid.centroid_files.CentroidSet` with magnitudes (or fluxes).
        camera: the :class:`~jstarid.Camera` that took it (its distortion is undone).
        epoch: Julian year of the observations (proper motion), ``None``: J1991.25.
        catalog: the identification :class:`~jstarid.Catalog`, whose close-pair settings the deep
            catalog of the fit shares (so a star it drops is clutter here as in the twin's sky).

    Returns:
        :class:`LabelledFit`.

    Raises:
        ValueError: the set is not labelled, has no magnitudes, or too few scenes have an attitude or
            too few stars are detected to fit (:meth:`~jstarid.DetectionModel.fit`).
    """
    from jstarid.attitude import solve_wahba
    from jstarid.detection_fit import fit_detection

    if not found.labelled:
        raise ValueError("the twin check needs a labelled set: a true Hipparcos number per detection "
                         "(−1 for a false star)")
    if any(m is None for m in found.mag):
        raise ValueError("the twin check needs measured brightness (a mag or flux column): the "
                         "detection model is fitted to it")
    kept = ("double_sep_deg", "double_mode")
    pairs = {} if catalog is None else {k: v for k, v in catalog.settings.items() if k in kept}
    full = load_catalog(FULL_DEPTH, epoch=epoch, sim_margin=0.0, **pairs)
    rows_of = [full.row_of_hip(h) if len(h) else np.zeros(0, np.int32) for h in found.hip]  # −1: none
    labelled_v = np.concatenate([full.mag[r[r >= 0]] for r in rows_of])
    faintest = float(labelled_v.max()) if labelled_v.size else camera.mag_limit
    depth = min(FULL_DEPTH, max(faintest, camera.mag_limit) + DEPTH_PAST_LABELS_MAG)
    deep = full.mag <= depth
    vectors, star_mag = full.unit_vectors[deep], full.mag[deep]

    b = len(found)
    xys = [np.asarray(camera.undistort(np.asarray(x, np.float64).reshape(-1, 2)), np.float64)
           for x in found.xy]
    rows = [np.where(r < deep.sum(), r, -1) for r in rows_of]  # rows of the deep list (brightest first)
    solved = np.array([(r >= 0).sum() >= MIN_LABELLED for r in rows], bool)
    if not solved.any():
        raise ValueError(f"no scene has {MIN_LABELLED} or more labelled catalog stars to fix its "
                         f"attitude")
    # every attitude in one Wahba call: the labelled stars padded to one length, weight 0 beyond
    width = max(int((r >= 0).sum()) for r in rows)
    pixels = np.tile([camera.cx, camera.cy], (b, width, 1))  # padding: the principal point (+z)
    ref, weight = np.zeros((b, width, 3)), np.zeros((b, width))
    ref[..., 2] = 1.0
    for i in np.nonzero(solved)[0]:
        star = rows[i] >= 0
        n = int(star.sum())
        pixels[i, :n], ref[i, :n], weight[i, :n] = xys[i][star], vectors[rows[i][star]], 1.0
    weight[~solved, 0] = 1.0  # a harmless problem for the scenes without an attitude
    body = camera.unproject(pixels)
    attitudes = np.asarray(solve_wahba(body, ref, weight), np.float64)
    attitudes[~solved] = np.nan
    residual = np.full(b, np.nan)
    true_v, detected, measured, position, unmatched = [], [], [], [], []
    for i in np.nonzero(solved)[0]:
        proj, front = (np.asarray(a) for a in camera.project(np.einsum("ij,nj->ni", attitudes[i],
                                                                       vectors)))
        inside = np.nonzero(front)[0]
        at = {int(r): j for j, r in enumerate(rows[i]) if r >= 0}
        hit = np.array([int(r) in at for r in inside], bool)
        det = np.array([at[int(r)] for r in inside[hit]], np.int64)
        dmag = np.full(inside.size, np.nan)
        dxy = np.full((inside.size, 2), np.nan)
        dmag[hit] = found.mag[i][det]
        dxy[hit] = xys[i][det] - proj[inside[hit]]
        residual[i] = float(np.sqrt(np.mean(np.sum(dxy[hit] ** 2, axis=1))))
        true_v.append(star_mag[inside])
        detected.append(hit)
        measured.append(dmag)
        position.append(dxy)
        unmatched.append(found.mag[i][rows[i] < 0])
    fit = fit_detection(np.concatenate(true_v), np.concatenate(detected), np.concatenate(measured),
                        np.concatenate(position),
                        unmatched_mag=np.concatenate(unmatched),
                        frames=int(solved.sum()))
    return LabelledFit(fit, attitudes, solved, float(depth), residual,
                       np.array([len(x) for x in found.xy]))


def real_scenes(found, labelled: LabelledFit, camera, catalog, capacity: int):
    """The labelled set as a :class:`~jstarid.Scene` batch (truth in ``catalog``'s rows, the fitted
    attitudes; NaN where none was fitted)."""
    scenes = found.scenes(capacity, camera=camera, catalog=catalog)
    return dataclasses.replace(scenes, attitude=jnp.asarray(labelled.attitudes, jnp.float32))


def twin_scenes(labelled: LabelledFit, camera, catalog, *, scenes: int, seed: int = 0,
                capacity: int = 64, sky: str = "real", progress: bool = False):
    """The set's simulated twin (module docstring, step 2).

    Args:
        labelled: :func:`fit_labelled`'s result.
        camera, catalog: the camera and the identification catalog (truth in its rows).
        scenes: how many twin scenes. seed: their PRNG seed. capacity: detections kept per scene.
        sky: ``"real"`` (:func:`near_attitudes` of the solved real scenes), ``"exact"`` (their
            attitudes themselves, in turn: the same stars in the same places, new detections) or
            ``"random"`` (uniform attitudes, as a sweep draws them). Twin scene j is drawn from
            solved real scene j mod R with the first two.

    Returns:
        ``(scenes, detections, settings)``: a :class:`~jstarid.Scene` batch of ``capacity``, (S,)
        detections per scene before the cut (at most :data:`DRAW_CAPACITY`; ``overflow`` flags more)
        and the engine's drawing settings.
    """
    from jstarid.engine import simulate_levels

    if sky not in SKIES:
        raise ValueError(f"sky must be one of {SKIES}, got {sky!r}")
    fit = labelled.fit
    fixed = {"magnitude_sigma": fit.magnitude_sigma, **fit.clutter}
    solved = labelled.attitudes[labelled.solved]
    attitudes = None  # sky "random": the engine draws them
    if sky == "real":
        attitudes = near_attitudes(solved, camera, scenes, seed)
    elif sky == "exact":
        attitudes = solved[source_scenes(scenes, len(solved))]
    # drawn at a capacity that holds every detection (their count is compared), then cut to the
    # algorithms' brightest ``capacity`` as a file's scenes are (overflow flagged)
    drawn = simulate_levels(camera, axes={"position_sigma_px": [fit.position_sigma_px]},
                            fixed=fixed, scenes=scenes, seed=seed, catalog=catalog,
                            capacity=max(capacity, DRAW_CAPACITY), attitudes=attitudes,
                            progress=progress, detection=fit.model)
    every = drawn.scenes
    twin = brightest(every, capacity)
    # the set's zero point: measured = catalog V + offset (the clutter was fitted in catalog V)
    mag = jnp.where(twin.valid, twin.mag + np.float32(fit.magnitude_offset), twin.mag)
    return dataclasses.replace(twin, mag=mag), np.asarray(every.n_stars), drawn.settings


def source_scenes(count: int, solved: int) -> np.ndarray:
    """(count,) int: the solved real scene each twin scene is drawn from with sky ``"real"`` or
    ``"exact"`` — each in turn (twin j from solved scene j mod ``solved``)."""
    return np.arange(count) % solved


def near_attitudes(attitudes, camera, count: int, seed: int = 0) -> np.ndarray:
    """``count`` attitudes near the given ones: each in turn, rolled about its boresight at random and
    tilted by up to a quarter of the field's height in each axis (uniform).

    The twin's sky is the real set's (star density, bright stars) while no star sits at the centre of
    every scene (a boresight put on a catalog star would favour an algorithm that starts from the
    star nearest the centre, as SGM does).

    Args:
        attitudes: (R, 3, 3) rotations ICRS → camera. camera: the :class:`~jstarid.Camera`.
        count: how many. seed: the draw's seed.

    Returns:
        (count, 3, 3) float64 rotations.
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    tilt = np.radians(camera.fov_y_deg / 4.0)
    turn = np.column_stack([rng.uniform(-tilt, tilt, (count, 2)), rng.uniform(-np.pi, np.pi, count)])
    base = np.asarray(attitudes, np.float64)[source_scenes(count, len(attitudes))]
    # camera-frame turns applied after the real attitude: C' = R C
    return np.einsum("bij,bjk->bik", Rotation.from_rotvec(turn).as_matrix(), base)


class TwinCheck(NamedTuple):
    """A labelled set and its twin, every algorithm on both (:func:`twin_check`).

    Attributes:
        labelled: :class:`LabelledFit`.
        result: :class:`~jstarid.SweepResult` with two levels, ``{"twin": 0}`` (the labelled set)
            and ``{"twin": 1}`` (its twin).
        detections: ``{"real": …, "twin": …}`` median detections per scene.
        labels: the labelled set's scene labels (its file order).
    """

    labelled: LabelledFit
    result: object
    detections: dict
    labels: tuple = ()

    def scene_rows(self) -> list[dict]:
        """Per solved real scene, with sky ``"real"`` or ``"exact"`` (else none): its label, the twin
        scenes drawn from it, and per entry the real scene's outcome (a name of
        :data:`jstarid.metrics.OUTCOME_NAMES`) beside the share of those twin scenes identified."""
        settings = self.result.settings
        if settings.get("sky") not in ("real", "exact"):
            return []
        outcome = np.asarray(self.result.scenes["outcome"])
        n_real = settings["real_scenes"]
        real, twin = outcome[:n_real], outcome[n_real:]
        solved = np.nonzero(self.labelled.solved)[0]
        source = solved[source_scenes(len(twin), len(solved))]
        rows = []
        for i in solved:
            drawn = twin[source == i]
            row = {"scene": self.labels[i] if self.labels else str(i), "twin_scenes": len(drawn)}
            for e, entry in enumerate(self.result.entries):
                row[f"{entry['label']}_real"] = OUTCOME_NAMES[int(real[i, e])]
                right = drawn[:, e] == CORRECT
                row[f"{entry['label']}_twin"] = float(right.mean()) if right.size else float("nan")
            rows.append(row)
        return rows

    def rows(self) -> list[dict]:
        """Per entry: real and twin identification and mis-identification rates with their 95 %
        Wilson intervals, and whether each twin rate lies inside the real interval."""
        out = []
        by_label: dict[str, dict] = {}
        for r in self.result.rows():
            side = "real" if r["twin"] == 0 else "twin"
            row = by_label.setdefault(r["label"], {"label": r["label"]})
            row[f"{side}_scenes"] = r["scenes"]
            for rate in ("identification", "misid"):
                row[f"{side}_{rate}"] = r[f"{rate}_rate"]
                row[f"{side}_{rate}_low"], row[f"{side}_{rate}_high"] = r[f"{rate}_low"], r[f"{rate}_high"]
        for row in by_label.values():
            for rate in ("identification", "misid"):
                row[f"{rate}_agrees"] = bool(row[f"real_{rate}_low"] <= row[f"twin_{rate}"]
                                             <= row[f"real_{rate}_high"])
            out.append(row)
        return out

    def table(self) -> str:
        """Markdown: one row per algorithm, real and twin side by side."""
        fit = self.labelled.fit
        lines = ["| algorithm | real identified | twin identified | agrees | real wrong | twin wrong "
                 "| agrees |", "|---|---:|---:|:-:|---:|---:|:-:|"]

        def cell(row, side, rate):
            return (f"{100 * row[f'{side}_{rate}']:.1f} % [{100 * row[f'{side}_{rate}_low']:.1f}–"
                    f"{100 * row[f'{side}_{rate}_high']:.1f}] of {row[f'{side}_scenes']}")

        for row in self.rows():
            lines.append(f"| {row['label']} | {cell(row, 'real', 'identification')} | "
                         f"{cell(row, 'twin', 'identification')} | "
                         f"{'yes' if row['identification_agrees'] else 'NO'} | "
                         f"{cell(row, 'real', 'misid')} | {cell(row, 'twin', 'misid')} | "
                         f"{'yes' if row['misid_agrees'] else 'NO'} |")
        model = fit.model
        half = model.faintest_detectable(fit.magnitude_sigma, odds=0.5)
        lines += ["", f"Fitted to {int(self.labelled.solved.sum())} of {len(self.labelled.solved)} "
                      f"scenes ({fit.detected} of {fit.stars} catalog stars to V "
                      f"{self.labelled.depth_mag:.1f} detected): 50 % complete at V {half:.2f}; floors "
                      f"σ_m {fit.magnitude_sigma:.3f} mag, "
                      f"σ_xy {fit.position_sigma_px:.3f} px; clutter "
                      f"{fit.clutter.get('false_mean', 0.0):.2f} per scene; detections per scene "
                      f"(median) real {self.detections['real']:.0f}, twin {self.detections['twin']:.0f}. "
                      "Rates: % of scenes, strict (any wrong name is wrong), 95 % Wilson intervals; "
                      "a twin rate agrees when it lies within the real interval."]
        return "\n".join(lines) + "\n"


def _trained_on(entry, model):
    """``entry`` with its config training on ``model`` where it trains on simulated scenes."""
    if "train_detection" not in {f.name for f in dataclasses.fields(entry.config)}:
        return entry
    return entry._replace(config=dataclasses.replace(entry.config, train_detection=model))


def twin_check(found, camera, algorithms="sgm,mlv,rpnet", *, scenes: int = 1000, seed: int = 0,
               capacity: int = 64, epoch: float | None = None, catalog=None, sky: str = "real",
               rpnet_network: str | None = None, train_on_fit: bool = False,
               progress: bool = True) -> TwinCheck:
    """A labelled set against its simulated twin, every algorithm on both (module docstring).

    Args:
        found: a labelled :class:`~jstarid.centroid_files.CentroidSet` with magnitudes.
        camera: the :class:`~jstarid.Camera` that took it.
        algorithms: as in :func:`jstarid.sweep` (each algorithm with its defaults for the camera).
        scenes: twin scenes. seed: their seed. capacity: detections per scene (real and twin).
        epoch: Julian year of the observations. catalog: the identification catalog (default:
            Hipparcos to the camera's limit at ``epoch``). sky: :func:`twin_scenes`.
        rpnet_network, progress: as in :func:`jstarid.sweep`.
        train_on_fit: the algorithms that train on simulated scenes (a ``train_detection`` config
            field: RpNet) train on the model fitted to ``found`` instead of their default — the
            network of a camera whose real frames were measured.

    Returns:
        :class:`TwinCheck`.
    """
    from jstarid.engine import compare
    from jstarid.engine.entries import check_camera
    from jstarid.engine.entries import entries as make_entries

    catalog = load_catalog(camera.mag_limit, epoch=epoch) if catalog is None else catalog
    entries = make_entries(algorithms, rpnet_network=rpnet_network, camera=camera)
    check_camera(entries, camera, catalog)  # before anything is fitted
    labelled = fit_labelled(found, camera, epoch=epoch, catalog=catalog)
    if train_on_fit:
        entries = [_trained_on(e, labelled.fit.model) for e in entries]
    real = real_scenes(found, labelled, camera, catalog, capacity)
    twin, twin_detections, drawn = twin_scenes(labelled, camera, catalog, scenes=scenes, seed=seed,
                                               capacity=capacity, sky=sky, progress=progress)
    both = jax.tree.map(lambda a, b: jnp.concatenate([jnp.asarray(a), jnp.asarray(b)]), real, twin)
    level_of = np.repeat([0, 1], [real.batch_size, twin.batch_size]).astype(np.int32)
    settings = {**drawn, "levels": list(LEVELS), "real_scenes": real.batch_size, "sky": sky,
                "criterion": "strict"}
    result = compare(both, entries, catalog, camera, level_of=level_of, levels=list(LEVELS),
                     criterion="strict", progress=progress, settings=settings)
    detections = {"real": float(np.median(labelled.detections)),
                  "twin": float(np.median(twin_detections))}
    return TwinCheck(labelled, result, detections, tuple(found.labels))
