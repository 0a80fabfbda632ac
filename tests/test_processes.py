"""Scale-out (:mod:`jstarid.engine.processes`): two JAX processes give the one-process table bit for
bit, and so do one device and several (the batch sharded over a process's devices). MLV runs
without its focal-length extensions: they add compilations to every process, not paths to compare."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import SUITE_XLA_FLAGS

import jstarid as js
from jstarid import cli
from jstarid.engine import processes

SWEEP = ["sweep", "--algorithms", "oracle,mlv", "--camera", "mlv2021", "--mag-limit", "5.5",
         "--set", "mlv.n_boresights=20000", "mlv.batch_chunk=100",
         "mlv.finishing.focal_search=[]", "mlv.finishing.fit_focal=false",
         "--levels", "0,2.5", "--fixed", "magnitude_sigma=0.3", "--scenes", "9",
         "--chunk-size", "4", "--quiet"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _launch(out, n_processes: int, devices: int, deadline_s: float = 300.0) -> None:
    """Run ``jstarid sweep`` as ``n_processes`` local processes of ``devices`` CPU devices each."""
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices} {SUITE_XLA_FLAGS}"}
    port = _free_port()
    extra = (lambda i: ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n_processes),
                        "--process-id", str(i)]) if n_processes > 1 else (lambda i: [])
    logs = [open(out.parent / f"{out.name}-{i}.log", "w+") for i in range(n_processes)]  # noqa: SIM115
    procs = [subprocess.Popen([sys.executable, "-m", "jstarid.cli", *SWEEP, "--out", str(out), *extra(i)],
                              env=env, stdout=logs[i], stderr=subprocess.STDOUT)
             for i in range(n_processes)]
    end = time.monotonic() + deadline_s
    try:  # a failed process can leave its peer waiting forever: stop everyone at the first failure
        while any(p.poll() is None for p in procs) and not any(p.poll() for p in procs):
            if time.monotonic() > end:
                break
            time.sleep(0.1)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
    text = []
    for log in logs:
        log.seek(0)
        text.append(log.read())
        log.close()
    assert all(p.returncode == 0 for p in procs), "\n".join(text)


def test_share_splits_rows_contiguously():
    blocks = [processes.share(10, i, 3) for i in range(3)]
    assert [(b.start, b.stop) for b in blocks] == [(0, 3), (3, 7), (7, 10)]
    assert processes.share(10) == slice(0, 10)  # one process: everything


@pytest.mark.slow
def test_two_processes_and_one_device_equal_this_process(tmp_path):
    here, one, two = tmp_path / "here", tmp_path / "one", tmp_path / "two"
    assert cli.main([*SWEEP, "--out", str(here)]) == 0  # this process: 4 devices
    _launch(one, 1, 1)
    _launch(two, 2, 2)
    base = js.load_sweep(here)
    for other, n in ((js.load_sweep(one), 1), (js.load_sweep(two), 2)):
        assert other.processes == n
        assert other.equal_outcomes(base)
        for a, b in zip(other.rows(), base.rows(), strict=True):
            timing = ("seconds", "scenes_per_second", "compile_seconds", "scenes_per_second_without_compile",
                      "peak_rss_mb")
            assert {k: v for k, v in a.items() if k not in timing} == \
                   {k: v for k, v in b.items() if k not in timing}
    assert base.rows()[2]["label"] == "mlv" and np.all(base.scenes["outcome"][:, 0] == 0)


def test_partial_distributed_arguments_are_an_error(capsys):
    assert cli.main([*SWEEP, "--coordinator", "127.0.0.1:1"]) == 2
    assert "together" in capsys.readouterr().err


@pytest.mark.parametrize("count", [1, 3])
def test_gather_in_one_process_returns_its_arrays(count):
    arrays = {"a": np.arange(count)}
    assert np.array_equal(processes.gather(arrays, count)["a"], np.arange(count))
