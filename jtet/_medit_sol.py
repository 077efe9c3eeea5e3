"""Medit solution files (``.sol``): the values at the vertices that MMG reads and writes
beside a ``.mesh`` / ``.meshb`` of the same name (a metric, a level set, a solution),
as ``TetMesh.point_data``.

The format (ASCII; libMeshb's keywords): ``MeshVersionFormatted 2``, ``Dimension 3``,
then ``SolAtVertices``, the vertex count, the number of solutions and their types (1:
scalar, 2: vector of 3, 3: symmetric 3 x 3 matrix as its 6 lower-triangle entries, 4:
full 3 x 3 matrix), then one row per vertex of every solution's values in turn, and
``End``. Lines from ``#`` on are comments. Solutions have no names: jtet names them in a
comment line (``# jtet names: T, v``) that it reads back; a file without one gives
``sol`` (one solution) or ``sol1``, ``sol2``, ...
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshInputError

#: the number of values of each solution type in 3-D (scalar, vector, sym. matrix, matrix)
TYPE_SIZES = {1: 1, 2: 3, 3: 6, 4: 9}
_NAMES = "# jtet names:"
# other sections of values (at edges, triangles, tets, ...): each skipped with a warning
_OTHER_SECTIONS = re.compile(r"SolAt\w+")


def sol_path(mesh_path: Path) -> Path:
    """The solution file MMG reads and writes beside the Medit mesh ``mesh_path``."""
    return Path(mesh_path).with_suffix(".sol")


def read_sol(path: Path, n_points: int, source: str) -> dict:
    """The values at the vertices in the ``.sol`` file ``path`` of a mesh of
    ``n_points`` vertices: {name: (n,) or (n, k) float64 array}. A file for another
    vertex count, or without values at vertices, is ignored with a warning (a leftover
    of another mesh); a damaged one is ``MeshInputError``."""
    text = Path(path).read_text(errors="replace")
    names = None
    for line in text.splitlines():
        if line.startswith(_NAMES):
            names = [n.strip() for n in line[len(_NAMES) :].split(",")]
    tokens = re.sub(r"#[^\n]*", " ", text).split()
    where = f"{source}: solution file {Path(path).name}"
    out: dict = {}
    i = 0
    try:
        while i < len(tokens):
            word = tokens[i]
            if word in ("MeshVersionFormatted", "Dimension"):
                if int(tokens[i + 1]) != 3 and word == "Dimension":
                    raise MeshInputError(f"{where}: dimension {tokens[i + 1]}, not 3")
                i += 2
            elif word == "End":
                break
            elif _OTHER_SECTIONS.fullmatch(word):
                count, n_sols = int(tokens[i + 1]), int(tokens[i + 2])
                types = [int(t) for t in tokens[i + 3 : i + 3 + n_sols]]
                if any(t not in TYPE_SIZES for t in types) or count < 0:
                    raise MeshInputError(f"{where}: {word}: solution types {types} (1-4)")
                width = sum(TYPE_SIZES[t] for t in types)
                start = i + 3 + n_sols
                if word != "SolAtVertices":
                    warnings.warn(
                        f"{where}: {word} not read (values at vertices only)", stacklevel=3
                    )
                elif count != n_points:
                    warnings.warn(
                        f"{where}: values at {count} vertices, the mesh has {n_points}; ignored",
                        stacklevel=3,
                    )
                else:
                    try:
                        values = np.array(tokens[start : start + count * width], np.float64)
                    except ValueError:  # the section's end, or damage, among its numbers
                        values = np.zeros(0)
                    if values.size != count * width:
                        raise MeshInputError(
                            f"{where}: {word} holds fewer than {count} rows of {width} numbers"
                        )
                    out.update(_split(values.reshape(count, width), types, names))
                i = start + count * width
            else:
                raise MeshInputError(f"{where}: unexpected {word[:40]!r}")
    except MeshInputError:
        raise
    except (ValueError, IndexError):  # a count or a type that is no number, a cut file
        raise MeshInputError(f"{where}: not a readable Medit solution file") from None
    return out


def _split(table: np.ndarray, types: list[int], names: list[str] | None) -> dict:
    """The columns of ``table`` (n, width) as one array per solution of ``types``
    (scalars ``name[0]``, ``name[1]``, ... joined into one array: ``joined_columns``)."""
    from ._point_data import joined_columns

    if names is None or len(names) != len(types) or not all(names):
        names = ["sol"] if len(types) == 1 else [f"sol{k + 1}" for k in range(len(types))]
    out, col = {}, 0
    for name, t in zip(names, types, strict=True):
        size = TYPE_SIZES[t]
        out[name] = table[:, col] if size == 1 else table[:, col : col + size]
        col += size
    return joined_columns(out)


def write_sol(path: Path, point_data: dict) -> None:
    """``point_data`` as the ``.sol`` file ``path``: an (n,) array as a scalar, (n, 3) a
    vector, (n, 6) a symmetric matrix, (n, 9) a matrix (MMG's metric: an (n,) size or an
    (n, 6) tensor); an array of another width as that many scalars ``name[i]``. Values
    are written as reals (17 significant digits: float64 exactly)."""
    from ._io import format_rows
    from ._point_data import scalar_columns

    names, types, columns = [], [], []
    by_size = {size: t for t, size in TYPE_SIZES.items()}
    for name, a in point_data.items():
        a = np.asarray(a, np.float64)
        width = 1 if a.ndim == 1 else a.shape[1]
        pieces = {name: a} if width in by_size else scalar_columns({name: a})
        for piece, b in pieces.items():
            names.append(piece)
            types.append(by_size[1 if b.ndim == 1 else b.shape[1]])
            columns.append(b.reshape(len(b), -1))
    table = np.column_stack(columns)
    with open(path, "w") as f:
        f.write(f"{_NAMES} {', '.join(names)}\n")
        f.write("MeshVersionFormatted 2\n\nDimension 3\n\nSolAtVertices\n")
        f.write(f"{len(table)}\n{len(types)} {' '.join(map(str, types))}\n")
        f.write(format_rows(table, " ".join(["%.17g"] * table.shape[1]) + "\n"))
        f.write("\nEnd\n")
