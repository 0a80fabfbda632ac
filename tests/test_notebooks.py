"""The notebooks run top to bottom (their code cells executed as one script, plots off-screen), at
the small size they choose under ``JSTARID_NOTEBOOK_SMALL=1``, and are stored without outputs."""

import json
from pathlib import Path

import matplotlib
import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
# The quickstart runs by default; the others (≈ 15–25 s each on 2 cores, mostly compilation of
# kernels other tests cover) with the slow tests.
DEFAULT_NOTEBOOKS = ("quickstart.ipynb",)


@pytest.mark.parametrize("path", [p if p.name in DEFAULT_NOTEBOOKS
                                  else pytest.param(p, marks=pytest.mark.slow) for p in NOTEBOOKS],
                         ids=lambda p: p.name)
def test_notebook_runs(path, monkeypatch):
    matplotlib.use("Agg")
    monkeypatch.chdir(path.parents[1])
    monkeypatch.setenv("JSTARID_NOTEBOOK_SMALL", "1")
    nb = json.loads(path.read_text())
    code = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    exec(compile(code, str(path), "exec"), {"__name__": "__notebook__"})


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_outputs_are_stripped(path):
    for cell in json.loads(path.read_text())["cells"]:
        if cell["cell_type"] == "code":
            assert cell["outputs"] == [] and cell["execution_count"] is None, path.name
