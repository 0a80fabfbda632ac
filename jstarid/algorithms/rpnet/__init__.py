"""RpNet: representation-learning star identification (Xu, Jiang, Liu, IEEE Access 7, 2019).

Modules (one concept each): :mod:`.config` (parameters, Table 3 presets, :class:`Tuning`),
:mod:`.guide_catalog` (guide reference stars, §II-A), :mod:`.pattern` (initial input, eq. 3),
:mod:`.model` (generator, decoder, classifier; eqs. 4–6), :mod:`.data` (training batches on the
fly, §II-C), :mod:`.train` (two-stage training, checkpoints), :mod:`.grid` (G models trained side
by side in one vmapped step: seeds × learning rates), :mod:`.database` (cached guide catalog +
networks) and :mod:`.identify` (weight search, eqs. 7–11, and naming of the other stars).

Usage::

    rpnet = js.algorithms.get("rpnet")
    cat = rpnet.load_guide_catalog()                # V ≤ 6.0, close pairs (0.1°) reduced to one
    cam = js.camera_preset("rpnet2019")
    cfg = rpnet.Config.quick()                      # Config(): Table 3 training (hours on a CPU)
    db = rpnet.build_database(cat, cam, cfg)        # trains once, then loads the cached checkpoint
    result = rpnet.identify(db, scenes)             # Config.paper(): without our extensions
"""

from jstarid.algorithms.rpnet.config import Config, Training, Tuning
from jstarid.algorithms.rpnet.database import (
    PRESETS,
    Database,
    build_database,
    database_from_variables,
    first_use,
    load_database,
)
from jstarid.algorithms.rpnet.grid import GridResult, grid_members, member_variables, train_grid
from jstarid.algorithms.rpnet.guide_catalog import guide_rows, load_guide_catalog
from jstarid.algorithms.rpnet.identify import Diagnostics, identify

__all__ = ["PRESETS", "Config", "Database", "Diagnostics", "GridResult", "Training", "Tuning",
           "build_database", "database_from_variables", "first_use", "grid_members", "guide_rows", "identify",
           "load_database", "load_guide_catalog", "member_variables", "train_grid"]
