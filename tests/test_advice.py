"""The notes ``improve`` adds to its summary (``jtet._advice``)."""

import contextlib
import io

import numpy as np
from helpers import grid_mesh

import jtet
from jtet._advice import (
    BOUNDARY_ONLY_SHARE,
    boundary_only_share,
    cornered_worst_tets,
    notes,
    pinned_worst_tets,
)
from jtet._quality import tet_all_measures
from jtet.cli import main


def _kinds_from_coordinates(points: np.ndarray) -> np.ndarray:
    """Vertex kinds of a unit-cube mesh from coordinates alone: how many coordinates are
    0 or 1 (0 free, 1 on a face, 2 on an edge, 3 a corner), an independent reference for
    the topology's classification."""
    return np.isclose(points, 0.0).sum(axis=1) + np.isclose(points, 1.0).sum(axis=1)


def test_pinned_worst_tets_against_coordinates():
    m = grid_mesh(2)
    kinds = _kinds_from_coordinates(np.asarray(m.points))[m.tets]  # (m, 4)
    expect = (kinds > 0).all(axis=1) & (kinds < 3).any(axis=1)
    assert expect.any() and not expect.all()  # both cases occur in this mesh
    for t in range(m.n_tets):
        q = np.ones(m.n_tets)
        q[t] = 0.5
        assert pinned_worst_tets(m, q).tolist() == ([t] if expect[t] else [])


def test_pinned_worst_tets_reads_every_tied_tet():
    m = grid_mesh(2)
    kinds = _kinds_from_coordinates(np.asarray(m.points))[m.tets]
    stuck = np.flatnonzero((kinds > 0).all(axis=1) & (kinds < 3).any(axis=1))
    free = np.flatnonzero((kinds == 0).any(axis=1))
    q = np.ones(m.n_tets)
    q[[free[0], stuck[1]]] = 0.25  # tied worst: one free, one pinned
    q[stuck[0]] = 0.25 + 1e-6  # not tied (beyond _advice.TIE)
    assert pinned_worst_tets(m, q).tolist() == [stuck[1]]


def test_cornered_worst_tets_against_coordinates():
    # one cube: every tet's four vertices are corners of the cube; a 2x2x2 grid: no tet's
    for n, every in ((1, True), (2, False)):
        m = grid_mesh(n)
        kinds = _kinds_from_coordinates(np.asarray(m.points))[m.tets]
        expect = (kinds == 3).all(axis=1)
        assert expect.all() if every else not expect.any()
        for t in range(m.n_tets):
            q = np.ones(m.n_tets)
            q[t] = 0.5
            assert cornered_worst_tets(m, q).tolist() == ([t] if expect[t] else [])


def _ball_labelled_grid() -> jtet.TetMesh:
    """A perturbed 6x6x6 grid whose tets with centroids within 0.3 of the centre are
    region 1: the interface between the regions bends at nearly every vertex (labels
    given to tets after meshing, as segmented images get them)."""
    m = grid_mesh(6, perturb=0.2, seed=1)
    centroids = np.asarray(m.points)[m.tets].mean(axis=1)
    return m.replace(region=(np.linalg.norm(centroids - 0.5, axis=1) < 0.3).astype(np.int64))


def test_improve_notes_a_worst_tet_held_by_corners():
    r = jtet.improve(_ball_labelled_grid(), check=True)
    (note,) = r.notes
    out = r.mesh
    _, lo, hi, qualities = tet_all_measures(out.points, out.tets)
    q = qualities[r.options.quality]
    (t, *_) = cornered_worst_tets(out, q)
    assert f"{lo[t]:.2f}-{hi[t]:.2f} deg" in note and "corners" in note
    assert "none of the run's flips raised it" in note
    # what the note says: no boundary setting moves its vertices
    slid = jtet.improve(out, ops=("smooth",), boundary="slide", check=True).mesh
    assert np.array_equal(slid.points[out.tets[t]], out.points[out.tets[t]])
    # without flips the note names them
    (no_flips,) = notes(out, jtet.Options(ops=("smooth",)), q, lo, hi)
    assert "--ops edge,face" in no_flips


def test_the_boundary_only_note_stands_for_the_corner_note():
    m = grid_mesh(1)  # every vertex a corner of the cube, every tet without a free one
    _, lo, hi, qualities = tet_all_measures(m.points, m.tets)
    q = qualities["biased_min_sine"]
    opts = jtet.Options(good_quality=None)
    (corner_note,) = notes(m, opts, q, lo, hi)
    assert "corners" in corner_note
    (boundary_note,) = notes(m, opts, q, lo, hi, input_boundary_only=boundary_only_share(m))
    assert boundary_note.startswith("100% of the input's tets")


def _mesh_with_a_pinned_worst_tet() -> jtet.TetMesh:
    """The 2x2x2 grid with the centre of its face x = 1 moved within that face: its
    worst tets have all four vertices on the boundary."""
    m = grid_mesh(2)
    pts = np.array(m.points)
    centre = np.flatnonzero(np.all(np.isclose(pts, [1.0, 0.5, 0.5]), axis=1))
    pts[centre] = [1.0, 0.3, 0.35]
    out = jtet.TetMesh(pts, m.tets)
    assert out.volumes.min() > 0
    return out


def test_notes_only_for_fixed_boundaries_below_good_quality():
    m = _mesh_with_a_pinned_worst_tet()
    q = m.quality("biased_min_sine")
    _, lo, hi, _ = tet_all_measures(m.points, m.tets)
    assert pinned_worst_tets(m, q).size
    (note,) = notes(m, jtet.Options(), q, lo, hi)
    t = pinned_worst_tets(m, q)[0]
    assert f"{lo[t]:.2f}-{hi[t]:.2f} deg" in note and "--boundary slide" in note
    assert notes(m, jtet.Options(boundary="slide"), q, lo, hi) == []
    # sliding is a smoothing option: without smoothing it frees nothing
    assert notes(m, jtet.Options(ops=("edge", "face")), q, lo, hi) == []
    # every tet at least as good as good_quality: the run left them alone on purpose
    assert notes(m, jtet.Options(good_quality=float(q.min())), q, lo, hi) == []


def test_improve_notes_a_pinned_worst_tet_that_sliding_frees():
    m = _mesh_with_a_pinned_worst_tet()
    fixed = jtet.improve(m, ops=("smooth",), check=True)
    assert len(fixed.notes) == 1
    assert f"note: {fixed.notes[0]}" in fixed.summary()
    assert fixed.as_dict()["notes"] == fixed.notes
    # what the note suggests does raise the worst tet
    slide = jtet.improve(m, ops=("smooth",), boundary="slide", check=True)
    assert slide.notes == []
    assert slide.stats_after.min_dihedral > fixed.stats_after.min_dihedral + 1.0


def test_improve_command_prints_the_note(tmp_path):
    src, out = tmp_path / "in.vtu", tmp_path / "out.vtu"
    jtet.save(_mesh_with_a_pinned_worst_tet(), src)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(io.StringIO()):
        assert main(["improve", str(src), str(out), "--ops", "smooth"]) == 0
    assert "note: the worst tet by biased_min_sine" in stdout.getvalue()
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(io.StringIO()):
        assert main(["improve", str(src), str(out), "--ops", "smooth", "--boundary", "slide"]) == 0
    assert "note:" not in stdout.getvalue()


def test_missed_goals_are_noted_whatever_else_holds():
    """A goal note names each missed goal with the mesh's value, none for met or unset
    goals, and comes even when every tet is good enough (the goal asks for more)."""
    m = _mesh_with_a_pinned_worst_tet()
    q = m.quality("biased_min_sine")
    _, lo, hi, _ = tet_all_measures(m.points, m.tets)
    good = jtet.Options(good_quality=float(q.min()))

    def goal_notes(**goals):
        return [n for n in notes(m, good.replace(**goals), q, lo, hi) if "goals" in n]

    assert goal_notes() == []
    assert goal_notes(goal_min_dihedral=float(lo.min()), goal_max_dihedral=float(hi.max())) == []
    (note,) = goal_notes(goal_min_dihedral=float(lo.min()) + 1.0)
    assert f"smallest dihedral angle {lo.min():.2f} deg (goal >= {lo.min() + 1:g})" in note
    assert "largest" not in note
    (note,) = goal_notes(goal_min_dihedral=1.0, goal_max_dihedral=float(hi.max()) - 1.0)
    assert "smallest" not in note and f"largest dihedral angle {hi.max():.2f} deg" in note


def test_note_when_the_perturbation_rounds_hit_their_limit():
    """A run whose rounds all kept a kick up to ``perturb`` gets a note to raise it; a
    run that kept fewer (its last round kept nothing), or stopped for a goal or the
    time limit (-1), does not."""
    grid = grid_mesh(2)
    q = grid.quality("biased_min_sine") * 0.5  # below good_quality: the notes look
    lo, hi = np.zeros(grid.n_tets), np.ones(grid.n_tets)
    opts = jtet.Options(perturb=3)
    (note,) = [n for n in notes(grid, opts, q, lo, hi, kept_rounds=3) if "perturb" in n]
    assert "limit (perturb 3: kept rounds)" in note and "(--perturb 6)" in note
    for kept in (2, -1):
        assert not [n for n in notes(grid, opts, q, lo, hi, kept_rounds=kept) if "perturb" in n]
    assert not [n for n in notes(grid, jtet.Options(perturb=0), q, lo, hi) if "perturb" in n]
    # "auto": the note names the count it stood for (8 on a small mesh, or the run's)
    auto = jtet.Options()
    (note,) = [n for n in notes(grid, auto, q, lo, hi, kept_rounds=8) if "perturb" in n]
    assert "limit (perturb auto: 8 kept rounds)" in note and "(--perturb 16)" in note
    assert not [n for n in notes(grid, auto, q, lo, hi, kept_rounds=7) if "perturb" in n]
    (note,) = [n for n in notes(grid, auto, q, lo, hi, 14, rounds=14) if "perturb" in n]
    assert "limit (perturb auto: 14 kept rounds)" in note and "(--perturb 28)" in note


def test_improve_notes_rounds_cut_by_their_limit():
    """On the demo mesh the first rounds all keep a kick: with ``perturb=1`` the run
    says so, and what the note suggests (more rounds) does raise the worst tet."""
    demo = jtet.demo_mesh()
    one = jtet.improve(demo, perturb=1)
    assert any("(--perturb 2)" in n for n in one.notes)
    two = jtet.improve(demo, perturb=2)
    q1 = one.stats_after.quality_min["biased_min_sine"]
    assert two.stats_after.quality_min["biased_min_sine"] > q1


def test_boundary_only_share_against_coordinates():
    """The share of tets without an interior vertex, and whether one of them has a
    vertex that sliding could move (on a face or an edge of the cube, not a corner),
    against the classification by coordinates."""
    for n in (1, 2, 3):
        m = grid_mesh(n)
        kinds = _kinds_from_coordinates(np.asarray(m.points))[m.tets]
        pinned = (kinds > 0).all(axis=1)
        share, slidable = boundary_only_share(m)
        assert share == pinned.mean()
        assert slidable == bool((pinned[:, None] & (kinds < 3)).any())
    assert boundary_only_share(grid_mesh(1)) == (1.0, False)  # 6 tets, 8 corners


def test_note_when_most_input_tets_have_no_interior_vertex():
    m = _mesh_with_a_pinned_worst_tet()
    q = m.quality("biased_min_sine")
    _, lo, hi, _ = tet_all_measures(m.points, m.tets)

    def share_notes(opts, share, slidable=False):
        found = notes(m, opts, q, lo, hi, input_boundary_only=(share, slidable))
        return [n for n in found if "of the input's tets" in n]

    (note,) = share_notes(jtet.Options(), 0.75)
    assert note.startswith("75% of the input's tets have all four vertices on the boundary")
    assert "TetGen -q" in note and "--boundary slide" not in note
    (note,) = share_notes(jtet.Options(), 1.0, slidable=True)
    assert "--boundary slide" in note
    assert share_notes(jtet.Options(), BOUNDARY_ONLY_SHARE) == []  # half is not most
    assert share_notes(jtet.Options(boundary="slide"), 1.0, True) == []
    # every tet good enough: no note, as for the others
    assert share_notes(jtet.Options(good_quality=float(q.min())), 1.0) == []


def _slab_without_interior_vertices() -> jtet.TetMesh:
    """Delaunay tets of two layers of 14 random points (the unit square's corners among
    them) at z = 0 and z = 0.2: every vertex lies on the slab's top or bottom face."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(3)
    corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
    pts = np.vstack(
        [np.column_stack([corners, np.full(4, z)]) for z in (0.0, 0.2)]
        + [np.column_stack([rng.random((10, 2)), np.full(10, z)]) for z in (0.0, 0.2)]
    )
    tets = Delaunay(pts).simplices.astype(np.int64)
    p = pts[tets]
    flip = np.linalg.det(p[:, 1:] - p[:, :1]) < 0
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    return jtet.TetMesh(pts, tets)


def test_improve_notes_an_input_without_interior_vertices(tmp_path):
    """A slab whose vertices all lie on its top and bottom faces: the run and the
    command say why its tets stay poor, and point to sliding (its faces are flat). The
    demo mesh (6 % of its tets without an interior vertex, some below good_quality after
    the run, so the notes are looked for) gets no such note."""
    m = _slab_without_interior_vertices()
    assert boundary_only_share(m) == (1.0, True)
    r = jtet.improve(m, perturb=0)
    assert r.stats_after.quality_min["biased_min_sine"] < 0.6
    (note,) = [n for n in r.notes if "of the input's tets" in n]
    assert note.startswith("100% of the input's tets") and "--boundary slide" in note
    src, out = tmp_path / "in.vtu", tmp_path / "out.vtu"
    jtet.save(m, src)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(io.StringIO()):
        assert main(["improve", str(src), str(out), "--perturb", "0"]) == 0
    assert "note: 100% of the input's tets" in stdout.getvalue()
    demo = jtet.improve(jtet.demo_mesh(), perturb=0)
    assert demo.stats_after.quality_min["biased_min_sine"] < 0.6
    assert not any("of the input's tets" in n for n in demo.notes)
