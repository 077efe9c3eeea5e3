"""Mends to meshio 5.3's Gmsh readers, applied for the length of one read.

meshio refuses several kinds of files that Gmsh writes every day, for reasons that do not
concern jtet (which reads points, tets, triangles, their tags and the data views):

* 4.1 files whose element blocks are not all in physical groups (``Mesh.SaveAll = 1``):
  ``_physical_for_every_block``;
* files with node or element data (a view saved with its mesh), which jtet reads as
  point and cell data (``_gmsh_views``) keyed by the node numbers and the tets' element
  numbers meshio drops: ``_read_data``;
* partitioned 4.1 files (``gmsh -part N``, ``Mesh.NbPartitions``), whose elements sit on
  partition entities that meshio does not read: ``_Partitions``.

The ``$Elements`` sections are read by jtet's own functions, which give meshio's output
and keep the element numbers it drops (``_read_elements41``, ``_read_cells22``). The
2.2 ones read a section whole instead of element by element (``ascii22_blocks``,
``binary22_blocks``): a 1M-tet binary 2.2 file as Gmsh writes it, with a header before
every element, took meshio 28 s.

``gmsh_read_mends()`` swaps meshio's functions for the mended ones and restores them on
exit; reads in other threads wait.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import itertools
import threading

import numpy as np

_GMSH_READ = threading.Lock()


def _msh41_reader(is_ascii: bool, data_size) -> tuple:
    """(fromfile, size_t, c_int) for the sections of an MSH 4.1 file: ``np.fromfile``
    reading text or binary as the file is, and its two integer types."""
    fromfile = functools.partial(np.fromfile, sep=" " if is_ascii else "")
    return fromfile, np.dtype(f"u{int(data_size)}"), np.dtype("i")


@dataclasses.dataclass
class _Partitions:
    """The ``$PartitionedEntities`` section of a partitioned Gmsh 4.1 file.

    Gmsh puts every element of a partitioned mesh on a partition entity: a piece of a
    model entity (its parent) in one partition, or a new entity on the interface between
    partitions (whose parent is of higher dimension). The tets, read by their parents,
    are the whole mesh with its volumes; interface triangles are no model surface and are
    dropped, as are ghost elements (copies of the neighbouring partitions' tets).
    """

    #: (dim, tag) of each partition entity -> (parent dim, parent tag)
    parents: dict = dataclasses.field(default_factory=dict)
    #: per dim: tag -> physical tags, tag -> bounding entities (meshio's own tables)
    physicals: tuple = ({}, {}, {}, {})
    bounding: tuple = ({}, {}, {}, {})
    ghosts: frozenset = frozenset()

    @classmethod
    def read(cls, f, is_ascii: bool, data_size: int) -> _Partitions:
        """Parse the section from ``f`` (just after its ``$PartitionedEntities`` line) up
        to and including ``$EndPartitionedEntities``."""
        from meshio.gmsh.common import _fast_forward_to_end_block

        fromfile, size_t, c_int = _msh41_reader(is_ascii, data_size)
        c_double = np.dtype("d")

        def count() -> int:
            return int(fromfile(f, size_t, 1)[0])

        out = cls()
        count()  # number of partitions
        n_ghosts = count()
        out.ghosts = frozenset(fromfile(f, c_int, 2 * n_ghosts)[::2].tolist())
        for dim, n in enumerate(fromfile(f, size_t, 4).tolist()):
            for _ in range(n):
                tag, parent_dim, parent_tag = fromfile(f, c_int, 3).tolist()
                fromfile(f, c_int, count())  # its partitions
                fromfile(f, c_double, 3 if dim == 0 else 6)  # point or bounding box
                out.physicals[dim][tag] = fromfile(f, c_int, count()).tolist()
                if dim > 0:
                    out.bounding[dim][tag] = fromfile(f, c_int, count())
                out.parents[dim, tag] = (parent_dim, parent_tag)
        _fast_forward_to_end_block(f, "PartitionedEntities")
        return out

    def tables(self, physical_tags, bounding_entities):
        """meshio's per-dim entity tables with the partition entities added."""
        physical_tags = physical_tags or ({}, {}, {}, {})
        bounding_entities = bounding_entities or ({}, {}, {}, {})
        return (
            tuple({**a, **b} for a, b in zip(physical_tags, self.physicals, strict=True)),
            tuple({**a, **b} for a, b in zip(bounding_entities, self.bounding, strict=True)),
        )

    def to_parents(self, cells, cell_data, cell_sets, numbers):
        """meshio's element blocks without interface and ghost blocks, each with its
        parent entity as ``gmsh:geometrical``; ``numbers``: the blocks' element
        numbers, kept likewise."""
        entities = cell_data["gmsh:geometrical"]
        keep, parents = [], []
        for block, tags in zip(cells, entities, strict=True):
            tag = int(tags[0]) if len(tags) else 0
            parent_dim, parent_tag = self.parents.get((block.dim, tag), (block.dim, tag))
            ghost = block.dim == 3 and tag in self.ghosts
            keep.append(parent_dim == block.dim and not ghost)
            parents.append(np.full(len(tags), parent_tag, tags.dtype))
        cell_data["gmsh:geometrical"] = parents

        def kept(blocks: list) -> list:
            return [b for b, k in zip(blocks, keep, strict=True) if k]

        return (
            kept(cells),
            {name: kept(arrays) for name, arrays in cell_data.items()},
            {name: kept(s) if len(s) == len(cells) else s for name, s in cell_sets.items()},
            kept(numbers),
        )


def binary22_blocks(f, total: int) -> list[tuple[int, int, np.ndarray]]:
    """The element blocks of a binary MSH 2.2 ``$Elements`` section whose ``total``
    elements start at ``f``'s position (after the count line): (Gmsh element type,
    number of tags, rows (k, 1 + tags + nodes) int32: number, tags, nodes), in file
    order; ``f`` is left just after them. Raises ``ValueError`` for a section that
    does not hold ``total`` elements of known types.

    Gmsh writes a header before every element of such a file (type, 1, number of tags):
    read header by header, as meshio 5.3 does, a 1M-tet file took 26 s. Here a run of
    identical one-element headers is one strided view (0.2 s)."""
    from meshio._common import num_nodes_per_cell
    from meshio.gmsh.common import _gmsh_to_meshio_type

    start = f.tell()
    raw = f.read()
    ints = np.frombuffer(raw, dtype=np.intc, count=len(raw) // 4)
    blocks, pos, done = [], 0, 0
    while done < total:
        if pos + 3 > len(ints):
            raise ValueError(f"the elements end after {done} of {total}")
        kind, count, n_tags = (int(x) for x in ints[pos : pos + 3])
        if kind not in _gmsh_to_meshio_type or count < 1 or n_tags < 0:
            raise ValueError(f"an element header reads type {kind}, {count} elements")
        width = 1 + n_tags + num_nodes_per_cell[_gmsh_to_meshio_type[kind]]
        if count > 1:
            end = pos + 3 + count * width
            if end > len(ints):
                raise ValueError(f"the elements end after {done} of {total}")
            blocks.append((kind, n_tags, ints[pos + 3 : end].reshape(count, width)))
            pos, done = end, done + count
            continue
        # a run of one-element blocks with this same header: windows growing 4x, so a
        # run costs time in its length (a file of alternating headers stays linear)
        stride, window = 3 + width, 64
        limit = min(total - done, (len(ints) - pos) // stride)
        if limit == 0:
            raise ValueError(f"the elements end after {done} of {total}")
        while True:
            seen = min(window, limit)
            heads = ints[pos : pos + seen * stride].reshape(seen, stride)[:, :3]
            same = np.all(heads == heads[0], axis=1)
            if not same.all():
                run = int(np.argmin(same))
                break
            run = seen
            if seen == limit:
                break
            window *= 4
        rows = ints[pos : pos + run * stride].reshape(run, stride)[:, 3:]
        blocks.append((kind, n_tags, rows))
        pos, done = pos + run * stride, done + run
    f.seek(start + 4 * pos)
    return blocks


def ascii22_blocks(f, total: int) -> list[tuple[int, int, np.ndarray]]:
    """``binary22_blocks`` for an ASCII MSH 2.2 ``$Elements`` section: its ``total``
    element lines (``number type n_tags tags... nodes...``) as blocks of consecutive
    lines of one type and tag count, rows (k, 1 + tags + nodes) int64. Raises
    ``ValueError`` for a line that is not such a line of integers.

    meshio 5.3 parses line by line in Python (5.5 s for 1M tets); here the lines' tokens
    are parsed at once and each line's first token found from the whitespace."""
    from meshio._common import num_nodes_per_cell
    from meshio.gmsh.common import _gmsh_to_meshio_type

    if total == 0:
        return []
    text = b"".join(itertools.islice(f, total))
    values = np.fromstring(text, dtype=np.int64, sep=" ")
    chars = np.frombuffer(text, np.uint8)
    space = np.isin(chars, np.frombuffer(b" \t\r\n", np.uint8))
    token_starts = np.flatnonzero(~space & np.concatenate([[True], space[:-1]]))
    line_starts = np.concatenate([[0], np.flatnonzero(chars == ord("\n"))[:-1] + 1])
    if len(token_starts) != len(values) or len(line_starts) != total:
        raise ValueError(f"the {total} element lines hold something other than integers")
    first = np.searchsorted(token_starts, line_starts)  # each line's first token
    width = np.diff(np.append(first, len(values)))  # tokens per line
    if width.min() < 3:
        raise ValueError("an element line holds fewer than 3 numbers")
    kind, n_tags = values[first + 1], values[first + 2]
    known = np.array(sorted(_gmsh_to_meshio_type))
    nodes_of = np.array([num_nodes_per_cell[_gmsh_to_meshio_type[k]] for k in known])
    at = np.minimum(np.searchsorted(known, kind), len(known) - 1)
    if not np.array_equal(known[at], kind) or not np.array_equal(width, 3 + n_tags + nodes_of[at]):
        raise ValueError("an element line's type or tag count does not match its length")
    # runs of consecutive lines of one type and tag count: one (k, width) block each
    cut = np.flatnonzero((np.diff(kind) != 0) | (np.diff(n_tags) != 0)) + 1
    blocks = []
    for a, b in zip(np.r_[0, cut], np.r_[cut, total], strict=True):
        rows = values[first[a] : first[a] + (b - a) * width[a]].reshape(b - a, width[a])
        blocks.append((int(kind[a]), int(n_tags[a]), np.delete(rows, (1, 2), axis=1)))
    return blocks


def _read_cells22(f, cells, point_tags, is_ascii, tet_numbers: list | None = None):
    """meshio 5.3's ``_gmsh22._read_cells`` (same output: ``cells`` filled in place,
    returns (has_additional_tag_data, {"gmsh:physical" / "gmsh:geometrical": {type:
    tags}})), on ``ascii22_blocks`` / ``binary22_blocks``: no loop over elements.
    ``tet_numbers``: a list that gets the element numbers of the tets, block by block
    (for the views, ``_gmsh_views``)."""
    from meshio.gmsh.common import (
        _fast_forward_to_end_block,
        _gmsh_to_meshio_order,
        _gmsh_to_meshio_type,
    )

    total = int(f.readline().decode())
    blocks = (ascii22_blocks if is_ascii else binary22_blocks)(f, total)
    point_tags = np.asarray(point_tags, dtype=np.int64) - 1
    remap = -np.ones(int(point_tags.max()) + 1, dtype=np.int64)
    remap[point_tags] = np.arange(len(point_tags))
    parts: list = []  # [type, [node arrays]] per run of one type, as meshio merges them
    tags: dict = {"gmsh:physical": {}, "gmsh:geometrical": {}}
    extra = False
    for kind, n_tags, rows in blocks:
        name = _gmsh_to_meshio_type[kind]
        if not parts or parts[-1][0] != name:
            parts.append((name, []))
        parts[-1][1].append(rows[:, 1 + n_tags :])
        if tet_numbers is not None and name == "tetra":
            tet_numbers.append(rows[:, 0].astype(np.int64))
        for column, key in ((1, "gmsh:physical"), (2, "gmsh:geometrical")):
            if n_tags >= column:
                tags[key].setdefault(name, []).append(rows[:, column])
        extra |= n_tags > 2
    for name, nodes in parts:
        cells.append((name, remap[_gmsh_to_meshio_order(name, np.vstack(nodes) - 1)]))
    _fast_forward_to_end_block(f, "Elements")
    out = {
        key: {name: np.concatenate(t).astype(np.intc) for name, t in by_type.items()}
        for key, by_type in tags.items()
        if by_type
    }
    return extra, out


def _read_elements41(
    f, point_tags, physical_tags, bounding_entities, is_ascii, data_size, field_data
):
    """meshio 5.3's ``_gmsh41._read_elements`` (the same (cells, cell_data, cell_sets)),
    and the element numbers of each block, which meshio drops (for the views,
    ``_gmsh_views``): returns (cells, cell_data, cell_sets, numbers), numbers[k] the
    (n_k,) int64 element numbers of block k."""
    from meshio import CellBlock
    from meshio._common import num_nodes_per_cell
    from meshio.gmsh.common import (
        _fast_forward_to_end_block,
        _gmsh_to_meshio_order,
        _gmsh_to_meshio_type,
    )

    fromfile, size_t, c_int = _msh41_reader(is_ascii, data_size)
    n_blocks = int(fromfile(f, size_t, 4)[0])
    cell_sets = {name: [None] * n_blocks for name in field_data}
    blocks = []
    for k in range(n_blocks):
        dim, tag, kind = fromfile(f, c_int, 3).tolist()
        (count,) = fromfile(f, size_t, 1)
        physical = physical_tags[dim][tag] if physical_tags else None
        for name, cell_set in cell_sets.items():
            # the block's elements are in the physical group named ``name``
            member = physical and field_data[name][1] == dim and field_data[name][0] in physical
            cell_set[k] = np.arange(count if member else 0, dtype=type(count))
        name = _gmsh_to_meshio_type[kind]
        width = 1 + num_nodes_per_cell[name]
        rows = fromfile(f, size_t, int(count * width)).reshape(-1, width)
        bounding = bounding_entities[dim][tag] if dim > 0 and bounding_entities else None
        blocks.append((physical, bounding, tag, name, rows))
    _fast_forward_to_end_block(f, "Elements")

    index = np.full(int(np.max(point_tags)) + 1, -1, dtype=int)
    index[point_tags] = np.arange(len(point_tags))
    cells, cell_data, numbers = [], {}, []
    for physical, bounding, tag, name, rows in blocks:
        nodes = index[rows[:, 1:].astype(np.int64) - 1]
        cells.append(CellBlock(name, _gmsh_to_meshio_order(name, nodes)))
        numbers.append(rows[:, 0].astype(np.int64))
        if physical:
            cell_data.setdefault("gmsh:physical", []).append(np.full(len(nodes), physical[0], int))
        cell_data.setdefault("gmsh:geometrical", []).append(np.full(len(nodes), tag, int))
        if bounding_entities:
            cell_sets.setdefault("gmsh:bounding_entities", []).append(bounding)
    return cells, cell_data, cell_sets, numbers


def _read_nodes41(f, is_ascii, data_size):
    """meshio 5.3's ``_gmsh41._read_nodes`` (the same (points, tags - 1, dim_tags)), also
    for the blocks of parametric nodes a file saved with ``Mesh.SaveParametric = 1``
    has, which meshio refuses: their u (curves), u v (surfaces) or u v w are dropped."""
    from meshio.gmsh.common import _fast_forward_to_end_block

    fromfile, size_t, c_int = _msh41_reader(is_ascii, data_size)
    n_blocks, total = (int(x) for x in fromfile(f, size_t, 4)[:2])
    points = np.empty((total, 3))
    tags = np.empty(total, dtype=int)
    dim_tags = np.empty((total, 2), dtype=int)
    at = 0
    for _ in range(n_blocks):
        dim, entity, parametric = fromfile(f, c_int, 3).tolist()
        count = int(fromfile(f, size_t, 1)[0])
        if at + count > total:
            raise ValueError(f"the node blocks hold more than the {total} nodes announced")
        block = slice(at, at + count)
        tags[block] = fromfile(f, size_t, count).astype(np.int64) - 1
        width = 3 + (dim if parametric else 0)
        values = fromfile(f, np.float64, count * width)
        if len(values) != count * width:
            raise ValueError("the nodes end early")
        points[block] = values.reshape(count, width)[:, :3]
        dim_tags[block] = dim, entity
        at += count
    _fast_forward_to_end_block(f, "Nodes")
    return points[:at], tags[:at], dim_tags[:at]


def _physical_for_every_block(cell_data, cells, physical_tags) -> None:
    """Give every block a ``gmsh:physical`` array when meshio gave one only to the
    blocks of physical groups.

    meshio then refuses its own mesh ("Incompatible cell data"). Gmsh writes such files
    with ``Mesh.SaveAll = 1`` (``-save_all``) once any physical group is defined: users
    set it when their physical groups are boundary surfaces and the tets are in none.
    Here each block gets its entity's first physical tag, 0 for none.
    """
    if physical_tags and len(cell_data.get("gmsh:physical", cells)) != len(cells):
        entities = cell_data["gmsh:geometrical"]
        cell_data["gmsh:physical"] = [
            np.full(len(e), (physical_tags[b.dim].get(int(e[0])) or [0])[0] if len(e) else 0)
            for b, e in zip(cells, entities, strict=True)
        ]


def _read_data(f, tag, is_ascii: bool, found: dict) -> None:
    """meshio's ``$NodeData`` / ``$ElementData`` reader, replaced: meshio 5.3 refuses
    many of the views Gmsh saves with its mesh (``PostProcessing.SaveMesh``): data over
    the tets only, which its binary reader rejects (element numbers not 1..n) and its
    ASCII reader puts on the wrong blocks; its 2.2 reader also splits any element data
    over two or more element blocks at element 2 (the length of a (type, cells) tuple).
    Here each section goes to ``found["views"]`` as it is (``_gmsh_views``), keyed by its
    node or element numbers; a section that does not parse is skipped (``_skip_view``),
    for the warning that names what a mesh does not carry."""
    from meshio.gmsh.common import _fast_forward_to_end_block

    from ._gmsh_views import read_view

    start = f.tell()
    try:
        found["views"].append(read_view(f, tag, is_ascii))
    except (ValueError, IndexError):
        f.seek(start)
        _skip_view(f, tag, found)
        return
    _fast_forward_to_end_block(f, tag)


def _skip_view(f, tag, found: dict) -> None:
    """Skip the view section ``tag`` that starts at ``f`` (after its ``$tag`` line),
    its name (the first string tag, ASCII in binary files too) in ``found["point"]``
    ($NodeData) or ``found["cell"]`` ($ElementData, $ElementNodeData: values at each
    node of each element, which jtet does not read)."""
    from meshio.gmsh.common import _fast_forward_to_end_block

    try:
        if int(f.readline()) > 0:
            name = f.readline().decode("utf-8", "replace").strip().strip('"')
            kind = "point" if tag == "NodeData" else "cell"
            if name not in found.setdefault(kind, []):
                found[kind].append(name)
    except ValueError:  # a damaged header: the skip to the end decides
        pass
    _fast_forward_to_end_block(f, tag)


@contextlib.contextmanager
def gmsh_read_mends():
    """Within it, meshio reads the Gmsh files described in the module docstring; it gives
    the data of the file read: {"views": the ``_gmsh_views.View`` sections, "nodes": the
    node numbers (n,) in meshio's point order, "tets": the tets' element numbers (m,) in
    jtet's order (read only when there are element views; None when they could not be
    read), "point" / "cell": names of the views skipped}."""
    try:
        from meshio.gmsh import _gmsh22, _gmsh41

        read_buffer, _ = _gmsh41.read_buffer, _gmsh41._read_elements  # both mended
        read_buffer22, _ = _gmsh22.read_buffer, _gmsh22._read_cells  # both mended
        read_nodes22, _ = _gmsh22._read_nodes, _gmsh41._read_nodes  # both mended
        skip_block = _gmsh41._fast_forward_to_end_block
        skip_block22 = _gmsh22._fast_forward_to_end_block
    except (ImportError, AttributeError):  # another meshio: its own readers as they are
        yield {}
        return
    state: dict = {}  # of the file being read: its format and its partitions
    found: dict = {"views": [], "nodes": None, "tets": None}

    def read_data(f, tag, data_dict, data_size, is_ascii):
        _read_data(f, tag, is_ascii, found)

    def reading(version: str, read, f, is_ascii, data_size):
        state.clear()
        state.update(version=version, is_ascii=is_ascii, data_size=int(data_size))
        mesh = read(f, is_ascii, data_size)
        found["tets"] = state.get("tet_numbers")  # kept while reading the elements
        return mesh

    def mended_read_buffer(f, is_ascii, data_size):
        return reading("4.1", read_buffer, f, is_ascii, data_size)

    def mended_read_buffer22(f, is_ascii, data_size):
        return reading("2.2", read_buffer22, f, is_ascii, data_size)

    def mended_skip_block(f, block):
        # meshio skips the sections it does not know: this one it needs
        if block == "PartitionedEntities" and "is_ascii" in state:
            state["partitions"] = _Partitions.read(f, state["is_ascii"], state["data_size"])
        elif block == "ElementNodeData":
            _skip_view(f, block, found)
        else:
            skip_block(f, block)

    def mended_skip_block22(f, block):
        if block == "ParametricNodes":  # meshio would skip the nodes, then fail obscurely
            raise ValueError(
                "MSH 2.2 $ParametricNodes (Mesh.SaveParametric = 1) are not read; save "
                "with Mesh.SaveParametric = 0, or in MSH 4.1"
            )
        if block == "ElementNodeData":
            _skip_view(f, block, found)
        else:
            skip_block22(f, block)

    def mended_read_nodes22(f, is_ascii):
        points, numbers = read_nodes22(f, is_ascii)
        found["nodes"] = np.asarray(numbers, np.int64)
        return points, numbers

    def mended_read_nodes41(f, is_ascii, data_size):
        points, tags, dim_tags = _read_nodes41(f, is_ascii, data_size)
        found["nodes"] = np.asarray(tags, np.int64) + 1  # meshio's tags are numbers - 1
        return points, tags, dim_tags

    def mended_read_cells22(f, *args):
        numbers: list = []
        out = _read_cells22(f, *args, tet_numbers=numbers)
        state["tet_numbers"] = np.concatenate(numbers) if numbers else np.zeros(0, np.int64)
        return out

    def mended_read_elements(f, point_tags, physical_tags, bounding_entities, *args):
        partitions = state.get("partitions")
        if partitions is not None:
            physical_tags, bounding_entities = partitions.tables(physical_tags, bounding_entities)
        cells, cell_data, cell_sets, numbers = _read_elements41(
            f, point_tags, physical_tags, bounding_entities, *args
        )
        _physical_for_every_block(cell_data, cells, physical_tags)
        if partitions is not None:
            cells, cell_data, cell_sets, numbers = partitions.to_parents(
                cells, cell_data, cell_sets, numbers
            )
        tets = [n for block, n in zip(cells, numbers, strict=True) if block.type == "tetra"]
        state["tet_numbers"] = np.concatenate(tets) if tets else np.zeros(0, np.int64)
        return cells, cell_data, cell_sets

    swaps = [
        (_gmsh41, "read_buffer", mended_read_buffer),
        (_gmsh41, "_fast_forward_to_end_block", mended_skip_block),
        (_gmsh41, "_read_nodes", mended_read_nodes41),
        (_gmsh41, "_read_elements", mended_read_elements),
        (_gmsh41, "_read_data", read_data),
        (_gmsh22, "read_buffer", mended_read_buffer22),
        (_gmsh22, "_fast_forward_to_end_block", mended_skip_block22),
        (_gmsh22, "_read_nodes", mended_read_nodes22),
        (_gmsh22, "_read_cells", mended_read_cells22),
        (_gmsh22, "_read_data", read_data),
    ]
    with _GMSH_READ:
        originals = [getattr(module, name) for module, name, _ in swaps]
        for module, name, mended in swaps:
            setattr(module, name, mended)
        try:
            yield found
        finally:
            for (module, name, _), original in zip(swaps, originals, strict=True):
                setattr(module, name, original)
