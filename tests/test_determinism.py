"""Determinism: the same input and options give a bit-identical output mesh.

Within one process and across processes (different Python hash seeds), with every
operation, regions and sliding boundaries; saved files are byte-identical too.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh

import jtet


def _digest(mesh: jtet.TetMesh) -> str:
    h = hashlib.sha256()
    for a in (mesh.points, mesh.tets, mesh.region, mesh.protected_faces, mesh.protected_edges):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


CASES = {
    "random": (lambda: delaunay_mesh(120, seed=8, surface_points=30), {}),
    "regions-slide": (
        lambda: grid_mesh(4, perturb=0.6, seed=2, two_regions=True),
        {"boundary": "slide", "quality": "radius_ratio"},
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_same_output_twice_in_one_process(case):
    make, kw = CASES[case]
    a = jtet.improve(make(), max_passes=3, **kw)
    b = jtet.improve(make(), max_passes=3, **kw)
    assert _digest(a.mesh) == _digest(b.mesh)
    assert [h["successes"] for h in a.history] == [h["successes"] for h in b.history]


_CHILD = """
import sys
sys.path.insert(0, "tests")
import test_determinism as t
make, kw = t.CASES[sys.argv[1]]
print(t._digest(t.jtet.improve(make(), max_passes=3, **kw).mesh))
"""


def test_same_output_in_separate_processes():
    case = "regions-slide"
    make, kw = CASES[case]
    here = _digest(jtet.improve(make(), max_passes=3, **kw).mesh)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    digests = []
    for hash_seed in ("1", "2"):
        env = dict(os.environ, PYTHONHASHSEED=hash_seed)
        out = subprocess.run(
            [sys.executable, "-c", _CHILD, case],
            cwd=root,
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        digests.append(out.stdout.strip().splitlines()[-1])
    assert digests == [here, here]


def test_saved_files_are_identical(tmp_path):
    mesh = delaunay_mesh(80, seed=9)
    r1 = jtet.improve(mesh, max_passes=2)
    r2 = jtet.improve(mesh, max_passes=2)
    jtet.save(r1.mesh, tmp_path / "a.vtu")
    jtet.save(r2.mesh, tmp_path / "b.vtu")
    assert (tmp_path / "a.vtu").read_bytes() == (tmp_path / "b.vtu").read_bytes()


def test_worker_threads_do_not_change_the_output(monkeypatch):
    # independent kernel calls run on _config.WORKERS threads (Klincsek chunk groups,
    # tree chunks, one smoothing colour's batches); 1 and 2 workers must agree bit for bit
    from jtet import _config

    mesh = jtet.demo_mesh()
    parallel_calls = []
    serial_map = _config.parallel_map

    def counting_map(fn, items):
        parallel_calls.append(len(items))
        return serial_map(fn, items)

    monkeypatch.setattr(_config, "parallel_map", counting_map)
    digests = []
    for workers in (1, 2):
        monkeypatch.setattr(_config, "WORKERS", workers)
        digests.append(_digest(jtet.improve(mesh, max_passes=2).mesh))
    assert max(parallel_calls) >= 2  # some calls really had several items to spread
    assert digests[0] == digests[1]
