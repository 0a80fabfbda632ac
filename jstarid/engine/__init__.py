"""The sweep engine: every algorithm on identical scenes, one or two noise axes, parameter grids.

- :mod:`.levels`: noise axes → levels → one (L · n,) :class:`~jstarid.NoiseConfig` batch;
- :mod:`.entries`: what runs (:class:`Entry`: algorithm, config, label) and parameter grids
  (:func:`grid`);
- :mod:`.run`: :func:`sweep` = :func:`simulate_levels` (every level in one simulate call) +
  :func:`compare` (every entry on given scenes, in memory-bounded chunks);
- :mod:`.result`: :class:`SweepResult`, the tidy table with Wilson intervals, save and :func:`load`;
- :mod:`.pixels`: sweeps from rendered frames (render → extract → label), sensor axes;
- :mod:`.processes`: a process's share of the scenes and the gather, under ``jax.distributed``.

Usage::

    import jstarid as js

    result = js.sweep("sgm,mlv,rpnet", "sgm2022", axes={"position_sigma_px": [0, 1, 2, 3]},
                      scenes=200, seed=0)
    print(result.table())
    result.save("results/my_sweep")                      # table.md, rates.png, results.json, …
    same = js.load_sweep("results/my_sweep")
    grid = js.sweep([js.grid("mlv", th1=[0, 1, 2], eps_deg=[0.1, 0.2])], "mlv2021",
                    axes={"position_sigma_px": [1.0, 2.5]})
"""

from jstarid.engine import pixels
from jstarid.engine.entries import Entry, check_camera, default_config, entries, grid
from jstarid.engine.levels import AXES, axis_field, level_grid, level_noise
from jstarid.engine.processes import initialize
from jstarid.engine.result import SweepResult, load
from jstarid.engine.run import BORESIGHTS, Levels, compare, plan, simulate_levels, sweep

__all__ = ["AXES", "BORESIGHTS", "Entry", "Levels", "SweepResult", "axis_field", "check_camera", "compare",
           "default_config", "entries", "grid", "initialize", "level_grid", "level_noise", "load",
           "pixels", "plan", "simulate_levels", "sweep"]
