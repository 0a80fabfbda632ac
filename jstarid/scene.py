"""The two pytrees every algorithm shares: :class:`Scene` (input) and :class:`Identification` (output).

Both follow docs/conventions.md §3–4: a batch axis first, a static capacity N per scene with a ``valid``
mask, and pixel coordinates in the camera convention of :mod:`jstarid.camera`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Scene", "Identification", "pad_with_empty", "scenes_from_centroids", "undistort_scenes"]


def take_batch_rows(tree, index):
    """``tree`` (a :class:`Scene` or :class:`Identification`) at ``index`` of its batch axis.

    An int keeps a batch axis of 1. An index array, mask or slice is gathered on the host: the
    host loops of the search and the finishing stage pick sub-batches of every length, and an eager
    gather or slice of device arrays compiles a program for each new length (a slice's length is
    static in XLA's ``dynamic_slice``); the rows go back to the device as they came (a device array
    stays one). Inside a trace the gather is part of the program.
    """
    if isinstance(index, int | np.integer):
        index = slice(int(index), int(index) + 1)
    traced = any(isinstance(x, jax.core.Tracer) for x in (index, *jax.tree_util.tree_leaves(tree)))
    if traced:
        return jax.tree_util.tree_map(lambda a: a[index], tree)
    if isinstance(index, slice):
        index = np.arange(jax.tree_util.tree_leaves(tree)[0].shape[0])[index]
    index = np.asarray(index)

    def take(a):
        rows = np.asarray(a)[index]
        # device_put, not jnp.asarray: the latter compiles a staging program per shape
        return jax.device_put(rows) if isinstance(a, jax.Array) else rows

    return jax.tree_util.tree_map(take, tree)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scene:
    """A batch of B star-tracker scenes with static capacity N (docs/conventions.md §3).

    Attributes:
        xy: (B, N, 2) float32 centroids (px), zero where not ``valid``.
        mag: (B, N) float32 observed magnitude (mag), +inf where not ``valid``.
        truth: (B, N) int32 catalog row of each detection, −1 for a false star, a star that is not in
            the identification catalog, or padding.
        valid: (B, N) bool, a real detection (true or false star). Valid entries come first and are
            sorted by observed magnitude, brightest first.
        attitude: (B, 3, 3) float32 true rotation ``C`` (ICRS → camera); NaN when unknown.
        overflow: (B,) bool, more detections than N were in the field (the brightest N were kept).
    """

    xy: jax.Array
    mag: jax.Array
    truth: jax.Array
    valid: jax.Array
    attitude: jax.Array
    overflow: jax.Array

    @property
    def batch_size(self) -> int:
        return int(self.xy.shape[0])

    @property
    def capacity(self) -> int:
        return int(self.xy.shape[1])

    @property
    def n_stars(self) -> jax.Array:
        """(B,) int32 number of valid detections per scene."""
        return jnp.sum(self.valid, axis=-1, dtype=jnp.int32)

    def __getitem__(self, index) -> Scene:
        """Index or slice the batch axis (``scenes[3]`` keeps a batch axis of 1; an index array
        gathers those scenes, :func:`take_batch_rows`)."""
        return take_batch_rows(self, index)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Identification:
    """What an algorithm says about a batch of scenes (docs/conventions.md §4).

    Attributes:
        ids: (B, N) int32 catalog row given to each detection, −1 = not identified.
        ok: (B,) bool, the algorithm claims success for the scene.
        attitude: (B, 3, 3) float32 estimated ``C`` or ``None`` when the algorithm gives none.
        focal_scale: (B,) float32 focal length fitted while solving / the camera's
            (:mod:`jstarid.camera_fit`), or ``None`` when not fitted.
        distortion_k1: (B,) float32 radial distortion fitted while solving (normalised
            coordinates, OpenCV's ``k1``; 0 where the names could not fit it,
            :func:`jstarid.camera_fit.fit_distorted`), or ``None`` when not fitted.
        false_match: (B,) float32 false-match probability of each claim, the one that decided
            ``ok`` (:func:`jstarid.finishing.confirmed_by_the_frame`; 1 where not claimed), or
            ``None`` where the algorithm gives none (:func:`jstarid.false_match.of_solutions`
            computes it from the names).
    """

    ids: jax.Array
    ok: jax.Array
    attitude: jax.Array | None = None
    focal_scale: jax.Array | None = None
    distortion_k1: jax.Array | None = None
    false_match: jax.Array | None = None

    def __getitem__(self, index) -> Identification:
        """Index or slice the batch axis, as :meth:`Scene.__getitem__`."""
        return take_batch_rows(self, index)

    def with_rows(self, rows, part: Identification) -> Identification:
        """These results with the scenes ``rows`` ((R,) int indices) replaced by ``part``'s (R scenes),
        on the host (an eager scatter compiles a program per row count). A field ``part`` lacks
        (``None``) stays as it is; one these results lack is filled (ids −1, ``ok`` False, NaN,
        false-match probability 1) elsewhere."""
        rows = np.asarray(rows)
        b = np.asarray(self.ok).shape[0]

        def put(old, new, fill, dtype, tail=()):
            if new is None:
                return old
            base = np.full((b, *tail), fill, dtype) if old is None else np.array(old)
            base[rows] = np.asarray(new)
            return jax.device_put(base)

        n = np.asarray(part.ids).shape[1:]
        return Identification(ids=put(self.ids, part.ids, -1, np.int32, n),
                              ok=put(self.ok, part.ok, False, bool),
                              attitude=put(self.attitude, part.attitude, np.nan, np.float32, (3, 3)),
                              focal_scale=put(self.focal_scale, part.focal_scale, np.nan, np.float32),
                              distortion_k1=put(self.distortion_k1, part.distortion_k1, np.nan, np.float32),
                              false_match=put(self.false_match, part.false_match, 1.0, np.float32))

    def failed(self, rows) -> Identification:
        """These results with the scenes ``rows`` (int indices or a (B,) bool mask) failed: ids −1,
        ``ok`` False, NaN attitude and fits, false-match probability 1. On the host, as
        :meth:`with_rows` (an eager scatter compiles a program per row count)."""
        rows = np.asarray(rows)

        def cleared(x, value):
            if x is None:
                return None
            out = np.array(x)  # a copy
            out[rows] = value
            return jax.device_put(out)

        return Identification(ids=cleared(self.ids, -1), ok=cleared(self.ok, False),
                              attitude=cleared(self.attitude, jnp.nan),
                              focal_scale=cleared(self.focal_scale, jnp.nan),
                              distortion_k1=cleared(self.distortion_k1, jnp.nan),
                              false_match=cleared(self.false_match, 1.0))


def undistort_scenes(scenes: Scene, camera) -> Scene:
    """Measured centroids moved to the ideal pinhole frame of ``camera`` (its lens distortion undone,
    :meth:`jstarid.Camera.undistort`); padding stays zero. Returns ``scenes`` itself for an ideal lens.
    """
    if not camera.distortion:
        return scenes
    # host copies first: an eager op on arrays sharded over CPU devices could stall (engine notes)
    xy, valid = np.asarray(scenes.xy), np.asarray(scenes.valid)
    ideal = np.where(valid[..., None], np.asarray(camera.undistort(xy.astype(np.float64))), 0.0)
    return dataclasses.replace(scenes, xy=jnp.asarray(ideal, scenes.xy.dtype))


def brightest(scenes: Scene, k: int) -> Scene:
    """The ``k`` brightest detections of every scene (valid entries come first, brightest first);
    ``overflow`` is set where more were kept. Returns ``scenes`` itself when ``k`` ≥ N."""
    if k >= scenes.capacity:
        return scenes
    rest = np.asarray(scenes.valid)[:, k:].any(axis=1)
    return dataclasses.replace(scenes, xy=scenes.xy[:, :k], mag=scenes.mag[:, :k],
                               truth=scenes.truth[:, :k], valid=scenes.valid[:, :k],
                               overflow=np.asarray(scenes.overflow) | rest)


def pad_with_empty(scenes: Scene, size: int) -> Scene:
    """The batch followed by empty scenes (no valid detection) up to ``size`` scenes.

    Padding for a batch of a fixed (e.g. power-of-two) size: an empty scene fails at once in every
    algorithm, where a copy of a real scene would cost a whole search (a failing one, the dearest).

    Args:
        scenes: (B, N) scenes, B ≤ ``size``.
        size: the padded batch size.

    Returns:
        (size, N) scenes; rows B… have ``valid`` False, zero centroids, ``mag`` +inf, ``truth`` −1,
        NaN attitude and no overflow.
    """
    extra = size - scenes.batch_size
    if extra < 0:
        raise ValueError(f"cannot pad {scenes.batch_size} scenes to {size}")
    if extra == 0:
        return scenes
    n = scenes.capacity
    empty = Scene(xy=np.zeros((extra, n, 2), np.float32), mag=np.full((extra, n), np.inf, np.float32),
                  truth=np.full((extra, n), -1, np.int32), valid=np.zeros((extra, n), bool),
                  attitude=np.full((extra, 3, 3), np.nan, np.float32), overflow=np.zeros(extra, bool))
    # on the host: a device concatenation would compile a program for every batch and pad size
    def padded(a, e):
        a = np.asarray(a)
        return jax.device_put(np.concatenate([a, e.astype(a.dtype)]))  # (take_batch_rows)

    return jax.tree.map(padded, scenes, empty)


def scenes_from_centroids(xy_list: Sequence, mag_list: Sequence | None = None, *,
                          capacity: int = 64, camera=None) -> Scene:
    """Pack user centroids (e.g. from a real image) into a :class:`Scene` batch.

    Args:
        xy_list: B arrays of shape (n_i, 2), centroids (px, column/row, origin at pixel (0,0) centre).
        mag_list: ``None`` or B arrays (n_i,) of magnitudes (or any brightness proxy where smaller is
            brighter). Without magnitudes, the given order is taken as brightest first.
        capacity: static N. Scenes with more than N centroids keep the brightest N and are flagged
            ``overflow``.
        camera: the :class:`~jstarid.Camera` that measured them; its lens distortion, if any, is
            undone (:func:`undistort_scenes`). ``None``: the centroids are taken as pinhole pixels.

    Returns:
        A :class:`Scene` with ``truth = −1`` and a NaN ``attitude`` (unknown).

    Raises:
        ValueError: non-finite centroids or magnitudes, wrong shapes, or a non-positive capacity.
    """
    if not isinstance(capacity, int | np.integer) or capacity < 1:
        raise ValueError(f"capacity must be a positive integer, got {capacity!r}")
    if isinstance(xy_list, np.ndarray | jax.Array) and np.ndim(xy_list) != 3:
        # a bare (n, 2) array would read as n one-star scenes: one scene is [xy]
        raise ValueError(f"xy_list must be a list of (n, 2) arrays (one per scene) or a (B, n, 2) "
                         f"array, got an array of shape {np.shape(xy_list)}; for one scene pass [xy]")
    if mag_list is not None and len(mag_list) != len(xy_list):
        raise ValueError(f"got {len(xy_list)} centroid arrays but {len(mag_list)} magnitude arrays")
    b = len(xy_list)
    xy_out = np.zeros((b, capacity, 2), np.float32)
    mag_out = np.full((b, capacity), np.inf, np.float32)
    valid = np.zeros((b, capacity), bool)
    overflow = np.zeros(b, bool)
    for i, xy in enumerate(xy_list):
        xy = np.asarray(xy, dtype=np.float64)
        if xy.size == 0:
            xy = np.zeros((0, 2))
        if xy.ndim != 2 or xy.shape[1] != 2:
            # (2, n) or (n, 3) x, y, flux arrays are refused rather than reshaped into wrong points
            raise ValueError(f"scene {i}: centroids must be an (n, 2) array of x, y (px), got shape "
                             f"{xy.shape}")
        if not np.all(np.isfinite(xy)):
            raise ValueError(f"scene {i}: centroids contain NaN or inf")
        if mag_list is None or mag_list[i] is None:
            mag = np.arange(len(xy), dtype=np.float64)  # given order = brightness order
        else:
            mag = np.asarray(mag_list[i], dtype=np.float64).reshape(-1)
            if mag.shape[0] != xy.shape[0]:
                raise ValueError(f"scene {i}: {xy.shape[0]} centroids but {mag.shape[0]} magnitudes")
            if not np.all(np.isfinite(mag)):
                raise ValueError(f"scene {i}: magnitudes contain NaN or inf")
        order = np.argsort(mag, kind="stable")[:capacity]
        n = len(order)
        overflow[i] = len(xy) > capacity
        xy_out[i, :n] = xy[order]
        mag_out[i, :n] = mag[order]
        valid[i, :n] = True
    scenes = Scene(
        xy=jnp.asarray(xy_out), mag=jnp.asarray(mag_out),
        truth=jnp.full((b, capacity), -1, jnp.int32), valid=jnp.asarray(valid),
        attitude=jnp.full((b, 3, 3), jnp.nan, jnp.float32), overflow=jnp.asarray(overflow),
    )
    return scenes if camera is None else undistort_scenes(scenes, camera)
