"""One call from a user's frame to names, attitude and WCS: :func:`solve` (the CLI's path too).

``js.solve(image_or_centroids, camera)`` runs what ``jstarid solve`` and ``jstarid identify`` run, in
this order:

1. **Detections.** An image (a path or a (H, W) array) goes through :func:`jstarid.extract_centroids`;
   centroids ((n, 2) x, y or (n, 3) x, y, magnitude, px) are packed by
   :func:`jstarid.scenes_from_centroids`. The camera's lens distortion is undone.
2. **Identification** by the registry's ``algorithm`` with its default config for the camera
   (``Config.for_camera`` where it has one), against a catalog as deep as the camera's detection limit
   (for a camera described by size and field of view: the field's depth,
   :func:`jstarid.sky_depth.identification_depth`).
3. **Naming** (``name_all``): the solved attitude and focal length name every detection they explain
   (:func:`jstarid.name_from_attitude`) against a deeper catalog
   (:func:`jstarid.sky_depth.naming_depth`: the whole of Hipparcos unless the pixels are coarse).
4. **Blends.** A named star with another Hipparcos star within the naming tolerance (for detections
   extracted from an image: within the centroid window, :data:`IMAGE_BLEND_PX`) that is at most
   :data:`BLEND_MAG` fainter (so that it moves the centroid) is reported as a blend of both
   (``Star.blend``): the detection is the light of the pair, and either number may be the one a
   reference solution lists.

The result is one :class:`Solution` per frame: per named detection its Hipparcos number and pixel,
the attitude, boresight and roll, the fitted focal-length scale and radial distortion, and
:meth:`Solution.to_dict` (the CLI's JSON).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jstarid.catalog import load_every_star
from jstarid.centroid import CentroidConfig
from jstarid.false_match import of_solutions

__all__ = ["Solution", "Star", "solve", "solve_scenes"]

#: The camera of a user's frames when none is given (identify, solve, score, calibrate, train): a real
#: tracker's, 11.4° over 1024×768. Sweeps default to the papers' camera instead.
DEFAULT_CAMERA = "tetra3_test"
IMAGE_CAPACITY = 24  # detections of an image the algorithm uses (the brightest)
CENTROID_CAPACITY = 64  # centroids of a given scene the algorithm uses
# a companion whose light reaches the centroid window of an extracted detection (the window's
# half-diagonal, CentroidConfig.window_px = 4, plus a PSF core's 2 px) blends with it
IMAGE_BLEND_PX = 4.0 * math.sqrt(2.0) + 2.0
NAMING_CAPACITY = 512  # detections per frame that naming looks at (the algorithms use fewer)
# peaks the extractor examines per image: noisy 8-bit frames (OreSat's) hold hundreds of hot pixels
# and noise peaks above 5 σ, which would otherwise crowd out the faint stars
NAMING_CENTROIDS = CentroidConfig(max_peaks=2 * NAMING_CAPACITY)
BLEND_MAG = 2.5  # a companion up to 2.5 mag fainter (10 % of the flux) moves a blended centroid


@dataclasses.dataclass(frozen=True)
class Star:
    """A named detection.

    Attributes:
        hip: Hipparcos number (for a catalog close pair merged into one entry: the brighter's).
        x: column (px) as measured (before the lens distortion is undone).
        y: row (px) as measured.
        v: the star's V (mag).
        detection: the detection's slot in its scene (brightest first).
        blend: Hipparcos numbers of every star the detection may be the light of (``hip`` first);
            ``()`` for a single star.
    """

    hip: int
    x: float
    y: float
    v: float
    detection: int
    blend: tuple[int, ...] = ()


@dataclasses.dataclass(frozen=True)
class Solution:
    """The solution of one frame (module docstring); attitude fields are ``None`` when not solved.

    Attributes:
        label: the frame's name (its path, or ``scene i``).
        solved: an attitude was found and its names agree.
        detections: detections used (at most the capacity).
        stars: the named detections.
        camera: the nominal camera (with its lens distortion).
        attitude: (3, 3) rotation, ``v_cam = C r_icrs`` (docs/conventions.md §1).
        ra_deg, dec_deg, roll_deg: boresight and roll (deg).
        residual_arcsec: RMS angle between the named detections, seen through the fitted focal
            length and radial term, and their stars (arcsec).
        focal_scale: fitted focal length / nominal (``None`` where not fitted).
        distortion_k1: fitted radial term (:mod:`jstarid.camera_fit`; ``None`` where not fitted).
        false_match_probability: an upper bound on the chance that a blind search finds a wrong
            attitude confirming as many of the algorithm's detections as this solution does
            (:mod:`jstarid.false_match`; the one that decided the claim, of its names or of the
            frame named from its attitude, where the algorithm ends with the finishing stage);
            near 1 means the names could be a coincidence.
        epoch: the star positions' epoch (Julian year; ``None``: the catalog's J1991.25).
    """

    label: str
    solved: bool
    detections: int
    stars: tuple[Star, ...]
    camera: object
    attitude: np.ndarray | None = None
    ra_deg: float | None = None
    dec_deg: float | None = None
    roll_deg: float | None = None
    residual_arcsec: float | None = None
    focal_scale: float | None = None
    distortion_k1: float | None = None
    false_match_probability: float | None = None
    epoch: float | None = None

    def wcs(self):
        """The solution as an ``astropy.wcs.WCS`` (TAN, TAN-SIP where a lens distortion was given or
        fitted; :func:`jstarid.wcs.wcs_from_solution`).

        Raises:
            ValueError: the frame was not solved.
        """
        from jstarid.wcs import wcs_from_solution

        if not self.solved:
            raise ValueError(f"{self.label} was not solved: it has no WCS")
        return wcs_from_solution(self.camera, self.to_dict())

    def to_dict(self) -> dict:
        """The JSON entry the CLI writes (``scene``, ``detections``, ``solved``, ``stars`` and, when
        solved, attitude fields)."""
        import jstarid as js

        entry = {"scene": self.label, "detections": self.detections, "solved": self.solved,
                 "stars": [{"hip": s.hip, "x": s.x, "y": s.y, "v": s.v, "detection": s.detection,
                            **({"blend": list(s.blend)} if s.blend else {})} for s in self.stars]}
        if self.solved:
            entry.update(ra_deg=self.ra_deg, dec_deg=self.dec_deg, roll_deg=self.roll_deg,
                         residual_arcsec=self.residual_arcsec, attitude=self.attitude.tolist(),
                         quaternion=np.asarray(js.quaternion_from_rotation(self.attitude)).tolist(),
                         false_match_probability=self.false_match_probability)
            if self.focal_scale is not None:
                f_px = self.camera.f_px * self.focal_scale
                entry.update(focal_scale=self.focal_scale, f_px_fitted=f_px,
                             fov_x_deg_fitted=math.degrees(2 * math.atan(self.camera.width / 2 / f_px)))
            if self.distortion_k1 is not None:
                entry.update(distortion_k1=self.distortion_k1)
        return entry


def solve(frames, camera=DEFAULT_CAMERA, algorithm: str = "mlv", *, epoch: float | None = None,
          mag_limit: float | None = None, capacity: int | None = None, name_all: bool = True,
          tol_px: float = 2.0, fov_max_error: float = 0.1, overrides: Sequence[str] = (),
          rpnet_network: str = "quick", labels: Sequence[str] | None = None):
    """Names, attitude and focal length of one frame or many (module docstring).

    Args:
        frames: one frame or a list of them. A frame is an image (a path, or a (H, W) array of pixel
            values) or centroids ((n, 2) x, y or (n, 3) x, y, magnitude, px, the rows brightest
            first without magnitudes; or a centroid file, ``.csv``/``.tsv``/``.json``, whose every
            scene is a frame).
        camera: a preset name, a camera file or a :class:`~jstarid.Camera`.
        algorithm: registry name (``mlv``, ``sgm``, ``rpnet``, …).
        epoch: the observation's Julian year (proper motion); ``None``: the catalog's J1991.25.
        mag_limit: identification catalog depth (V mag); ``None``: the camera's detection limit.
        capacity: detections the algorithm uses per frame (the brightest); ``None``:
            :data:`IMAGE_CAPACITY` for images, :data:`CENTROID_CAPACITY` for centroids. Naming
            (``name_all``) uses up to :data:`NAMING_CAPACITY`.
        name_all: name every detection the attitude explains (step 3).
        tol_px: naming tolerance (px).
        fov_max_error: how far off the camera's focal length (field of view) may be: unsolved frames
            are tried again at 1 % steps out to it (the finishing stage's ladder), and a solved
            frame may need at most this correction.
        overrides: ``FIELD=VALUE`` items for the algorithm's config (JSON values).
        rpnet_network: RpNet's network preset (trained for the camera on first use).
        labels: a name per frame (default: the path, or ``frame i``).

    Returns:
        A :class:`Solution`, or a list of them for a list of frames (or a file of several scenes).

    Raises:
        ValueError: an unreadable file, images of another size than the camera's, bad centroids or
            settings.
    """
    import jstarid as js
    from jstarid.camera_files import load_camera

    single = not isinstance(frames, list | tuple)
    items = [frames] if single else list(frames)
    if not items:
        raise ValueError("solve needs at least one frame")
    cam = load_camera(camera)
    kinds = {_kind(f) for f in items}
    if len(kinds) != 1:
        raise ValueError("give either images or centroids, not both in one call")
    if kinds == {"image"}:
        if labels is None:
            labels = [str(f) if isinstance(f, str | Path) else f"frame {i}" for i, f in enumerate(items)]
        measured = image_detections([js.read_image(f) if isinstance(f, str | Path)
                                     else np.asarray(f, np.float32) for f in items], cam)
    else:
        arrays, labels = _centroid_arrays(items, labels)
        if any(a.ndim != 2 or a.shape[1] not in (2, 3) for a in arrays):
            raise ValueError("centroids must be (n, 2) x, y or (n, 3) x, y, magnitude arrays (px)")
        mags = None if all(a.shape[1] == 2 for a in arrays) else [
            a[:, 2] if a.shape[1] == 3 else np.arange(len(a), dtype=float) for a in arrays]
        measured = js.scenes_from_centroids([a[:, :2] for a in arrays], mags,
                                            capacity=max(NAMING_CAPACITY, capacity or CENTROID_CAPACITY))
    capacity = capacity or (IMAGE_CAPACITY if kinds == {"image"} else CENTROID_CAPACITY)
    out = solve_scenes(measured, cam, algorithm, labels=list(labels), capacity=capacity, epoch=epoch,
                       mag_limit=mag_limit, blend_px=IMAGE_BLEND_PX if kinds == {"image"} else None,
                       name_all=name_all, tol_px=tol_px, fov_max_error=fov_max_error,
                       overrides=overrides, rpnet_network=rpnet_network)
    return out[0] if single and len(out) == 1 else out


def image_detections(images, camera):
    """The detections naming looks at (:data:`NAMING_CAPACITY`, brightest first) of (H, W) images
    taken by ``camera``, as measured (lens distortion not undone): a (B, N) Scene.

    Raises:
        ValueError: an image of another size than the camera's.
    """
    from jstarid.centroid import extract_centroids

    if any(np.shape(im) != (camera.height, camera.width) for im in images):
        raise ValueError(f"every image must be {camera.height}×{camera.width} px (camera {camera.name}); "
                         f"got {sorted({np.shape(im) for im in images})}")
    return extract_centroids(np.stack(images), NAMING_CENTROIDS, capacity=NAMING_CAPACITY, shard=True)


def _centroid_arrays(items, labels):
    """(n, 2|3) arrays and labels of centroid frames: arrays as given, files read by
    :func:`jstarid.centroid_files.read_centroid_set` (every scene of a file is a frame)."""
    from jstarid.centroid_files import read_centroid_set

    arrays, names = [], []
    for i, item in enumerate(items):
        if isinstance(item, str | Path):
            found = read_centroid_set(item).brightest_first()
            for label, xy, mag in zip(found.labels, found.xy, found.mag, strict=True):
                arrays.append(xy if mag is None else np.column_stack([xy, mag]))
                names.append(str(item) if len(found) == 1 else f"{item}#{label}")
        else:
            arrays.append(np.asarray(item, np.float64))
            names.append(f"frame {i}")
    if labels is not None and len(labels) != len(arrays):
        raise ValueError(f"got {len(labels)} labels for {len(arrays)} frames")
    return arrays, names if labels is None else list(labels)


def _kind(frame) -> str:
    if isinstance(frame, str | Path):
        return "centroids" if Path(frame).suffix.lower() in (".csv", ".tsv", ".json") else "image"
    array = np.asarray(frame)
    # no image is 2 or 3 px wide
    return "centroids" if array.ndim == 2 and array.shape[1] in (2, 3) else "image"


def solve_scenes(measured, camera, algorithm: str = "mlv", *, labels: Sequence[str], capacity=None,
                 epoch=None,
                 mag_limit=None, name_all: bool = True, tol_px: float = 2.0,
                 fov_max_error: float = 0.1, overrides: Sequence[str] = (),
                 rpnet_network: str = "quick", blend_px: float | None = None, log=None) -> list[Solution]:
    """Steps 2–4 of the module docstring on ``measured`` scenes (centroids as measured, px).

    Args:
        measured: (B, N) :class:`~jstarid.Scene` of measured centroids (lens distortion not undone),
            brightest first.
        capacity: detections the algorithm uses (the brightest; ``None``: all N); naming uses all N.
        camera: the :class:`~jstarid.Camera` that measured them.
        labels: B names.
        blend_px: the distance (px) within which a companion star blends with a named one (default
            ``tol_px``; :data:`IMAGE_BLEND_PX` for detections extracted from images).
        log: a callable taking one line (default: print to stderr); the first-use notice goes there.
        Other arguments: as :func:`solve`.

    Returns:
        B :class:`Solution`.
    """
    import jstarid as js
    from jstarid.algorithms import base
    from jstarid.experiment import with_overrides
    from jstarid.scene import brightest
    from jstarid.sky_depth import naming_depth

    log = log or (lambda line: print(line, file=sys.stderr))
    if len(labels) != measured.xy.shape[0]:
        raise ValueError(f"got {len(labels)} labels for {measured.xy.shape[0]} scenes")
    scenes = js.undistort_scenes(measured, camera)
    pinhole = camera.pinhole()  # the scenes' centroids are undistorted already
    limit = pinhole.mag_limit if mag_limit is None else float(mag_limit)
    cat = js.load_catalog(limit, epoch=epoch)
    algo = js.algorithms.get(algorithm)
    cfg = with_overrides(js.engine.default_config(algorithm, rpnet_network=rpnet_network,
                                                  camera=pinhole, frames=True), list(overrides))
    if getattr(cfg, "finishing", None) is not None:  # a field of view known to ± fov_max_error
        cfg = dataclasses.replace(cfg, finishing=cfg.finishing.reaching(fov_max_error))
    js.engine.check_camera([js.Entry(algorithm, algorithm, cfg)], pinhole, cat)
    built = base.first_use(algo, cat, pinhole, cfg)
    if built:
        took = f"{built[1] / 60:.0f} min" if built[1] >= 90 else f"{max(built[1], 1):.0f} s"
        log(f"first use builds {built[0]} (≈ {took} on 2 CPU cores), once")
    few = brightest(scenes, capacity or scenes.capacity)
    result = algo.identify(algo.build_database(cat, pinhole, cfg), few, cfg)
    # the evidence of the identification itself: its catalog, the detections it was given; the
    # probability that decided the claim where the algorithm's finishing stage gives it
    false_match = of_solutions(few, result, cat, pinhole)
    if not name_all:  # the algorithm's names only: the detections it was given
        scenes, measured = few, brightest(measured, few.capacity)
    else:
        deep = js.load_catalog(naming_depth(pinhole, tol_px, at_least=limit), epoch=epoch)
        result = _to_catalog(_widened(result, scenes.capacity), cat, deep)
        cat = deep
        result = js.name_from_attitude(cat, pinhole, scenes, result, tol_px=tol_px,
                                       max_scale_error=fov_max_error)
    att, _, have = (np.asarray(a) for a in js.estimate_attitude(cat, pinhole, scenes, result))
    if result.attitude is not None:  # the camera fit's attitude (focal length fitted with it)
        fitted = np.isfinite(np.asarray(result.attitude)).all(axis=(1, 2))
        att = np.where(fitted[:, None, None], np.asarray(result.attitude), att)
    b = len(labels)
    scale = np.full(b, np.nan) if result.focal_scale is None else np.asarray(result.focal_scale, float)
    k1 = np.full(b, np.nan) if result.distortion_k1 is None else np.asarray(result.distortion_k1, float)
    ra, dec, roll = (np.degrees(np.asarray(a, np.float64)) for a in js.rotation_to_radec_roll(att))
    xy = np.asarray(measured.xy)
    ids, ok = np.asarray(result.ids), np.asarray(result.ok)
    n_det = np.asarray(measured.valid).sum(axis=1)
    residual = _residual_arcsec(pinhole, scenes, ids, cat.unit_vectors, att, scale, k1)
    blends = _blend_finder(cat, pinhole, tol_px if blend_px is None else blend_px)
    out = []
    for i, label in enumerate(labels):
        named = np.nonzero(ids[i] >= 0)[0]
        solved = bool(ok[i] and have[i])
        stars = tuple(Star(hip=int(cat.hip[ids[i, j]]), x=float(xy[i, j, 0]), y=float(xy[i, j, 1]),
                           v=float(cat.mag[ids[i, j]]), detection=int(j), blend=blends(int(ids[i, j])))
                      for j in named)
        fields = {}
        if solved:
            fields = dict(attitude=np.asarray(att[i], np.float64), ra_deg=float(ra[i]),
                          dec_deg=float(dec[i]), roll_deg=float(roll[i]),
                          residual_arcsec=float(residual[i]),
                          focal_scale=float(scale[i]) if np.isfinite(scale[i]) else None,
                          distortion_k1=float(k1[i]) if np.isfinite(k1[i]) else None,
                          false_match_probability=float(false_match[i]))
        out.append(Solution(label=label, solved=solved, detections=int(n_det[i]), stars=stars,
                            camera=camera, epoch=epoch, **fields))
    return out


def _residual_arcsec(camera, scenes, ids, star_vectors, attitude, scale, k1) -> np.ndarray:
    """(B,) RMS angle (arcsec) between the named detections, seen through each scene's fitted focal
    length ``scale · f_px`` and radial term ``k1`` (:func:`jstarid.camera_fit.unproject_scaled`;
    1 and 0 where not fitted), and their stars rotated by ``attitude`` (B, 3, 3); NaN where nothing
    is named."""
    from jstarid.camera_fit import unproject_scaled
    from jstarid.geometry.angles import angle_between

    scale = np.where(np.isfinite(scale), scale, 1.0).astype(np.float32)
    k1 = np.where(np.isfinite(k1), k1, 0.0).astype(np.float32)
    body = unproject_scaled(camera, np.asarray(scenes.xy), scale[:, None], k1[:, None])
    ref = np.asarray(star_vectors, np.float32)[np.clip(ids, 0, len(star_vectors) - 1)]
    pred = np.einsum("bij,bnj->bni", np.nan_to_num(attitude), ref)
    angle = np.asarray(angle_between(body, pred), np.float64)
    named = (ids >= 0) & np.asarray(scenes.valid)
    with np.errstate(invalid="ignore"):
        mean_square = np.where(named, angle**2, 0.0).sum(axis=1) / named.sum(axis=1)
    return np.degrees(np.sqrt(mean_square)) * 3600.0


def _widened(result, n: int):
    """``result`` of the brightest detections padded with unnamed ones to ``n`` per scene."""
    ids = np.asarray(result.ids)
    if ids.shape[1] == n:
        return result
    wide = np.full((ids.shape[0], n), -1, np.int32)
    wide[:, :ids.shape[1]] = ids
    return dataclasses.replace(result, ids=wide)


def _to_catalog(result, source, target):
    """``result`` with its catalog rows of ``source`` moved to the rows of the same Hipparcos numbers
    in ``target`` (a deeper catalog holds every star of a shallower one)."""
    ids = np.asarray(result.ids)
    named = ids >= 0
    rows = np.full(ids.shape, -1, np.int32)
    if named.any():
        rows[named] = target.row_of_hip(source.hip[ids[named]])
    return dataclasses.replace(result, ids=rows)


def _blend_finder(catalog, camera, blend_px: float):
    """``blend(row) -> tuple of HIP numbers``: the stars (all of Hipparcos, close pairs not merged)
    within ``blend_px`` of catalog row ``row`` and at most :data:`BLEND_MAG` fainter than it, or ``()``
    when it is the only one."""
    from scipy.spatial import cKDTree


    every = load_every_star(catalog.settings["epoch"])
    radius = max(blend_px / camera.f_px, math.radians(catalog.settings["double_sep_deg"]))
    tree = cKDTree(every.unit_vectors)

    def blend(row: int) -> tuple[int, ...]:
        near = tree.query_ball_point(catalog.unit_vectors[row], 2.0 * math.sin(radius / 2.0))
        near = [j for j in near if every.mag[j] <= catalog.mag[row] + BLEND_MAG]
        hips = [int(catalog.hip[row])] + sorted({int(every.hip[j]) for j in near} - {int(catalog.hip[row])})
        return tuple(hips) if len(hips) > 1 else ()

    return blend
