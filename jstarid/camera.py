"""Pinhole camera model (with optional lens distortion) and the camera presets of docs/conventions.md §6.

Frames (docs/conventions.md §1): camera +z along the boresight, +x along increasing pixel column, +y
along increasing row. Pixels ``(x, y) = (column, row)``, origin at the centre of pixel (0, 0): the
image spans ``0 ≤ x ≤ W−1``, ``0 ≤ y ≤ H−1``; the default principal point is ``((W−1)/2, (H−1)/2)``.
A :class:`Camera` is frozen and hashable (a static jit argument); ``project`` / ``unproject`` are pure
``jnp`` functions.

Lens distortion (OpenCV's Brown–Conrady coefficients ``k1, k2, p1, p2, k3``) lives only at the edge:
scenes, the simulator and every algorithm work in the ideal pinhole frame, and measured centroids
are moved there once, when they become scenes (:meth:`Camera.undistort`, called by
:func:`jstarid.scenes_from_centroids` and :func:`jstarid.extract_centroids` given the camera).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp

__all__ = ["Camera", "camera_preset", "preset_names", "tolerance_scales"]

#: Fixed-point steps of :meth:`Camera.undistort` (OpenCV's undistortPoints uses 5 by default; each
#: step shrinks the error by about 2 |k1| r² — 0.025 at the corner of a 20° field with k1 = 0.2 —
#: so 10 steps leave far less than 1e-9 px).
UNDISTORT_STEPS = 10
_DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")


@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera, optionally with lens distortion (module docstring).

    Attributes:
        width: image width W (px, columns).
        height: image height H (px, rows).
        f_px: focal length in pixels (focal length / pixel size).
        cx: principal point column (px); ``None`` → ``(W−1)/2``.
        cy: principal point row (px); ``None`` → ``(H−1)/2``.
        mag_limit: detection limit (V mag): stars whose observed magnitude is brighter than or equal to
            this are detected by the simulator.
        name: a label (the preset name, or ``"custom"``).
        distortion: OpenCV's distortion coefficients ``(k1, k2, p1, p2, k3)`` in its order, any
            leading part of them (``(k1,)``, ``(k1, k2)``, …); ``()`` for an ideal lens. On the
            normalised coordinates ``u = (x − cx) / f_px``, ``v = (y − cy) / f_px``, ``r² = u² + v²``,
            the lens moves ``u`` to ``u (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 u v + p2 (r² + 2u²)`` and ``v``
            likewise (``p1`` and ``p2`` swapped).
    """

    width: int
    height: int
    f_px: float
    cx: float | None = None
    cy: float | None = None
    mag_limit: float = 6.0
    name: str = "custom"
    distortion: tuple[float, ...] = ()

    def __post_init__(self):
        if int(self.width) < 2 or int(self.height) < 2:
            raise ValueError(f"camera size must be at least 2x2 px, got {self.width}x{self.height}")
        if not (math.isfinite(self.f_px) and self.f_px > 0):
            raise ValueError(f"f_px must be a positive finite number, got {self.f_px}")
        if not math.isfinite(self.mag_limit):
            raise ValueError(f"mag_limit must be finite, got {self.mag_limit}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "f_px", float(self.f_px))
        object.__setattr__(self, "mag_limit", float(self.mag_limit))
        cx = (self.width - 1) / 2.0 if self.cx is None else float(self.cx)
        cy = (self.height - 1) / 2.0 if self.cy is None else float(self.cy)
        object.__setattr__(self, "cx", cx)
        object.__setattr__(self, "cy", cy)
        coefficients = tuple(float(c) for c in self.distortion)
        if len(coefficients) > len(_DISTORTION_NAMES) or not all(map(math.isfinite, coefficients)):
            raise ValueError("distortion must be at most 5 finite coefficients (k1, k2, p1, p2, k3), "
                             f"got {self.distortion!r}")
        while coefficients and coefficients[-1] == 0.0:  # (k1, 0) and (k1,) are the same lens
            coefficients = coefficients[:-1]
        object.__setattr__(self, "distortion", coefficients)

    @classmethod
    def from_optics(cls, width, height, focal_length_mm, pixel_size_mm, **kwargs) -> Camera:
        """A camera from focal length and pixel pitch (both mm)."""
        return cls(width, height, focal_length_mm / pixel_size_mm, **kwargs)

    @classmethod
    def from_fov(cls, width, height, fov_x_deg, **kwargs) -> Camera:
        """A camera whose horizontal field of view (edge to edge of the W-px side) is ``fov_x_deg``."""
        return cls(width, height, (width / 2.0) / math.tan(math.radians(fov_x_deg) / 2.0), **kwargs)

    # ------------------------------------------------------------------ geometry
    @property
    def pixel_scale_arcsec(self) -> float:
        """Angle (arcsec) one pixel spans at the principal point."""
        return math.degrees(1.0 / self.f_px) * 3600.0

    def database_fields(self) -> dict:
        """Every field but the lens distortion: what a database or a trained network depends on
        (distortion is undone before any algorithm sees a centroid), their cache keys as before
        cameras had it."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "distortion"}

    def pinhole(self) -> Camera:
        """This camera with an ideal lens (the frame scenes and algorithms work in)."""
        return dataclasses.replace(self, distortion=()) if self.distortion else self

    def pinhole_numbers(self) -> jnp.ndarray:
        """(5,) float32 ``(width, height, f_px, cx, cy)`` (px): the pinhole model as an array, which a
        kernel takes as a traced argument (:meth:`traced`) so that one compiled program serves every
        camera of the same shapes. The lens distortion is not part of it."""
        return jnp.asarray([self.width, self.height, self.f_px, self.cx, self.cy], jnp.float32)

    @classmethod
    def traced(cls, numbers) -> Camera:
        """The pinhole camera of :meth:`pinhole_numbers` inside a traced function.

        Its fields are traced scalars, so its array methods (:meth:`project`, :meth:`unproject`,
        :meth:`contains`) work, while what needs Python numbers does not (the float-valued
        properties, validation, hashing). An ideal lens.

        Args:
            numbers: (5,) float32 ``(width, height, f_px, cx, cy)``.
        """
        camera = object.__new__(cls)
        fields = ("width", "height", "f_px", "cx", "cy")
        values = {name: numbers[i] for i, name in enumerate(fields)}
        for name, value in {**values, "mag_limit": math.nan, "name": "traced", "distortion": ()}.items():
            object.__setattr__(camera, name, value)
        return camera

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view (deg), edge to edge."""
        return math.degrees(2.0 * math.atan((self.width / 2.0) / self.f_px))

    @property
    def fov_y_deg(self) -> float:
        """Vertical field of view (deg), edge to edge."""
        return math.degrees(2.0 * math.atan((self.height / 2.0) / self.f_px))

    @property
    def fov_diagonal_deg(self) -> float:
        """Diagonal field of view (deg), corner to corner."""
        return math.degrees(2.0 * math.atan(math.hypot(self.width, self.height) / 2.0 / self.f_px))

    @property
    def inscribed_half_field_deg(self) -> float:
        """Radius (deg) of the largest circle about the principal point inside the frame: the
        principal point to the nearest edge (a pattern or neighbor circle of this radius about a
        central star is never cut by the frame)."""
        edge = min(self.cx, self.cy, self.width - 1 - self.cx, self.height - 1 - self.cy)
        return math.degrees(math.atan(edge / self.f_px))

    @property
    def half_diagonal_rad(self) -> float:
        """Largest angle (rad) between the boresight and any pixel of the frame (to the pixel-grid corner
        farthest from the principal point); bounds the catalog stars that may fall in the frame.
        """
        dx = max(self.cx, self.width - 1 - self.cx)
        dy = max(self.cy, self.height - 1 - self.cy)
        return math.atan(math.hypot(dx, dy) / self.f_px)

    def project(self, v_cam):
        """Project camera-frame vectors to pixels (docs/conventions.md §1 pinhole model).

        Args:
            v_cam: (..., 3) vectors in the camera frame (need not be unit length).

        Returns:
            ``(xy, in_field)``: (..., 2) float pixel coordinates and (...,) bool, True when ``v_z > 0``
            and the point lies inside ``[0, W−1] × [0, H−1]``. For ``v_z ≤ 0`` the pixel values are
            finite but meaningless (a safe divisor is used so gradients and jit stay NaN-free).
        """
        v_cam = jnp.asarray(v_cam)
        x, y, in_field = self.project_components(v_cam[..., 0], v_cam[..., 1], v_cam[..., 2])
        return jnp.stack([x, y], axis=-1), in_field

    def project_components(self, vx, vy, vz):
        """:meth:`project` on separate x, y, z component arrays → ``(x, y, in_field)`` (structure of arrays:
        XLA fuses rotation and projection into one elementwise loop, the simulator's hot path).
        """
        front = vz > 0
        safe_vz = jnp.where(front, vz, 1.0)  # double-where: no inf/NaN behind the camera
        x = self.cx + self.f_px * vx / safe_vz
        y = self.cy + self.f_px * vy / safe_vz
        inside = (x >= 0) & (x <= self.width - 1) & (y >= 0) & (y <= self.height - 1)
        return x, y, front & inside

    def contains(self, xy, inset_px=0.0):
        """(...,) bool: pixel coordinates ``xy`` (..., 2) inside the frame shrunk by ``inset_px`` on every
        side (e.g. a match tolerance: a star predicted just inside the edge is not expected).
        """
        xy = jnp.asarray(xy)
        x, y = xy[..., 0], xy[..., 1]
        return ((x >= inset_px) & (x <= self.width - 1 - inset_px)
                & (y >= inset_px) & (y <= self.height - 1 - inset_px))

    def unproject(self, xy):
        """Pixels (..., 2) → unit vectors (..., 3) in the camera frame (inverse of :meth:`project`)."""
        xy = jnp.asarray(xy)
        u = (xy[..., 0] - self.cx) / self.f_px
        v = (xy[..., 1] - self.cy) / self.f_px
        ray = jnp.stack([u, v, jnp.ones_like(u)], axis=-1)
        return ray / jnp.linalg.norm(ray, axis=-1, keepdims=True)

    # ------------------------------------------------------------------ distortion
    def _coefficients(self):
        return dict(zip(_DISTORTION_NAMES, self.distortion + (0.0,) * 5, strict=False))

    def _lens_shift(self, u, v):
        """The distorted normalised coordinates of ideal ones (class docstring)."""
        c = self._coefficients()
        r2 = u * u + v * v
        radial = 1.0 + r2 * (c["k1"] + r2 * (c["k2"] + r2 * c["k3"]))
        du = 2.0 * c["p1"] * u * v + c["p2"] * (r2 + 2.0 * u * u)
        dv = c["p1"] * (r2 + 2.0 * v * v) + 2.0 * c["p2"] * u * v
        return u * radial + du, v * radial + dv, radial, du, dv

    def distort(self, xy):
        """Ideal pinhole pixels (..., 2) → where this lens puts them (..., 2); identity for ``()``."""
        xy = jnp.asarray(xy)
        if not self.distortion:
            return xy
        u, v = (xy[..., 0] - self.cx) / self.f_px, (xy[..., 1] - self.cy) / self.f_px
        ud, vd, *_ = self._lens_shift(u, v)
        return jnp.stack([self.cx + self.f_px * ud, self.cy + self.f_px * vd], axis=-1)

    def undistort(self, xy):
        """Measured pixels (..., 2) → ideal pinhole pixels (..., 2), the inverse of :meth:`distort`.

        :data:`UNDISTORT_STEPS` fixed-point steps ``u ← (u_d − tangential(u)) / radial(u)`` from
        ``u = u_d`` (the iteration of OpenCV's ``undistortPoints``); identity for ``()``.
        """
        xy = jnp.asarray(xy)
        if not self.distortion:
            return xy
        ud, vd = (xy[..., 0] - self.cx) / self.f_px, (xy[..., 1] - self.cy) / self.f_px
        u, v = ud, vd
        for _ in range(UNDISTORT_STEPS):
            _, _, radial, du, dv = self._lens_shift(u, v)
            u, v = (ud - du) / radial, (vd - dv) / radial
        return jnp.stack([self.cx + self.f_px * u, self.cy + self.f_px * v], axis=-1)


def _tetra3_test() -> Camera:
    # FLIR BFS-U3-31S4M-C binned 2x2 (6.9 µm) behind a 35 mm lens: nominally f = 5072 px, but the
    # cedar-solve reference fits give a horizontal FOV of 11.424° on all four images
    # (shared/data/real/reference.json); we keep the fitted value since it is what the images show.
    return Camera.from_fov(1024, 768, 11.4243, mag_limit=7.0, name="tetra3_test")


_PRESETS = {
    # You et al. 2022 (SGM), §Simulation setting: 1024², 20°×20° FOV, V ≤ 6.0.
    "sgm2022": lambda: Camera(1024, 1024, 512.0 / math.tan(math.radians(10.0)), mag_limit=6.0,
                              name="sgm2022"),
    # Sensors 2021 multilayer voting (MLV), §3: 1024², 25°×25° FOV, V ≤ 5.5 (simulation catalog to 6.5).
    "mlv2021": lambda: Camera(1024, 1024, 512.0 / math.tan(math.radians(12.5)), mag_limit=5.5,
                              name="mlv2021"),
    # Xu et al. 2019 (RpNet), Table 4: f = 49.277 mm, 0.012 mm pixels. The paper's "20°×20°" is in fact the
    # diagonal FOV of these optics (≈14.2° per side); we keep the optics (conventions §6 note).
    "rpnet2019": lambda: Camera.from_optics(1024, 1024, 49.277, 0.012, mag_limit=6.0,
                                            name="rpnet2019"),
    # Xu et al. 2019 (RpNet), Table 7 (ZY-3 star tracker): f = 43.258 mm, 0.015 mm pixels,
    # off-centre principal point.
    "zy3": lambda: Camera.from_optics(1024, 1024, 43.258, 0.015, cx=515.247, cy=513.320,
                                      mag_limit=6.0, name="zy3"),
    "tetra3_test": _tetra3_test,
    # A simulated twin of a narrow, deep star tracker (issue: any camera): 1392×1040 px at 15.8″/px,
    # a 6.1° × 4.6° field, 40–130 detections per frame down to V ≈ 10. Its noise (0.8 px, ≤ 2 false
    # stars) is jstarid.papers.narrow_field.NOISE.
    "narrow_twin": lambda: Camera.from_fov(1392, 1040, 6.1, mag_limit=10.0, name="narrow_twin"),
}


def preset_names() -> tuple[str, ...]:
    """Names accepted by :func:`camera_preset`."""
    return tuple(_PRESETS)


def camera_preset(name: str, **overrides) -> Camera:
    """A camera preset of conventions §6 (``sgm2022``, ``mlv2021``, ``rpnet2019``, ``zy3``, ``tetra3_test``).

    Args:
        name: preset name.
        **overrides: fields to replace (e.g. ``mag_limit=6.5``).

    Raises:
        ValueError: unknown preset name.
    """
    if name not in _PRESETS:
        raise ValueError(f"unknown camera preset {name!r}; choose one of {', '.join(_PRESETS)}")
    cam = _PRESETS[name]()
    return dataclasses.replace(cam, **overrides) if overrides else cam


#: The papers' own cameras: the range of pixel scales and fields their tolerances were chosen for.
PAPER_CAMERAS = ("sgm2022", "mlv2021", "rpnet2019", "zy3")


def _clip_ratio(value: float, low: float, high: float) -> float:
    """1 inside ``[low, high]``, else ``value / low`` below it or ``value / high`` above it."""
    return value / low if value < low else value / high if value > high else 1.0


#: Share of the inscribed half field a circle about a central star takes when the published radius
#: does not fit (room for the star's offset from the centre and the focal-length search's ±2 %).
CIRCLE_FILL = 0.9


def radius_that_fits(camera: Camera, radius_deg: float) -> float:
    """``radius_deg`` where it fits ``camera``'s inscribed half field, else :data:`CIRCLE_FILL` × that
    half field rounded down to 0.1° (deg): SGM's neighbor circle, RpNet's pattern radius. A circle
    the frame cuts gives patterns no catalog star's pattern matches (``tetra3_test``: 6° → 3.8°).
    """
    half = camera.inscribed_half_field_deg
    if radius_deg <= half:
        return float(radius_deg)
    return max(math.floor(CIRCLE_FILL * half * 10) / 10, 0.1)


def tolerance_scales(camera: Camera) -> tuple[float, float]:
    """How much a tolerance chosen on the papers' cameras must shrink or grow on ``camera``.

    Returns:
        ``(pixel, field)``: the camera's pixel scale (arcsec) and diagonal field (deg), each as a
        ratio to the nearest end of the papers' range (:data:`PAPER_CAMERAS`: 50–89″/px, 20–35°),
        and 1 inside it, so a paper's values stay as published on every paper's camera. A tolerance
        that is a centroid error in angle scales by ``pixel``; one that grows with the stars'
        separations too (a triangle's v1) by ``pixel × field``.
    """
    papers = [camera_preset(name) for name in PAPER_CAMERAS]
    pixels = [c.pixel_scale_arcsec for c in papers]
    fields = [c.fov_diagonal_deg for c in papers]
    return (_clip_ratio(camera.pixel_scale_arcsec, min(pixels), max(pixels)),
            _clip_ratio(camera.fov_diagonal_deg, min(fields), max(fields)))
