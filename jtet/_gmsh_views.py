"""Gmsh views saved with a mesh: ``$NodeData`` and ``$ElementData`` sections as point
and cell data.

A view is what Gmsh (``PostProcessing.SaveMesh``), meshio and many solvers write next to
the mesh in a ``.msh`` file: a name, a time step, and one value (or 3, or 9) per node or
per element, each keyed by its node or element number. Every time step is a section of
its own. jtet reads the last step of each view that gives a value to every node (point
data) or to every tet (cell data), and writes point and cell data back as views of one
step, over all the nodes and over the tets (the first elements of its files).

Node numbers come from the ``$Nodes`` section meshio reads. Element numbers meshio drops:
jtet's own readers of the ``$Elements`` section (``_gmsh_read``) keep the tets', in the
order jtet takes the tets (file order in MSH 2.2; entity blocks in MSH 4.1, ghost blocks
of a partitioned file left out).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._point_data import joined_columns, scalar_columns

#: the component counts a Gmsh view may have (scalar, vector, tensor)
_VIEW_COMPONENTS = (1, 3, 9)


@dataclasses.dataclass
class View:
    """One ``$NodeData`` / ``$ElementData`` section: a view at one time step."""

    kind: str  #: "point" ($NodeData) or "cell" ($ElementData)
    name: str
    step: int  #: time step index (the first integer tag)
    time: float  #: the first real tag (0 without one)
    numbers: np.ndarray  #: (k,) int64 node / element numbers
    values: np.ndarray  #: (k, c) float64


def read_view(f, tag: str, is_ascii: bool) -> View:
    """Parse the section ``tag`` ("NodeData" / "ElementData") from ``f``, just after its
    ``$NodeData`` line, up to its values (the caller skips to its end line). Raises
    ``ValueError`` for a header or values that do not parse."""
    strings = [_line(f).strip().strip('"') for _ in range(_tag_count(f))]
    reals = [float(_line(f)) for _ in range(_tag_count(f))]
    ints = [int(_line(f)) for _ in range(_tag_count(f))]
    if len(ints) < 3 or ints[1] < 1 or ints[2] < 0:
        raise ValueError(f"integer tags {ints}: no component and value counts")
    step, n_comp, n_items = ints[:3]
    # a damaged count must not ask for more memory than the file could fill (an ASCII
    # number takes at least 2 bytes with its separator)
    here = f.tell()
    left = f.seek(0, 2) - here
    f.seek(here)
    if n_items * (1 + n_comp) * (2 if is_ascii else 4) > left:
        raise ValueError(f"{n_items} values of {n_comp} components do not fit the file")
    if is_ascii:
        flat = np.fromfile(f, dtype=np.float64, count=n_items * (1 + n_comp), sep=" ")
        if len(flat) != n_items * (1 + n_comp):
            raise ValueError("fewer values than the header counts")
        rows = flat.reshape(n_items, 1 + n_comp)
        numbers, values = rows[:, 0], rows[:, 1:]
        if not np.array_equal(numbers, np.round(numbers)):
            raise ValueError("a node or element number is not an integer")
    else:
        dtype = np.dtype([("number", "<i4"), ("values", "<f8", (n_comp,))])
        rows = np.fromfile(f, dtype=dtype, count=n_items)
        if len(rows) != n_items:
            raise ValueError("fewer values than the header counts")
        numbers, values = rows["number"], rows["values"]
    return View(
        kind="point" if tag == "NodeData" else "cell",
        name=strings[0] if strings else f"{tag}_{step}",
        step=step,
        time=reals[0] if reals else 0.0,
        numbers=numbers.astype(np.int64),
        values=np.ascontiguousarray(values, dtype=np.float64).reshape(n_items, n_comp),
    )


def _line(f) -> str:
    return f.readline().decode("utf-8", "replace")


def _tag_count(f) -> int:
    """A count of string, real or integer tags (Gmsh writes at most a few)."""
    count = int(_line(f))
    if not 0 <= count <= 64:
        raise ValueError(f"{count} tags")
    return count


def view_data(
    views: list[View], node_numbers: np.ndarray | None, tets: np.ndarray | None
) -> tuple[dict, dict, list[str], list[str]]:
    """Point and cell data of a file's views: {name: (n,) or (n, c)} for the views whose
    last step gives a value to every node of ``node_numbers`` (n,) (point views) or to
    every tet numbered in ``tets`` (m,) (cell views), in
    that order (None: the numbers are unknown, and no view of that kind is read); views
    of one component named ``name[0]``, ``name[1]``, ... are joined
    (``scalar_columns``). Returns (point_data, cell_data, the views not read and why,
    the views read at the last of several time steps).
    """
    from ._io import _carried_array_name

    # (kind, name) -> step -> its sections: a step may come in several sections (one
    # per partition of a partitioned mesh, the fourth integer tag)
    by_step: dict = {}
    for v in views:
        if _carried_array_name(v.name):
            by_step.setdefault((v.kind, v.name), {}).setdefault(v.step, []).append(v)
    out: dict = {"point": {}, "cell": {}}
    not_read, last_steps = [], []
    for (kind, name), steps in by_step.items():
        sections = steps[max(steps)]
        wanted = node_numbers if kind == "point" else tets
        what = "nodes" if kind == "point" else "tets"
        if wanted is None:
            number = "node" if kind == "point" else "element"
            not_read.append(f"the {kind} view {name!r} (its {number} numbers could not be read)")
            continue
        if len({s.values.shape[1] for s in sections}) > 1:
            not_read.append(f"the {kind} view {name!r} (sections of one step differ in width)")
            continue
        numbers = np.concatenate([s.numbers for s in sections])
        rows = _rows_of(numbers, wanted)
        if rows is None:
            covered = int(np.isin(wanted, numbers).sum())
            not_read.append(
                f"the {kind} view {name!r} (values at {covered} of {len(wanted)} {what})"
            )
            continue
        values = np.concatenate([s.values for s in sections])[rows]
        out[kind][name] = values[:, 0] if values.shape[1] == 1 else values
        if len(steps) > 1:
            last_steps.append(
                f"the {kind} view {name!r} is read at the last of its {len(steps)} time "
                f"steps (time {sections[-1].time:g})"
            )
    return joined_columns(out["point"]), joined_columns(out["cell"]), not_read, last_steps


def _rows_of(numbers: np.ndarray, wanted: np.ndarray) -> np.ndarray | None:
    """Row of ``numbers`` holding each of ``wanted`` (the last, if one is listed twice),
    or None if some number of ``wanted`` is missing."""
    if len(numbers) == 0:
        return None if len(wanted) else np.zeros(0, np.int64)
    # a stable sort, reversed: among equal numbers the last row comes first
    order = np.argsort(numbers[::-1], kind="stable")
    order = len(numbers) - 1 - order
    sorted_numbers = numbers[order]
    at = np.minimum(np.searchsorted(sorted_numbers, wanted), len(numbers) - 1)
    if not np.array_equal(sorted_numbers[at], wanted):
        return None
    return order[at]


def write_views(fh, point_data: dict, cell_data: dict) -> None:
    """Append ``point_data`` (values at nodes 1..n) and ``cell_data`` (values at
    elements 1..m: the tets, written first) to the binary MSH 2.2 file open as ``fh``,
    one view of one time step each. Gmsh views hold 1, 3 or 9 components: other arrays
    go as their columns ``name[0]``, ``name[1]``, ..."""
    for tag, data in (("NodeData", point_data), ("ElementData", cell_data)):
        for name, values in _view_arrays(data).items():
            n_comp = values.shape[1]
            fh.write(f'${tag}\n1\n"{name}"\n1\n0\n3\n0\n{n_comp}\n{len(values)}\n'.encode())
            rows = np.empty(len(values), np.dtype([("n", "<i4"), ("v", "<f8", (n_comp,))]))
            rows["n"] = np.arange(1, len(values) + 1)
            rows["v"] = values
            fh.write(rows.tobytes())
            fh.write(f"\n$End{tag}\n".encode())


def _view_arrays(data: dict) -> dict:
    """{name: (n, c) float64} of ``data`` with c in 1, 3, 9; other arrays split into
    scalar columns. A quote in a name (which ends Gmsh's string tag) becomes ``'``."""
    out = {}
    for name, a in data.items():
        a = np.asarray(a, np.float64)
        name = str(name).replace('"', "'")
        if a.ndim == 2 and a.shape[1] in _VIEW_COMPONENTS:
            out[name] = a
        else:
            out.update({k: c[:, None] for k, c in scalar_columns({name: a}).items()})
    return out
