"""Gmsh views (``$NodeData`` / ``$ElementData``) as point and cell data: read from files
Gmsh and meshio write, written by ``save``, carried by ``jtet improve``."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import warnings

import meshio
import numpy as np
import pytest

import jtet
from jtet import _gmsh_views


@contextlib.contextmanager
def _gmsh_box(size: float):
    """The ``gmsh`` module (skips without it), initialized, holding a mesh of the unit
    box (model "box": physical volume 5, physical surface 7 on two faces) of element
    size ``size``; finalized on exit."""
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], 5)
        gmsh.model.addPhysicalGroup(2, [1, 2], 7)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        yield gmsh
    finally:
        gmsh.finalize()


def _save_with_views(gmsh, path, views, version: float, binary: int = 0) -> None:
    """Write the mesh, then append ``views``, as Gmsh saves views with their mesh."""
    gmsh.option.setNumber("Mesh.MshFileVersion", version)
    gmsh.option.setNumber("Mesh.Binary", binary)
    gmsh.write(str(path))
    gmsh.option.setNumber("PostProcessing.SaveMesh", 0)
    for view in views:
        gmsh.view.write(view, str(path), append=True)


def _box_with_views(path, version: float, binary: int, steps: int):
    """A Gmsh mesh of the unit box with a node view ``temp`` (x + step) and an element
    view ``eid`` over the tets (element number + 100 step), ``steps`` time steps each,
    saved with the mesh. Returns {element number: centroid} of the tets."""
    with _gmsh_box(0.3) as gmsh:
        nodes, coords, _ = gmsh.model.mesh.getNodes()
        xyz = coords.reshape(-1, 3)
        _, (tets,), (corners,) = gmsh.model.mesh.getElements(3)
        temp, eid = gmsh.view.add("temp"), gmsh.view.add("eid")
        for s in range(steps):
            values = (xyz[:, 0] + s)[:, None]
            gmsh.view.addModelData(temp, s, "box", "NodeData", nodes, values, time=0.5 * s)
            values = (tets + 100.0 * s)[:, None]
            gmsh.view.addModelData(eid, s, "box", "ElementData", tets, values, time=0.5 * s)
        _save_with_views(gmsh, path, (temp, eid), version, binary)
    position = dict(zip(nodes.tolist(), xyz, strict=True))
    return {
        int(t): np.mean([position[n] for n in corners[4 * i : 4 * i + 4]], axis=0)
        for i, t in enumerate(tets)
    }


@pytest.mark.parametrize("steps", [1, 2])
@pytest.mark.parametrize("binary", [0, 1])
@pytest.mark.parametrize("version", [2.2, 4.1])
def test_views_gmsh_saves_with_its_mesh(tmp_path, version, binary, steps):
    path = tmp_path / "box.msh"
    centroids = _box_with_views(path, version, binary, steps)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = jtet.load(path)
    messages = [str(w.message) for w in caught]
    if steps == 1:
        assert messages == []
    else:
        assert len(messages) == 2
        assert all("at the last of its 2 time steps (time 0.5)" in t for t in messages)
    last = steps - 1
    # a value at every node, linear in x: read at the right nodes (ASCII files print
    # coordinates and values to 16 digits, so x + 1 may differ in its last bit)
    np.testing.assert_allclose(m.point_data["temp"], m.points[:, 0] + last, rtol=0, atol=1e-15)
    # each tet's value is its element number: that element's centroid is the tet's
    numbers = m.cell_data["eid"] - 100 * last
    assert m.cell_data["eid"].dtype == np.float64
    expected = np.array([centroids[int(n)] for n in numbers])
    np.testing.assert_allclose(m.points[m.tets].mean(axis=1), expected, rtol=0, atol=1e-14)
    assert sorted(numbers.astype(int)) == sorted(centroids)


def _data_mesh(protected: bool):
    """The two-region demo mesh (with or without its protected faces) carrying point
    data of widths 1, 2, 3, 9 and cell data of widths 1 and 3, integer and float."""
    mesh = jtet.demo_mesh("two_regions")
    if protected:  # a labelled patch of boundary faces: triangles in the .msh
        topo = mesh.topology
        faces = topo.faces[topo.boundary_face][:20]
        mesh = mesh.replace(protected_faces=faces, protected_face_labels=np.full(20, 3))
    rng = np.random.default_rng(0)
    n, m = mesh.n_points, mesh.n_tets
    return mesh.replace(
        point_data={
            "T": rng.random(n),
            "pair": rng.random((n, 2)),
            "u": rng.random((n, 3)),
            "sigma": rng.random((n, 9)),
        },
        cell_data={"material": rng.integers(1, 4, m).astype(np.int32), "e": rng.random((m, 3))},
    )


@pytest.mark.parametrize("protected", [False, True])
def test_save_writes_views_load_reads_them(tmp_path, protected):
    mesh = _data_mesh(protected)
    path = tmp_path / "out.msh"
    quality = {"quality_min_sine": mesh.quality()}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        jtet.save(mesh, path, cell_data=quality)
    messages = " ".join(str(w.message) for w in caught)
    if protected:
        # beside the labelled triangles: the mesh's own data written, a warning for
        # meshio; jtet's quality array left out
        assert "the cell data (material, e) are written as element data" in messages
        assert "not saved in the Gmsh file: 1 cell array(s)" in messages
    else:
        assert messages == ""
        # a file of tets only: meshio reads the views too
        plain = meshio.read(path)
        np.testing.assert_array_equal(plain.point_data["T"], mesh.point_data["T"])
        np.testing.assert_array_equal(plain.cell_data["material"][0], mesh.cell_data["material"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = jtet.load(path)
    assert list(back.point_data) == ["T", "pair", "u", "sigma"]
    for name, values in mesh.point_data.items():
        np.testing.assert_array_equal(back.point_data[name], values)
        assert back.point_data[name].shape == values.shape
    # Gmsh views hold reals: the integer material comes back as float64
    assert set(back.cell_data) == {"material", "e"}
    assert back.cell_data["material"].dtype == np.float64
    for name, values in mesh.cell_data.items():
        np.testing.assert_array_equal(back.cell_data[name], values)
    np.testing.assert_array_equal(back.tets, mesh.tets)


def test_gmsh_reads_the_views_jtet_writes(tmp_path):
    gmsh = pytest.importorskip("gmsh")
    mesh = _data_mesh(protected=True)
    path = tmp_path / "out.msh"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        jtet.save(mesh, path)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(path))
        names = [gmsh.option.getString(f"View[{i}].Name") for i in range(len(gmsh.view.getTags()))]
        kind, numbers, values, _, _ = gmsh.view.getModelData(gmsh.view.getTags()[0], 0)
    finally:
        gmsh.finalize()
    assert names == ["T", "pair[0]", "pair[1]", "u", "sigma", "material", "e"]
    assert kind == "NodeData"
    np.testing.assert_array_equal(np.ravel(values), mesh.point_data["T"][np.asarray(numbers) - 1])


def test_a_view_that_does_not_parse_is_named_and_the_mesh_read(tmp_path):
    mesh = _data_mesh(protected=False).replace(cell_data={})
    path = tmp_path / "out.msh"
    jtet.save(mesh.replace(point_data={}), path)
    # an ASCII section with fewer values than its header counts
    with open(path, "ab") as f:
        f.write(b'$NodeData\n1\n"short"\n1\n0\n3\n0\n1\n5\n1 0.5\n2 0.5\n$EndNodeData\n')
    with pytest.warns(UserWarning, match=r"not read: 1 point array\(s\) \(short\)"):
        back = jtet.load(path)
    assert not back.point_data
    np.testing.assert_array_equal(back.tets, mesh.tets)


def test_rows_of_is_the_last_row_of_each_number():
    rng = np.random.default_rng(3)
    for _ in range(50):
        numbers = rng.integers(1, 30, rng.integers(0, 40))
        wanted = rng.permutation(30)[: rng.integers(0, 12)] + 1
        rows = _gmsh_views._rows_of(numbers, wanted)
        last = {int(n): i for i, n in enumerate(numbers)}  # later rows overwrite
        if all(int(w) in last for w in wanted):
            assert rows.tolist() == [last[int(w)] for w in wanted]
        else:
            assert rows is None


def test_improve_carries_gmsh_views(tmp_path):
    """``jtet improve in.msh out.msh``: a field linear in the coordinates stays exact at
    the moved vertices, and each new tet takes a material of the input (read back as
    float64, so carried by overlap, not kept as a label)."""
    mesh = jtet.demo_mesh().relabel({0: 1})
    centroid_x = mesh.points[mesh.tets].mean(axis=1)[:, 0]
    data = mesh.replace(
        point_data={"T": 2.0 * mesh.points[:, 0] - mesh.points[:, 2]},
        cell_data={"material": (centroid_x > 1.0).astype(np.int32)},
    )
    src, out = tmp_path / "in.msh", tmp_path / "out.msh"
    jtet.save(data, src)
    run = subprocess.run(
        [sys.executable, "-m", "jtet.cli", "improve", str(src), str(out), "--perturb", "0", "-q"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    back = jtet.load(out)
    # linear interpolation of a linear field: exact to rounding (coordinates ~1)
    np.testing.assert_allclose(
        back.point_data["T"], 2.0 * back.points[:, 0] - back.points[:, 2], rtol=0, atol=1e-12
    )
    assert set(np.unique(back.cell_data["material"])) == {0.0, 1.0}
    assert jtet.stats(back).min_dihedral > jtet.stats(mesh).min_dihedral


def _binary22_section(rng, n_blocks: int) -> tuple[bytes, int]:
    """A binary MSH 2.2 element section (after its count line) of random blocks: runs of
    one-element blocks with one header, as Gmsh writes, and larger blocks, as meshio
    writes, of points, lines, triangles and tets with 2-3 tags (one count per type:
    meshio stacks a type's tags). Returns (bytes, total)."""
    nodes = {15: 1, 1: 2, 2: 3, 4: 4}
    tag_counts = {kind: int(rng.integers(2, 4)) for kind in nodes}
    parts, total = [], 0
    for _ in range(n_blocks):
        kind = int(rng.choice(list(nodes)))
        n_tags = tag_counts[kind]
        counts = (
            [1] * int(rng.integers(1, 200)) if rng.random() < 0.6 else [int(rng.integers(2, 9))]
        )
        for count in counts:
            rows = rng.integers(1, 1000, (count, 1 + n_tags + nodes[kind]), dtype=np.intc)
            parts.append(np.array([kind, count, n_tags], np.intc).tobytes() + rows.tobytes())
            total += count
    return b"".join(parts), total


def _ascii22_section(rng, blocks: bytes) -> bytes:
    """The ASCII lines of the elements of a binary section (``_binary22_section``),
    numbers separated by 1-2 spaces or a tab."""
    ints = np.frombuffer(blocks, np.intc)
    nodes = {15: 1, 1: 2, 2: 3, 4: 4}
    lines, pos = [], 0
    while pos < len(ints):
        kind, count, n_tags = ints[pos : pos + 3].tolist()
        width = 1 + n_tags + nodes[kind]
        rows = ints[pos + 3 : pos + 3 + count * width].reshape(count, width)
        for row in rows.tolist():
            fields = [row[0], kind, n_tags, *row[1:]]
            gaps = rng.choice([" ", "  ", "\t"], len(fields))
            lines.append("".join(f"{v}{g}" for v, g in zip(fields, gaps, strict=True)) + "\n")
        pos += 3 + count * width
    return "".join(lines).encode()


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_element_sections_read_as_meshio_reads_them(tmp_path, encoding):
    """``_read_cells22`` (whole blocks at once: runs of one-element blocks as strided
    views, ASCII lines parsed together) gives meshio 5.3's own ``_read_cells`` output
    and leaves the file at the same place, on random sections whose nodes are listed
    out of order; a section that ends early is a ValueError."""
    from meshio.gmsh import _gmsh22

    from jtet._gmsh_read import _read_cells22

    rng = np.random.default_rng(5)
    node_numbers = rng.permutation(np.arange(1, 1000))  # node i of the file is number ...
    for trial in range(20):
        section, total = _binary22_section(rng, int(rng.integers(1, 12)))
        if encoding == "ascii":
            section = _ascii22_section(rng, section)
        path = tmp_path / f"s{trial}.msh"
        path.write_bytes(f"{total}\n".encode() + section + b"\n$EndElements\n$Next\n")
        outputs = []
        for read in (_gmsh22._read_cells, _read_cells22):
            cells = []
            with open(path, "rb") as f:
                result = read(f, cells, node_numbers, encoding == "ascii")
                outputs.append((cells, result, f.readline()))
        (cells, (extra, tags), after), (mine, (my_extra, my_tags), my_after) = outputs
        assert after == my_after == b"$Next\n"
        assert [c[0] for c in mine] == [c[0] for c in cells]
        for (_, a), (_, b) in zip(cells, mine, strict=True):
            np.testing.assert_array_equal(a, b)
        assert extra == my_extra
        assert tags.keys() == my_tags.keys()
        for key in tags:
            assert tags[key].keys() == my_tags[key].keys()
            for name in tags[key]:
                np.testing.assert_array_equal(tags[key][name], my_tags[key][name])
    path.write_bytes(f"{total}\n".encode() + section[: len(section) // 2])
    with open(path, "rb") as f, pytest.raises(ValueError):
        _read_cells22(f, [], node_numbers, encoding == "ascii")


@pytest.mark.parametrize(
    "header",
    [
        b"1000000000\n",  # string tags: would read empty lines for ever
        b'1\n"big"\n1\n0\n3\n0\n1\n999999999999\n',  # more values than the file holds
        b'1\n"neg"\n1\n0\n3\n0\n-2\n5\n',  # a negative component count
    ],
    ids=["tag-count", "value-count", "components"],
)
def test_damaged_view_headers_are_skipped_quickly(tmp_path, header):
    mesh = _data_mesh(protected=False).replace(point_data={}, cell_data={})
    path = tmp_path / "out.msh"
    jtet.save(mesh, path)
    with open(path, "ab") as f:
        f.write(b"$NodeData\n" + header + b"1 0.5\n$EndNodeData\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the first case names no view
        back = jtet.load(path)
    assert not back.point_data
    np.testing.assert_array_equal(back.tets, mesh.tets)


def _msh41_elements(rng, encoding: str) -> tuple[bytes, tuple, tuple, dict, list]:
    """A random MSH 4.1 ``$Elements`` section (after its header line) of point, line,
    triangle and tet blocks on entities, with the entity tables meshio builds from
    ``$Entities`` (physical tags, bounding entities) and ``$PhysicalNames``, and the
    element numbers of each block."""
    nodes = {15: (0, 1), 1: (1, 2), 2: (2, 3), 4: (3, 4)}  # type: (dim, nodes)
    physical = ({}, {}, {}, {})
    bounding = ({}, {}, {}, {})
    field_data = {"skin": np.array([7, 2]), "body": np.array([5, 3])}
    blocks, number = [], 1
    for _ in range(int(rng.integers(1, 9))):
        kind = int(rng.choice(list(nodes)))
        dim, n_nodes = nodes[kind]
        tag = int(rng.integers(1, 4))
        physical[dim][tag] = [int(rng.choice([5, 7, 9]))] if rng.random() < 0.7 else []
        if dim:
            bounding[dim][tag] = rng.integers(1, 5, 2)
        count = int(rng.integers(1, 30))
        rows = np.column_stack(
            [np.arange(number, number + count), rng.integers(1, 300, (count, n_nodes))]
        )
        number += count + int(rng.integers(0, 5))  # numbers with gaps
        blocks.append((dim, tag, kind, rows))
    total = sum(len(b[3]) for b in blocks)
    numbers = [rows[:, 0] for *_, rows in blocks]
    if encoding == "ascii":
        text = f"{len(blocks)} {total} 1 {number}\n"
        for dim, tag, kind, rows in blocks:
            text += f"{dim} {tag} {kind} {len(rows)}\n"
            text += "".join(" ".join(map(str, r)) + "\n" for r in rows.tolist())
        return text.encode(), physical, bounding, field_data, numbers
    size_t = np.uint64
    data = np.array([len(blocks), total, 1, number], size_t).tobytes()
    for dim, tag, kind, rows in blocks:
        data += np.array([dim, tag, kind], np.intc).tobytes()
        data += np.array([len(rows)], size_t).tobytes() + rows.astype(size_t).tobytes()
    return data + b"\n", physical, bounding, field_data, numbers


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_msh41_elements_read_as_meshio_reads_them(tmp_path, encoding):
    """``_read_elements41`` gives meshio 5.3's own ``_read_elements`` output (cells,
    physical and entity tags, physical-group sets, bounding entities), and the element
    numbers of each block."""
    from meshio.gmsh import _gmsh41

    from jtet._gmsh_read import _read_elements41

    rng = np.random.default_rng(6)
    point_tags = rng.permutation(300)  # meshio's node tags: node numbers - 1
    for trial in range(20):
        section, physical, bounding, field_data, written = _msh41_elements(rng, encoding)
        path = tmp_path / f"e{trial}.msh"
        path.write_bytes(section + b"$EndElements\n$Next\n")
        args = (point_tags, physical, bounding, encoding == "ascii", 8, field_data)
        with open(path, "rb") as f:
            cells, data, sets = _gmsh41._read_elements(f, *args)
            after = f.readline()
        with open(path, "rb") as f:
            mine, my_data, my_sets, numbers = _read_elements41(f, *args)
            assert f.readline() == after == b"$Next\n"
        assert [c.type for c in mine] == [c.type for c in cells]
        for a, b in zip(cells, mine, strict=True):
            np.testing.assert_array_equal(a.data, b.data)
        assert data.keys() == my_data.keys()
        for key in data:
            for a, b in zip(data[key], my_data[key], strict=True):
                np.testing.assert_array_equal(a, b)
        assert sets.keys() == my_sets.keys()
        for key in sets:
            for a, b in zip(sets[key], my_sets[key], strict=True):
                np.testing.assert_array_equal(a, b)
        # the element numbers, block by block, as written
        assert [n.tolist() for n in numbers] == [n.tolist() for n in written]


def test_a_step_in_several_sections_is_joined(tmp_path):
    """A view step may come in several sections (one per partition: the fourth integer
    tag); the last step's sections together give every node its value."""
    mesh = jtet.demo_mesh()
    path = tmp_path / "parts.msh"
    blocks = [meshio.CellBlock("tetra", mesh.tets)]
    tags = {
        "gmsh:physical": [np.ones(mesh.n_tets, int)],
        "gmsh:geometrical": [np.ones(mesh.n_tets, int)],
    }
    meshio.write(path, meshio.Mesh(mesh.points, blocks, cell_data=tags), "gmsh22", binary=False)
    half = mesh.n_points // 2
    with open(path, "a") as f:
        for step in (0, 1):
            for part, nodes in ((1, range(1, half + 1)), (2, range(half + 1, mesh.n_points + 1))):
                f.write(f'$NodeData\n1\n"T"\n1\n{step}.0\n4\n{step}\n1\n{len(nodes)}\n{part}\n')
                f.write("".join(f"{i} {10.0 * step + i}\n" for i in nodes) + "$EndNodeData\n")
    with pytest.warns(UserWarning, match="at the last of its 2 time steps"):
        back = jtet.load(path)
    np.testing.assert_array_equal(back.point_data["T"], 10.0 + np.arange(1, mesh.n_points + 1))


@pytest.mark.parametrize("version", [2.2, 4.1])
def test_element_node_data_is_named_as_not_read(tmp_path, version):
    """A view of values at each node of each element ($ElementNodeData, a field
    discontinuous across elements) has no place in point or cell data: a warning names
    it (meshio skips it silently), the other views are read."""
    path = tmp_path / "enode.msh"
    with _gmsh_box(0.5) as gmsh:
        _, (tets,), _ = gmsh.model.mesh.getElements(3)
        nodes, coords, _ = gmsh.model.mesh.getNodes()
        per_node = gmsh.view.add("jumps")
        gmsh.view.addModelData(per_node, 0, "box", "ElementNodeData", tets, np.ones((len(tets), 4)))
        temp = gmsh.view.add("temp")
        gmsh.view.addModelData(temp, 0, "box", "NodeData", nodes, coords.reshape(-1, 3)[:, :1])
        _save_with_views(gmsh, path, (per_node, temp), version)
    with pytest.warns(UserWarning, match=r"not read: 1 cell array\(s\) \(jumps\)"):
        m = jtet.load(path)
    assert list(m.point_data) == ["temp"] and not m.cell_data
