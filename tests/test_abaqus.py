"""Abaqus / CalculiX input files (.inp): written and read back, the element-face
surfaces checked against the Abaqus face table, files of Gmsh and meshio read, bad
files refused. (experiments/calculix_inp.py runs CalculiX itself on jtet's files.)"""

import re
import warnings

import meshio
import numpy as np
import pytest
from helpers import delaunay_mesh

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet.cli import main

# The Abaqus manual's C3D4 faces, by 1-based element node: S1 1-2-3, S2 1-4-2,
# S3 2-4-3, S4 3-4-1 (typed here from the manual, not taken from jtet)
ABAQUS_C3D4_FACES = {1: (1, 2, 3), 2: (1, 4, 2), 3: (2, 4, 3), 4: (3, 4, 1)}


@pytest.fixture(scope="module")
def labelled():
    m = delaunay_mesh(120, seed=6, surface_points=80)
    T = m.topology
    faces = T.faces[T.boundary_face]
    centre = m.points[faces].mean(axis=1)
    labels = np.where(np.isclose(centre[:, 0], 1), 7, np.where(np.isclose(centre[:, 0], 0), 8, 9))
    region = np.digitize(m.points[m.tets].mean(axis=1)[:, 2], [0.5]) + 1
    return m.replace(
        region=region,
        protected_faces=faces,
        protected_face_labels=labels,
        label_names={(3, 1): "lower half", (2, 7): "load"},
    )


def _save(mesh, path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jtet.save(mesh, path, **kw)


def test_round_trip(tmp_path, labelled):
    path = tmp_path / "m.inp"
    _save(labelled, path)
    back = jtet.load(path)
    # 16 significant digits (CalculiX refuses 17 with an exponent): within 2 ulp
    np.testing.assert_allclose(back.points, labelled.points, rtol=0, atol=4e-16)
    for name in ("tets", "region", "protected_faces", "protected_face_labels"):
        np.testing.assert_array_equal(getattr(back, name), getattr(labelled, name), err_msg=name)
    # names become Abaqus names (letters, digits, underscores)
    assert dict(back.label_names) == {(3, 1): "lower_half", (2, 7): "load"}
    text = path.read_text()
    assert "*ELEMENT, TYPE=C3D4, ELSET=lower_half" in text and "ELSET=REGION2" in text
    assert "*SURFACE, NAME=load, TYPE=ELEMENT" in text and "*NSET, NSET=load_NODES" in text
    # every element, for decks that put their section on Eall (not a region when read)
    assert f"*ELSET, ELSET=EALL, GENERATE\n1, {labelled.n_tets}, 1\n" in text


def test_surfaces_follow_the_abaqus_face_table(tmp_path, labelled):
    """Each element-face set of a written surface names, through the manual's face
    table, exactly the protected faces of that label, and every face number occurs."""
    path = tmp_path / "m.inp"
    _save(labelled, path)
    text = path.read_text()
    elements = {}
    for block in re.findall(r"\*ELEMENT, TYPE=C3D4[^\n]*\n((?:\d[^\n]*\n)+)", text):
        for line in block.splitlines():
            e, *nodes = map(int, line.split(","))
            elements[e] = nodes
    sets = {
        name: [int(v) for v in body.replace(",", " ").split()]
        for name, body in re.findall(r"\*ELSET, ELSET=(\S+)\n((?:[\d, ]+\n)+)", text)
    }
    seen = set()
    for label in (7, 8, 9):
        name = "load" if label == 7 else f"SURFACE{label}"
        body = re.search(rf"\*SURFACE, NAME={name}, TYPE=ELEMENT\n((?:\S+, S\d\n)+)", text)
        found = set()
        for line in body.group(1).splitlines():
            elset, side = (p.strip() for p in line.split(","))
            k = int(side[1])
            seen.add(k)
            for e in sets[elset]:
                nodes = elements[e]
                found.add(tuple(sorted(nodes[i - 1] - 1 for i in ABAQUS_C3D4_FACES[k])))
        mine = labelled.protected_faces[labelled.protected_face_labels == label]
        assert found == {tuple(sorted(f)) for f in mine.tolist()}
    assert seen == {1, 2, 3, 4}


def test_file_written_by_gmsh(tmp_path):
    """Gmsh writes physical volumes and surfaces as element sets (*ELSET) beside its
    entities' sets: the regions and the labelled surface match Gmsh's own .msh."""
    from helpers import named_ball_in_box

    named_ball_in_box(tmp_path / "g.msh", tmp_path / "g.inp")
    inp, msh = jtet.load(tmp_path / "g.inp"), jtet.load(tmp_path / "g.msh")
    np.testing.assert_array_equal(inp.tets, msh.tets)
    assert {v: k for k, v in inp.label_names.items() if k[0] == 3} == {
        "ball": (3, 1),
        "box": (3, 2),
    }
    for name in ("ball", "box"):
        label_inp = next(k[1] for k, v in inp.label_names.items() if v == name)
        label_msh = next(k[1] for k, v in msh.label_names.items() if v == name)
        assert inp.volumes[inp.region == label_inp].sum() == pytest.approx(
            msh.volumes[msh.region == label_msh].sum(), rel=1e-12
        )
    assert {tuple(f) for f in inp.protected_faces.tolist()} == {
        tuple(f) for f in msh.protected_faces.tolist()
    }
    assert set(inp.protected_face_labels.tolist()) == {1}
    assert inp.label_names[(2, 1)] == "walls"


def test_file_written_by_meshio(tmp_path, labelled):
    m = meshio.Mesh(
        labelled.points,
        [("tetra", labelled.tets)],
        cell_sets={
            "low": [np.flatnonzero(labelled.region == 1)],
            "high": [np.flatnonzero(labelled.region == 2)],
        },
    )
    meshio.abaqus.write(tmp_path / "m.inp", m)
    back = jtet.load(tmp_path / "m.inp")
    np.testing.assert_array_equal(back.tets, labelled.tets)
    low = next(k[1] for k, v in back.label_names.items() if v == "low")
    np.testing.assert_array_equal(back.region == low, labelled.region == 1)


def test_improve_cli(tmp_path, labelled):
    src, out = tmp_path / "in.inp", tmp_path / "out.inp"
    _save(labelled, src)
    assert main(["improve", str(src), str(out), "-q", "--max-passes", "2", "--perturb", "0"]) == 0
    back = jtet.load(out)
    assert back.is_valid().ok
    assert jtet.stats(back).min_dihedral >= jtet.stats(labelled).min_dihedral - 1e-9
    assert (back.region != 0).all() and len(back.protected_faces)


NODES = "*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n3, 0, 1, 0\n4, 0, 0, 1\n5, 1, 1, 1\n"


@pytest.mark.parametrize(
    "text, error, match",
    [
        (NODES + "*ELEMENT, TYPE=C3D8\n1, 1, 2, 3, 4, 5, 1, 2, 3\n", MeshInputError, "C3D8 x 1"),
        (NODES + "*ELEMENT, TYPE=C3D10\n1, 1, 2, 3, 4, 5, 1, 2, 3, 4, 5\n", MeshInputError,
         "quadratic"),
        ("*PART, NAME=P1\n" + NODES, MeshInputError, r"\*PART is not supported"),
        (NODES + "*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 9\n", MeshInputError, "node 9, which no"),
        (NODES + "*ELEMENT, TYPE=C3D4\n1, 1, 2, x, 4\n", MeshFileError, "not numbers"),
        ("*NODE\n1, 0, 0\n2, 1, 0\n", MeshInputError, "2-D"),
        (NODES + "1, 0, 0, 0\n*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 4\n", MeshInputError,
         "node 1 is defined twice"),
        (NODES + "*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 4\n*SURFACE, NAME=S\nNOPE, S1\n",
         MeshInputError, "unknown set 'NOPE'"),
        (NODES + "*ELEMENT, TYPE=CPS3\n1, 1, 2, 3\n", MeshInputError, "no tetrahedra"),
        ("1, 0, 0, 0\n", MeshFileError, "data before any keyword"),
        ("*HEADING\nonly a heading\n", MeshInputError, "no \\*NODE"),
        ("*NODE, SYSTEM=C\n1, 1, 0, 0\n", MeshInputError, "SYSTEM=C is not supported"),
        ("*NODE, INPUT=nodes.inp\n", MeshInputError, "INPUT= .* is not supported"),
    ],
)  # fmt: skip
def test_bad_files_are_refused(tmp_path, text, error, match):
    path = tmp_path / "bad.inp"
    path.write_text(text)
    with pytest.raises(error, match=match) as e:
        jtet.load(path)
    assert str(path) in str(e.value)


def test_sets_by_range_and_by_name(tmp_path):
    """``*ELSET, GENERATE`` ranges and sets made of other sets' names, and a set of
    every tet (CalculiX's "Eall"), which is no region when there are others."""
    text = (
        NODES
        + "*ELEMENT, TYPE=C3D4, ELSET=EALL\n1, 1, 2, 3, 4\n2, 2, 3, 4, 5\n"
        + "*ELSET, ELSET=FIRST, GENERATE\n1, 1, 1\n*ELSET, ELSET=ALSO\nFIRST\n"
        + "*ELSET, ELSET=SECOND\n2\n*SURFACE, NAME=TOP, TYPE=ELEMENT\nFIRST, S1\n"
        # a surface listing its elements one by one (CalculiX writes them so), and a
        # line that is neither: S3 of element 2 (nodes 2 3 4 5) is nodes 2-4-3 -> 3 5 4
        + "*SURFACE, NAME=SIDE, TYPE=ELEMENT\n2, S3\noops\n"
    )
    path = tmp_path / "sets.inp"
    path.write_text(text)
    with pytest.warns(UserWarning, match=r"SIDE: 1 line\(s\) .* skipped"):
        m = jtet.load(path)
    side = next(k[1] for k, v in m.label_names.items() if v == "SIDE")
    assert np.sort(m.protected_faces[m.protected_face_labels == side], axis=1).tolist() == [
        [2, 3, 4]
    ]
    assert m.region.tolist() == [1, 2]  # ALSO adds no tet: no region of its own
    assert {k: v for k, v in m.label_names.items() if k[0] == 3} == {
        (3, 1): "FIRST",
        (3, 2): "SECOND",
    }
    top = m.protected_faces[m.protected_face_labels == 1]
    assert top.tolist() == [[0, 1, 2]] and m.label_names[(2, 1)] == "TOP"


def _node_sets(path) -> dict[str, set[int]]:
    """{NSET name: node ids} of an .inp file, parsed here with a regular expression
    (ids only, as Gmsh and jtet write them)."""
    found = re.findall(r"(?ms)^\*NSET, ?NSET=([^\n,]+)\n(.*?)(?=^\*|\Z)", path.read_text())
    return {name.strip(): {int(t) for t in body.replace(",", " ").split()} for name, body in found}


def test_gmsh_node_sets_are_written_back(tmp_path):
    """Gmsh's export with ``Mesh.SaveGroupsOfNodes`` (what CalculiX decks name in
    *BOUNDARY): the physical volume names the region (not Gmsh's elementary set beside
    it), the physical point's node set is a node set (the others are the nodes of the
    region and surfaces, written again from them), and an improved output has a node
    set of each physical group's name holding the same node ids (jtet keeps the nodes'
    numbering; flips change no node set of a region, surface or point)."""
    gmsh = pytest.importorskip("gmsh")
    path = tmp_path / "g.inp"
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], 1, name="solid")
        gmsh.model.addPhysicalGroup(2, [1], 2, name="fix")
        gmsh.model.addPhysicalGroup(2, [2], 3, name="load")
        gmsh.model.addPhysicalGroup(0, [1], 4, name="corner")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.3)
        gmsh.option.setNumber("Mesh.SaveGroupsOfNodes", 1)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    mesh = jtet.load(path)
    assert {v for k, v in mesh.label_names.items() if k[0] == 3} == {"solid"}
    given = _node_sets(path)
    assert set(given) == {"solid", "fix", "load", "corner"}
    assert [ns.name for ns in mesh.node_sets] == ["corner"]
    assert (mesh.node_sets[0].ids + 1).tolist() == sorted(given["corner"])
    out = tmp_path / "out.inp"
    result = jtet.improve(mesh, max_passes=3, perturb=0)
    assert result.mesh.n_tets != mesh.n_tets  # flips ran
    _save(result.mesh, out)
    written = _node_sets(out)
    for name, ids in given.items():
        assert written[name] == ids, name
    np.testing.assert_array_equal(jtet.load(out).node_sets[0].ids, mesh.node_sets[0].ids)


def test_node_sets_of_a_deck_stay_put(tmp_path, labelled):
    """Hand-made node sets (a probe inside, a tip sharing a node with it, every node)
    are kept as they are, overlaps included: improve never moves the probe's or the
    tip's nodes (while it moves others), a set of every node ("NALL") constrains
    nothing, and the output writes each back under its name with its nodes."""
    src = tmp_path / "deck.inp"
    _save(labelled, src)
    interior = np.setdiff1d(np.arange(labelled.n_points), np.unique(labelled.protected_faces))
    probe, corner = interior[:3] + 1, [1]
    text = src.read_text() + (
        "*NSET, NSET=PROBE\n" + ", ".join(map(str, probe)) + "\n"
        "*NSET, NSET=NALL, GENERATE\n1, " + str(labelled.n_points) + ", 1\n"
        "*NSET, NSET=TIP\n" + ", ".join(map(str, [*corner, probe[0]])) + "\n"
    )
    src.write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = jtet.load(src)
    sets = {ns.name: (ns.ids + 1).tolist() for ns in mesh.node_sets}
    assert sets == {
        "PROBE": sorted(probe.tolist()),
        "NALL": list(range(1, labelled.n_points + 1)),
        "TIP": sorted([*corner, int(probe[0])]),
    }
    assert len(mesh.protected_vertices) == 0
    result = jtet.improve(mesh, max_passes=3, perturb=0)
    moved = np.flatnonzero((result.mesh.points != mesh.points).any(axis=1))
    assert len(moved) and not set(moved.tolist()) & {i - 1 for i in [*probe, *corner]}
    out = tmp_path / "out.inp"
    _save(result.mesh, out)
    written = _node_sets(out)
    assert {k: sorted(written[k]) for k in sets} == sets
