"""Write the Exodus II test fixtures with writers other than jtet's (tests/test_exodus.py).

Runs in a Python that has netCDF4 and meshio (never jtet dependencies), e.g. a venv of
its own: ``python -m venv /tmp/nc && /tmp/nc/bin/pip install netCDF4 meshio scipy``, then

    /tmp/nc/bin/python experiments/exodus_fixtures.py tests/data

- ``exodus_meshio.exo``: meshio 5.3's Exodus writer (netCDF-4, that is HDF5 inside; the
  old ``coord`` variable; element types "TETRA" without a node count) of a Delaunay mesh
  of 40 seeded random points in the unit cube, 6 on its face x = 0 and its corners,
  split into two blocks at x = 0.5, with a point set "probe" of nodes 3 and 7.
- ``exodus_classic.exo``: the same mesh in netCDF classic 64-bit offset, laid out here
  variable by variable as the Exodus II manual describes it (``coordx``... ``TETRA4``):
  blocks 10 "left" and 20 "right", side set 7 "wall" on the faces at x = 0 with sides
  numbered by the manual's TETRA table, node set 7 "wall" of those faces' nodes
  (derived from the side set), node set 4 "probe" of nodes 3 and 7.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def mesh():
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(11)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    on_wall = rng.random((6, 3))
    on_wall[:, 0] = 0.0  # points on the side set's face x = 0
    points = np.vstack([corners, rng.random((40, 3)), on_wall])
    tets = Delaunay(points).simplices.astype(np.int64)
    p = points[tets]
    volume = np.einsum(
        "ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])
    )
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]  # positive (VTK / Exodus order)
    tets = tets[np.abs(volume) > 1e-12]
    left = points[tets].mean(axis=1)[:, 0] < 0.5
    return points, tets, left


# the Exodus manual's TETRA sides, 1-based nodes
SIDES = {1: (1, 2, 4), 2: (2, 3, 4), 3: (1, 4, 3), 4: (1, 3, 2)}


def classic(path: Path) -> None:
    import netCDF4

    points, tets, left = mesh()
    blocks = [(10, "left", tets[left]), (20, "right", tets[~left])]
    ordered = np.concatenate([b[2] for b in blocks])
    elements, sides = [], []
    for e, tet in enumerate(ordered):
        for s, nodes in SIDES.items():
            face = tet[[n - 1 for n in nodes]]
            if np.all(points[face][:, 0] == 0.0):
                elements.append(e + 1)
                sides.append(s)
    wall = np.unique([ordered[e - 1][n - 1] for e, s in zip(elements, sides) for n in SIDES[s]])
    f = netCDF4.Dataset(path, "w", format="NETCDF3_64BIT_OFFSET")
    f.api_version, f.version = np.float32(8.11), np.float32(8.11)
    f.floating_point_word_size, f.file_size = np.int32(8), np.int32(1)
    f.title = "exodus_fixtures.py"
    for name, size in (("len_name", 33), ("time_step", None), ("num_dim", 3),
                       ("num_nodes", len(points)), ("num_elem", len(ordered)),
                       ("num_el_blk", 2), ("num_side_sets", 1), ("num_node_sets", 2)):  # fmt: skip
        f.createDimension(name, size)

    for axis, c in zip("xyz", points.T):
        f.createVariable(f"coord{axis}", "f8", ("num_nodes",))[:] = c
    f.createVariable("eb_prop1", "i4", ("num_el_blk",))[:] = [10, 20]
    f.variables["eb_prop1"].setncattr("name", "ID")
    v = f.createVariable("eb_names", "S1", ("num_el_blk", "len_name"))
    v[:] = netCDF4.stringtochar(np.array(["left", "right"], "S33"))
    for b, (_, _, cells) in enumerate(blocks, 1):
        f.createDimension(f"num_el_in_blk{b}", len(cells))
        f.createDimension(f"num_nod_per_el{b}", 4)
        c = f.createVariable(f"connect{b}", "i4", (f"num_el_in_blk{b}", f"num_nod_per_el{b}"))
        c[:] = cells + 1
        c.elem_type = "TETRA4"
    f.createVariable("ss_prop1", "i4", ("num_side_sets",))[:] = [7]
    v = f.createVariable("ss_names", "S1", ("num_side_sets", "len_name"))
    v[:] = netCDF4.stringtochar(np.array(["wall"], "S33"))
    f.createDimension("num_side_ss1", len(elements))
    f.createVariable("elem_ss1", "i4", ("num_side_ss1",))[:] = elements
    f.createVariable("side_ss1", "i4", ("num_side_ss1",))[:] = sides
    f.createVariable("ns_prop1", "i4", ("num_node_sets",))[:] = [7, 4]
    v = f.createVariable("ns_names", "S1", ("num_node_sets", "len_name"))
    v[:] = netCDF4.stringtochar(np.array(["wall", "probe"], "S33"))
    for s, nodes in enumerate([wall, np.array([3, 7])], 1):
        f.createDimension(f"num_nod_ns{s}", len(nodes))
        f.createVariable(f"node_ns{s}", "i4", (f"num_nod_ns{s}",))[:] = nodes + 1
    f.close()


def with_meshio(path: Path) -> None:
    import meshio

    points, tets, left = mesh()
    m = meshio.Mesh(
        points,
        [("tetra", tets[left]), ("tetra", tets[~left])],
        point_sets={"probe": np.array([3, 7])},
    )
    meshio.write(path, m, file_format="exodus")


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "tests/data")
    classic(out / "exodus_classic.exo")
    with_meshio(out / "exodus_meshio.exo")
    print("wrote", out / "exodus_classic.exo", out / "exodus_meshio.exo")
