"""Runs inside cedar-solve's own environment (numpy < 2, no jstarid): build or load the database,
solve every scene of an exported ``.npz``, write the matches as JSON. Called by
:mod:`jstarid.peers.cedar` as ``python cedar_worker.py JOB.json``."""

import json
import sys
import time

import numpy as np
from tetra3 import Tetra3


def main(job_path):
    job = json.loads(open(job_path).read())
    t3 = Tetra3(load_database=None)
    try:
        t3.load_database(job["database"])
    except Exception:  # noqa: BLE001 (any failure to load means: build it)
        t0 = time.perf_counter()
        t3.generate_database(max_fov=job["fov_deg"], star_catalog=job["catalog"], save_as=job["database"],
                             star_max_magnitude=job["mag_limit"], epoch_proper_motion=None)
        print(f"cedar database built in {time.perf_counter() - t0:.0f} s", flush=True)
        t3.load_database(job["database"])  # cedar 0.5.1 sets its pattern count only when loading
    if not job.get("scenes"):
        return
    data = np.load(job["scenes"])
    centroids, counts = data["centroids"], data["counts"]
    out = {}
    for err in job["max_errors"]:
        matched, ids, seconds, solved = [], [], [], []
        for s in range(len(counts)):
            t0 = time.perf_counter()
            r = t3.solve_from_centroids(centroids[s, : counts[s]], (job["height"], job["width"]),
                                        fov_estimate=job["fov_deg"], return_matches=True, match_max_error=err,
                                        solve_timeout=job["timeout_ms"])
            seconds.append(time.perf_counter() - t0)
            ok = r.get("RA") is not None
            solved.append(ok)
            matched.append(np.asarray(r["matched_centroids"], float).reshape(-1, 2).tolist() if ok else [])
            ids.append(np.asarray(r["matched_catID"], np.int64).reshape(-1).tolist() if ok else [])
        out[str(err)] = {"matched": matched, "ids": ids, "seconds": seconds, "solved": solved}
    with open(job["result"], "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main(sys.argv[1])
