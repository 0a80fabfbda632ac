"""Simulated scenes of catalog stars with their Hipparcos numbers: the labelled frames the tests of
centroid files, ``identify``, ``score`` and ``js.solve`` write and read back."""

import jax
import numpy as np

import jstarid as js


def catalog_star_scenes(seed: int, n_scenes: int, *, camera_limit: float = 5.5,
                        position_sigma_px: float = 0.3, capacity: int = 64):
    """``n_scenes`` mlv2021 scenes (stars to V ``camera_limit``, no false stars) as a list of
    ``(xy (n, 2) px, mag (n,), hip (n,))``, brightest first."""
    cat = js.load_catalog(camera_limit)
    cam = js.camera_preset("mlv2021", mag_limit=camera_limit)
    scenes = js.simulate(jax.random.key(seed), cat, cam, js.NoiseConfig(position_sigma_px=position_sigma_px),
                         batch_size=n_scenes, capacity=capacity)
    out = []
    for i in range(n_scenes):
        keep = np.asarray(scenes.valid[i]) & (np.asarray(scenes.truth[i]) >= 0)
        out.append((np.asarray(scenes.xy[i])[keep], np.asarray(scenes.mag[i])[keep],
                    cat.hip[np.asarray(scenes.truth[i])[keep]]))
    return out
