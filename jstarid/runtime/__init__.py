"""The batching runtime shared by the simulator and every algorithm.

- :mod:`.devices`: split a batch over a 1-D device mesh (``map_batch``: pad to a multiple of the
  device count, ``shard_map``, unpad) and expose CPU cores as devices (``use_cpu_cores``);
- :mod:`.batching`: run a kernel over a batch in calls of a few static sizes (``chunk_calls``,
  ``run_calls``), retry flagged rows with a larger buffer (``grow_until``), and inside one compiled
  call run rows of different sizes in chunks of the narrowest width that holds them
  (``map_by_width``);
- :mod:`.padding`: the padding rules (``pad_rows``, ``next_power_of_two``, ``padded_indices``,
  ``call_size``);
- :mod:`.pairs`: one kernel over many (scene, candidate) pairs, grouped by static size, cut to a
  memory budget and split over the devices (``run_pairs``), padding pairs skipped inside a call
  (``skip_padding``);
- :mod:`.cache`: device copies and derived tables of long-lived objects (``DeviceCache``);
- :mod:`.memory_maps`: drop JAX's compiled caches before a process reaches Linux's limit on memory
  mappings (``relieve``);
- :mod:`.staging_memory`: drop what JAX keeps of staging programs already compiled, and trim the
  heap (``release_staging``);
- :mod:`.static`: the static config a kernel compiles with (``static_config``);
- :mod:`.compilations`: count the programs XLA compiles inside a block (``CountCompilations``);
- :mod:`.program_store`: keep compiled programs on disk so that a later process loads them without
  tracing, lowering or compiling (``stored_jit``; on in the CLI and scripts).
"""

from jstarid.runtime import program_store
from jstarid.runtime.batching import Call, chunk_calls, grow_until, map_by_width, run_calls, take_rows
from jstarid.runtime.cache import DeviceCache, device_cache, on_every_device
from jstarid.runtime.compilations import CountCompilations
from jstarid.runtime.devices import batch_mesh, map_batch, replicate, shard_batch, use_cpu_cores
from jstarid.runtime.memory_maps import relieve
from jstarid.runtime.padding import (
    call_padded,
    call_size,
    call_width,
    coarse_size,
    columns_in_use,
    next_power_of_two,
    pad_rows,
    padded_indices,
)
from jstarid.runtime.pairs import run_pairs, skip_padding
from jstarid.runtime.staging_memory import release_staging
from jstarid.runtime.static import static_config

__all__ = ["batch_mesh", "Call", "call_padded", "call_size", "call_width", "chunk_calls", "coarse_size",
           "columns_in_use", "CountCompilations", "device_cache", "DeviceCache", "grow_until", "map_batch",
           "map_by_width", "next_power_of_two", "on_every_device", "pad_rows", "padded_indices",
           "program_store", "release_staging", "relieve", "replicate", "run_calls", "run_pairs",
           "shard_batch", "skip_padding", "static_config", "take_rows", "use_cpu_cores"]
