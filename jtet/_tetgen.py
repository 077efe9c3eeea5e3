"""TetGen files jtet reads and writes itself: the second-order ``.ele`` file
(``tetgen -o2``: 10-node tets), and the ``.node`` / ``.ele`` files of its output.

TetGen writes a tet's four corners, then the nodes of its edges in the order of its
edge table (``edge2ver`` read through ``orgpivot`` / ``destpivot``): the edges 23, 03,
01, 12, 13, 02 (``TETGEN_MID_EDGES``; checked against TetGen 1.6's own output in the
tests). All the edge nodes are numbered after the corners. Its ``.face`` file then
lists, after a face's corners a, b, c, the nodes of its edges ab, bc, ca (``outfaces``
and ``outsubfaces`` walk the face's edges from its origin; TetGen 1.6's own file
agrees): ``load`` drops them (they are the tets' nodes), ``save`` writes them.

``load(path, linear=True)`` reads such a file as its corners (``linear_copy``: a
4-node ``.ele`` beside a link to the ``.node`` file, for meshio), noting the edge nodes
with their edges for ``load`` to drop them or keep them as curved edges.
``save`` writes TetGen files itself (``write_tetgen``), with 10-node tets for
``quadratic=True``.
"""

from __future__ import annotations

import os
import re
import shutil
import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError
from ._quadratic import vtk_edge_columns

# the comment line of a ``.node`` file that names its attribute columns (meshio's)
NAMES_COMMENT = "# attribute and marker names:"
# corner pairs of the edge nodes of a TetGen 10-node tet, in the file's order
TETGEN_MID_EDGES = np.array([[2, 3], [0, 3], [0, 1], [1, 2], [1, 3], [0, 2]])
# for each of TetGen's edge nodes, its column among VTK's
_VTK_COLUMN = vtk_edge_columns(TETGEN_MID_EDGES)


def _numbers(path: Path) -> np.ndarray:
    """Every number of a TetGen file (comments blanked), in one C-level parse: int64
    when they all are integers, else float64 (exact for ids below 2**53; the integer
    parse is 8 times faster: 8M numbers 0.19 s); ``MeshFileError`` for a word among
    them."""
    try:
        text = re.sub(r"#[^\n]*", " ", path.read_text(errors="replace"))
    except OSError as e:
        raise MeshFileError(f"{path}: cannot read ({e.strerror or e})") from None
    for dtype in (np.int64, np.float64):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # np.fromstring warns and stops at a word
            try:
                return np.fromstring(text, dtype=dtype, sep=" ")
            except (ValueError, DeprecationWarning):
                pass  # a decimal number for the integers; a word for both
    raise MeshFileError(f"{path}: not a readable TetGen file (a word among its numbers)")


def _node_count_and_base(node: Path) -> tuple[int, int]:
    """(number of nodes, number of the first node: 0 or 1, the base of every id in the
    ``.ele`` and ``.face`` files) of the TetGen ``.node`` file, from its first two lines
    that hold more than a comment."""
    lines = []
    try:
        with open(node, errors="replace") as f:
            for line in f:
                data = line.split("#")[0].split()
                if data:
                    lines.append(data)
                if len(lines) == 2:
                    break
    except OSError as e:
        raise MeshFileError(f"{node}: cannot read ({e.strerror or e})") from None
    try:
        return int(lines[0][0]), int(float(lines[1][0]))
    except (IndexError, ValueError):
        raise MeshFileError(f"{node}: not a readable TetGen node file") from None


def _quadratic_table(ele: Path) -> tuple[np.ndarray, int]:
    """(rows (m, 11 + k): number, 10 node ids, k attributes; k) of the TetGen ``.ele``
    file of 10-node tets ``ele``."""
    values = _numbers(ele)
    if len(values) < 3:
        raise MeshFileError(f"{ele}: not a readable TetGen element file (no header)")
    count, n_attributes = int(values[0]), int(values[2])
    width = 11 + n_attributes
    if count < 0 or n_attributes < 0 or len(values) - 3 != count * width:
        raise MeshFileError(
            f"{ele}: not a readable TetGen element file ({count} elements of 10 nodes and "
            f"{n_attributes} attribute(s) announced, {len(values) - 3} numbers read)"
        )
    rows = values[3:].reshape(count, width)
    if (rows[:, :11] != np.round(rows[:, :11])).any():
        raise MeshInputError(f"{ele}: an element number or node id is no integer")
    return rows, n_attributes


def linear_copy(ele: Path, directory: Path) -> Path:
    """The ``.node`` path of a linear copy of the TetGen mesh whose ``.ele`` file
    ``ele`` holds 10-node tets, made in ``directory`` (the caller removes it): the
    ``.ele`` file of their corners and attributes, and a link to (or copy of) the
    ``.node`` file. The edge nodes are noted with their edges (``note_mid_nodes``).

    TetGen 1.6's ``-o2`` writes ids that are no node for some of its first tet's edge
    nodes. A tet whose edge node ids are out of the ``.node`` file's range, or are a
    tet's corner, gets its corners read and its edge nodes ignored, with a warning: the
    nodes of its edges are those the other tets around them list.
    """
    from ._io import _check_tetgen_attributes, format_rows, note_mid_nodes

    node = ele.with_suffix(".node")
    n_nodes, base = _node_count_and_base(node)
    rows, n_attributes = _quadratic_table(ele)
    attributes = rows[:, 11:]
    if (attributes != np.round(attributes)).any():
        _check_tetgen_attributes(ele)  # says which element and what its attribute is
    ids = rows[:, 1:11].astype(np.int64) - base
    corners, mids = ids[:, :4], ids[:, 4:]
    if len(corners) and (corners.min() < 0 or corners.max() >= n_nodes):
        bad = int(np.flatnonzero(((corners < 0) | (corners >= n_nodes)).any(axis=1))[0])
        raise MeshInputError(
            f"{ele}: element {int(rows[bad, 0])} has a corner that is no node of the "
            f"{n_nodes} in {node.name}"
        )
    is_corner = np.zeros(n_nodes, bool)
    is_corner[corners.reshape(-1)] = True
    wrong = ((mids < 0) | (mids >= n_nodes)).any(axis=1)
    wrong[~wrong] = is_corner[mids[~wrong]].any(axis=1)
    if wrong.any():
        numbers = ", ".join(str(int(k)) for k in rows[wrong, 0][:5])
        warnings.warn(
            f"{ele}: {int(wrong.sum())} element(s) ({numbers}) list edge node ids that are no "
            "edge node (TetGen 1.6's -o2 writes such ids for its first element): their "
            "corners are read, and their edges keep the nodes the other elements list",
            stacklevel=4,
        )
    note_mid_nodes(mids[~wrong], corners[~wrong][:, TETGEN_MID_EDGES])
    table = np.column_stack(
        [rows[:, 0].astype(np.int64), corners + base, attributes.astype(np.int64)]
    )
    out = directory / "linear.ele"
    with open(out, "w") as f:
        f.write(f"{len(rows)} 4 {n_attributes}\n")
        f.write(format_rows(table, "%d" + " %d" * (table.shape[1] - 1) + "\n"))
    linked = directory / "linear.node"
    try:
        os.symlink(node.resolve(), linked)
    except OSError:  # a file system without links
        shutil.copyfile(node, linked)
    return linked


def write_tetgen(
    node: Path,
    points: np.ndarray,
    point_data: dict,
    tets: np.ndarray,
    region: np.ndarray,
) -> None:
    """The TetGen ``.node`` file at ``node`` and the ``.ele`` file beside it, numbered
    from 0: ``points`` (n, 3) with ``point_data`` (arrays over the n points) as float
    attribute columns named in a comment line (``_io._tetgen_point_data`` reads them
    back) and a boundary marker column of zeros; ``tets`` (m, 4), or (m, 10) in VTK's
    order (``_quadratic.QuadraticMesh.tets``, written in TetGen's ``-o2`` order), with
    ``region`` (m,) as their attribute. Every number in one C-level formatting per file
    (meshio's writer formats row by row: 757k nodes 2-6 s); coordinates with 17
    significant digits, as TetGen writes them, so they read back exactly."""
    from ._io import format_rows
    from ._point_data import scalar_columns

    points = np.asarray(points, np.float64)
    columns = scalar_columns(point_data)
    names = [*columns, "tetgen:ref"] if columns else []
    # with attributes, a boundary marker column (of zeros) after them: without one a
    # reader may take the last attribute for the markers
    markers = [np.zeros(len(points))] if columns else []
    table = np.column_stack([np.arange(len(points)), points, *columns.values(), *markers])
    fmt = "%d" + " %.17g" * (3 + len(columns)) + (" %d" if columns else "") + "\n"
    with open(node, "w") as f:
        f.write(
            "# nodes: id, x, y, z" + (", attributes, boundary marker" if columns else "") + "\n"
        )
        if names:
            f.write(f"{NAMES_COMMENT} {', '.join(names)}\n")
        f.write(f"{len(points)} 3 {len(columns)} {int(bool(columns))}\n")
        f.write(format_rows(table, fmt))
    tets = np.asarray(tets, np.int64)
    if tets.shape[1] == 10:
        tets = np.concatenate([tets[:, :4], tets[:, 4 + _VTK_COLUMN]], axis=1)
    table = np.column_stack([np.arange(len(tets)), tets, np.asarray(region, np.int64)])
    with open(node.with_suffix(".ele"), "w") as f:
        if tets.shape[1] == 10:
            f.write("# 10-node tets: id, 4 corners, the nodes of edges 23 03 01 12 13 02, region\n")
        else:
            f.write("# tets: id, 4 corners, region\n")
        f.write(f"{len(tets)} {tets.shape[1]} 1\n")
        f.write(format_rows(table, "%d" + " %d" * (tets.shape[1] + 1) + "\n"))
