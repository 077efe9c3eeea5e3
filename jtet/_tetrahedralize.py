"""Tetrahedral meshes of surfaces, made by fTetWild (``pytetwild``): where a user has only
a surface (an STL of a part, a segmented organ, a CAD export), the mesh to improve.

fTetWild (Hu et al., "Fast Tetrahedral Meshing in the Wild") meshes triangle soups: open,
self-intersecting or non-manifold surfaces too. It keeps the output's boundary within
``epsilon`` (relative to the bounding box's diagonal) of the input surface and keeps
what the surface's winding number puts inside. Its output is already optimized for its
own energy (AMIPS), not for dihedral angles: ``jtet improve`` then raises the worst tets.
fTetWild runs in a child process (``_ftetwild``): it writes a scratch file into its
working directory (the child's is a temporary one), and a crash of its C++ code on a
strange surface becomes a clear error instead of taking the caller's process down.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError
from ._mesh import TetMesh

#: File extensions ``read_surface`` reads (OFF by ``_read_off``, the others through
#: pyvista); a ``.vtk`` / ``.vtp`` may hold a volume grid, whose boundary is taken.
SURFACE_EXTENSIONS = (".stl", ".obj", ".ply", ".off", ".vtp", ".vtk")

#: fTetWild's defaults, relative to the surface's bounding box diagonal: the target edge
#: length and the envelope (shared by ``tetrahedralize`` and ``jtet tetrahedralize``)
EDGE_LENGTH_FAC, EPSILON = 0.05, 1e-3


def _surface_here(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of the surface file ``path``, read in this process."""
    if path.suffix.lower() == ".off":
        return _read_off(path)
    import pyvista as pv

    from ._io import _clean, _vtk_capture

    with _vtk_capture() as errors, warnings.catch_warnings(record=True) as caught:
        # pyvista reports its readers' failures as warnings: they mean an unreadable file.
        # Its others (a point array of the wrong length in a damaged file) are about data
        # that is not read
        warnings.simplefilter("always")
        data = pv.read(str(path))
        errs = errors() + [
            _clean(str(w.message).splitlines()[0]) for w in caught if "error" in str(w.message)
        ]
        if errs:
            raise MeshFileError(f"{path}: not a readable surface file ({errs[0]})")
        if not isinstance(data, pv.PolyData):
            if not hasattr(data, "extract_surface"):
                raise MeshFileError(f"{path}: holds a {type(data).__name__}, not a surface")
            data = data.extract_surface()
        return _polydata_triangles(data)


def _read_off(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of an ASCII OFF file: ``OFF``, the vertex, face and edge
    counts, a line of 3 coordinates per vertex, a line per face (its vertex count, its
    vertex ids, maybe a colour); ``#`` starts a comment. Polygons are split into fans.
    (meshio's reader loops forever on a file cut short after its header.)"""
    import re

    text = re.sub(rb"#[^\n]*", b"", path.read_bytes())
    fast = _read_off_triangles(text)
    if fast is not None:
        return fast
    lines = [ln.split() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines or lines[0][0] != b"OFF":
        raise MeshFileError(f"{path}: not an OFF file (its first word is not OFF)")
    head = lines[0][1:] or (lines[1] if len(lines) > 1 else [])
    body = lines[1:] if lines[0][1:] else lines[2:]
    try:
        n_verts, n_faces = int(head[0]), int(head[1])
        if n_verts < 0 or n_faces < 0 or len(body) < n_verts + n_faces:
            raise ValueError(f"{len(body)} data lines for {n_verts} vertices, {n_faces} faces")
        points = np.array([ln[:3] for ln in body[:n_verts]], dtype=np.float64).reshape(-1, 3)
        faces = body[n_verts : n_verts + n_faces]
        sizes = np.array([int(f[0]) for f in faces], np.int64)
        if (sizes < 3).any() or any(len(f) <= k for f, k in zip(faces, sizes, strict=True)):
            raise ValueError("a face with fewer than 3 vertices or fewer ids than its count")
        flat = np.array(
            [v for f, k in zip(faces, sizes, strict=True) for v in f[1 : k + 1]], dtype=np.int64
        )
    except (ValueError, IndexError) as e:
        raise MeshFileError(f"{path}: not a readable OFF file ({e})") from None
    # a fan of triangles (0, j, j + 1) of each polygon, in the faces' order: polygon f's
    # ids start at start[f] in ``flat``, its triangles j = 1 .. sizes[f] - 2
    start = np.cumsum(sizes) - sizes
    fans = sizes - 2
    first = np.repeat(start, fans)
    j = np.arange(int(fans.sum())) - np.repeat(np.cumsum(fans) - fans, fans) + 1
    return points, np.stack([flat[first], flat[first + j], flat[first + j + 1]], axis=1)


def _read_off_triangles(text: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """``_read_off`` of an OFF file (comments removed) of triangles without colours, by
    whole-file token arrays (1M triangles: 0.9 s instead of 4.6 s line by line); None
    for any other file."""
    tokens = text.split()
    try:
        n_verts, n_faces = int(tokens[1]), int(tokens[2])
    except (IndexError, ValueError):
        return None
    if tokens[0] != b"OFF" or n_verts < 0 or len(tokens) != 4 + 3 * n_verts + 4 * n_faces:
        return None
    try:
        points = np.array(tokens[4 : 4 + 3 * n_verts], dtype=np.float64).reshape(-1, 3)
        faces = np.array(tokens[4 + 3 * n_verts :], dtype=np.int64).reshape(-1, 4)
    except ValueError:
        return None
    return (points, faces[:, 1:]) if (faces[:, 0] == 3).all() else None


def _polydata_triangles(data) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float64, triangles (k, 3) int64) of a ``pyvista.PolyData``: its
    polygons and strips split into triangles (lines and vertices bound no volume)."""
    data = data.triangulate()
    faces = np.asarray(data.faces, np.int64).reshape(-1, 4)  # (3, a, b, c) rows
    return np.asarray(data.points, np.float64), faces[:, 1:]


def read_surface(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangulated surface: (points (n, 3) float64, triangles (k, 3) int64).

    ``.stl``, ``.obj``, ``.ply``, ``.vtp``, ``.vtk`` (VTK's readers, in a forked child:
    some take their process down on a damaged file) and ``.off``. Polygons are split
    into triangles; a volume grid gives its boundary surface.

    Raises:
        MeshFileError: a missing, unreadable or damaged file, or another extension.
    """
    from ._io import _reason

    p = Path(path)
    if p.suffix.lower() not in SURFACE_EXTENSIONS:
        raise MeshFileError(
            f"{p}: unknown surface file extension {p.suffix or '(none)'!r}; jtet reads "
            f"surfaces from {', '.join(SURFACE_EXTENSIONS)}"
        )
    if not p.is_file():
        raise MeshFileError(f"{p}: no such file")

    def read():
        try:
            return _surface_here(p)
        except MeshFileError:
            raise
        except Exception as e:
            raise MeshFileError(f"{p}: not a readable surface file ({_reason(e)})") from None

    from ._forked import call_in_child, can_fork

    if not can_fork() or p.suffix.lower() == ".off":  # Python and NumPy: no crash
        return read()
    return call_in_child(
        read,
        lambda how: MeshFileError(
            f"{p}: not a readable surface file (VTK's reader {how}: the file is damaged)"
        ),
    )


def check_surface(points, triangles, source: str = "surface") -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float64, triangles (k, 3) int64) checked for fTetWild.

    Raises:
        MeshInputError: wrong shapes, non-finite coordinates, indices out of range, fewer
            than 4 triangles, or all points in one plane.
    """
    pts = np.asarray(points)
    tris = np.asarray(triangles)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
        raise MeshInputError(f"{source}: points must be an (n, 3) array, got {pts.shape}")
    if tris.ndim != 2 or tris.shape[1] != 3 or not np.issubdtype(tris.dtype, np.integer):
        raise MeshInputError(
            f"{source}: triangles must be a (k, 3) integer array, got {tris.shape} {tris.dtype}"
        )
    pts = pts.astype(np.float64)
    tris = tris.astype(np.int64)
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise MeshInputError(
            f"{source}: {int(bad.sum())} point(s) with NaN or infinite coordinates "
            f"(first: point {int(np.flatnonzero(bad)[0])})"
        )
    if len(tris) < 4:
        raise MeshInputError(
            f"{source}: {len(tris)} triangle(s); a surface around a volume has at least 4"
        )
    if tris.min() < 0 or tris.max() >= len(pts):
        raise MeshInputError(
            f"{source}: triangle vertex ids must be in 0..{len(pts) - 1}, found "
            f"{int(tris.min())}..{int(tris.max())}"
        )
    from ._driver import MAX_EXTENT, MIN_EXTENT

    used = pts[np.unique(tris)]
    extent = float(np.ptp(used, axis=0).max())
    if not MIN_EXTENT <= extent <= MAX_EXTENT:
        raise MeshInputError(
            f"{source}: the surface spans {extent:.3g} length units; jtet needs extents in "
            f"[{MIN_EXTENT:g}, {MAX_EXTENT:g}] (the mesh's quality is float64): rescale it"
        )
    # the smallest singular value against the largest (of the spread scaled to ~1, which
    # cannot overflow): 0 for points in one plane
    sv = np.linalg.svd((used - used.mean(axis=0)) / extent, compute_uv=False)
    if sv[-1] <= 1e-12 * sv[0]:
        raise MeshInputError(f"{source}: all points lie in one plane (or line): no volume")
    return pts, tris


def open_edges(triangles: np.ndarray) -> int:
    """How many edges of ``triangles`` (k, 3) are not shared by exactly two of them (0
    for a closed manifold surface)."""
    e = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    _, count = np.unique(e, axis=0, return_counts=True)
    return int((count != 2).sum())


# The child's program: the surface from surface.npz in its working directory, fTetWild's
# mesh to tets.npz. It imports NumPy and pytetwild only (not jtet, not JAX).
_FTETWILD_CHILD = """
import json, sys
import numpy as np
import pytetwild
surface = np.load("surface.npz")
points, tets = pytetwild.tetrahedralize(
    surface["points"], surface["triangles"], vtk_ordering=True, quiet=True,
    **json.loads(sys.argv[1]),
)
np.savez("tets.npz", points=np.asarray(points, np.float64), tets=np.asarray(tets, np.int64))
"""


def _ftetwild(points, triangles, settings: dict, source: str) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild's (points (n, 3) float64, tets (m, 4) int64) of the surface, run in a
    new Python process whose working directory is a temporary one (fTetWild writes a
    scratch file there).

    A new process, not a fork of this one: fTetWild runs on TBB's thread pool, and a
    fork of a process whose pool exists (pytetwild called here before) inherits a pool
    without threads, where the child waited forever (seen in the test suite). It costs
    ~0.2 s to start.

    Raises:
        MeshInputError: fTetWild failed or crashed (the message says which).
    """
    import json
    import signal
    import subprocess
    import sys

    from ._io import _clean

    with tempfile.TemporaryDirectory(prefix="jtet-ftetwild-") as tmp:
        np.savez(Path(tmp) / "surface.npz", points=points, triangles=triangles.astype(np.int32))
        proc = subprocess.run(
            [sys.executable, "-c", _FTETWILD_CHILD, json.dumps(settings)],
            cwd=tmp,
            capture_output=True,
            text=True,
            errors="replace",
        )
        if proc.returncode == 0:
            with np.load(Path(tmp) / "tets.npz") as out:
                return out["points"], out["tets"].reshape(-1, 4)
    if proc.returncode < 0:
        how = f"crashed with {signal.Signals(-proc.returncode).name}"
    else:
        lines = proc.stderr.strip().splitlines()
        how = f"failed ({_clean(lines[-1]) if lines else f'exit code {proc.returncode}'})"
    raise MeshInputError(f"{source}: fTetWild {how} on this surface")


def tetrahedralize(
    surface,
    *,
    edge_length: float | None = None,
    edge_length_fac: float = EDGE_LENGTH_FAC,
    epsilon: float = EPSILON,
    optimize: bool = True,
    threads: int = 0,
) -> TetMesh:
    """A tetrahedral mesh of the volume a surface bounds, made by fTetWild.

    Args:
        surface: a surface file (``read_surface``), a ``pyvista.PolyData`` or a pair
            (points (n, 3), triangles (k, 3)).
        edge_length: target edge length in the surface's units; None: ``edge_length_fac``
            times the diagonal of the surface's bounding box.
        edge_length_fac: target edge length relative to the bounding box's diagonal
            (fTetWild's default 0.05).
        epsilon: how far the mesh's boundary may lie from the surface, relative to the
            bounding box's diagonal (fTetWild's envelope; default 1e-3).
        optimize: run fTetWild's own optimization (False: its raw output, with flat and
            very poor tets, much faster).
        threads: fTetWild's threads (0: all cores). fTetWild's output differs from run to
            run even on one thread: save it, and improve the saved mesh, for runs that
            can be repeated.

    Returns:
        The mesh, positively oriented, with no protected entities and one region
        labelled 1: a Gmsh physical volume (solvers that read Gmsh files, dolfinx's
        among them, take their cells from physical groups, and tag 0 is none), a Medit
        reference, a TetGen region attribute.

    Raises:
        MeshFileError: an unreadable surface file.
        MeshInputError: a surface with no volume (``check_surface``), settings out of
            range, or fTetWild failing on it (its crash included).
    """
    if isinstance(surface, str | os.PathLike):
        source = str(surface)
        points, triangles = read_surface(surface)
    elif hasattr(surface, "faces") and hasattr(surface, "points"):  # pyvista.PolyData
        source = "surface"
        points, triangles = _polydata_triangles(surface)
    else:
        source = "surface"
        try:
            points, triangles = surface
        except (TypeError, ValueError):
            raise MeshInputError(
                "surface must be a file name, a pyvista.PolyData or (points, triangles)"
            ) from None
    points, triangles = check_surface(points, triangles, source)
    for name, value, lo, hi in (
        ("edge_length_fac", edge_length_fac, 0.0, 1.0),
        ("epsilon", epsilon, 0.0, 1.0),
    ):
        if not (np.isfinite(value) and lo < value <= hi):
            raise MeshInputError(f"{name} must be in ({lo:g}, {hi:g}], got {value!r}")
    if edge_length is not None and not (np.isfinite(edge_length) and edge_length > 0):
        raise MeshInputError(f"edge_length must be positive, got {edge_length!r}")
    if int(threads) != threads or threads < 0:
        raise MeshInputError(f"threads must be a whole number >= 0, got {threads!r}")
    settings = {
        "edge_length_fac": float(edge_length_fac),
        "edge_length_abs": None if edge_length is None else float(edge_length),
        "epsilon": float(epsilon),
        "optimize": bool(optimize),
        "num_threads": int(threads),
    }

    tet_points, tets = _ftetwild(points, triangles, settings, source)
    if not len(tets):
        raise MeshInputError(
            f"{source}: fTetWild made no tets: does the surface enclose a volume? "
            f"({open_edges(triangles)} open edge(s))"
        )
    used, tets = np.unique(tets, return_inverse=True)
    tets = tets.reshape(-1, 4)
    return TetMesh.from_arrays(
        tet_points[used], tets, np.ones(len(tets), np.int64), source=f"fTetWild({source})"
    )
