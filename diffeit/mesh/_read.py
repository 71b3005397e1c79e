"""Meshes from standard mesh files (gmsh, STL, OBJ, VTU and the other formats meshio reads)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._messages import name_indices
from ._mesh import Mesh, _boundary_edges, _consistently_oriented, _signed_areas

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

ElectrodeFinder = Callable[[np.ndarray, np.ndarray], Sequence["ArrayLike"]]


def read(path: str | os.PathLike, electrodes: Sequence[ArrayLike] | ElectrodeFinder) -> Mesh:
    """Read a mesh file's triangles as a `Mesh`, flat or a surface in 3D.

    The file is read with meshio, its format chosen by the extension: gmsh .msh (2.2 and 4.1,
    ASCII or binary), .stl (ASCII or binary), .obj, .vtu and the others meshio reads. The mesh
    is the file's triangle cells (other cells, such as gmsh's boundary lines and points, are
    ignored). Its nodes are (N, 2) when the file is 2D or every node's z coordinate is exactly
    zero, (N, 3) otherwise; nodes that belong to no triangle are dropped and the rest keep
    their order. STL lists each facet's vertices on their own: vertices with exactly equal
    coordinates are merged, so that the facets join into one surface, and are numbered in the
    order they first appear in the file (meshio's numbering). Coordinates are taken as metres.

    Electrodes are given either as node indices in the file's numbering (the position of a
    node in the file's node list, from 0; for STL, the order of first appearance), or, for
    files whose numbering is not worth knowing, as a function that finds them on the mesh.

    Arguments:
        path: The mesh file.
        electrodes: Either one sequence of node indices per electrode, in the file's numbering:
            a contiguous run of at least two boundary nodes, in any order, as in
            `Mesh.from_arrays`. Or a callable `electrodes(nodes, boundary_edges)` given the
            mesh's (N, 2) or (N, 3) nodes, as read (unused nodes dropped, STL vertices
            merged), and its (B, 2) boundary edges in those nodes' numbering, directed as the
            mesh's `boundary_edges`; it returns one node index array per electrode in the same
            numbering.

    Returns:
        The `Mesh`, its triangles reoriented as `Mesh` does (counter-clockwise in 2D,
        consistently with the file's first triangle in 3D).

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file, for an extension meshio does not read, a file meshio
            cannot read (not a mesh, truncated, damaged), a file without triangle cells (the
            message names the cells it has), electrode indices outside the file's nodes or on
            nodes of no triangle, and as `Mesh` for a mesh a forward model cannot use (errors
            raised by the `electrodes` callable itself pass through unchanged).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such mesh file: {path}")
    file_format, contents = _read_meshio(path)
    blocks = [np.asarray(block.data) for block in contents.cells if block.type == "triangle"]
    if not blocks:
        counts = [f"{block.type} x {len(block.data)}" for block in contents.cells]
        held = f"its cells are {', '.join(counts)}" if counts else "it holds no cells"
        raise ValueError(f"{path} holds no triangle cells ({held}); a diffeit Mesh is made of triangles")
    triangles = np.concatenate(blocks).astype(np.int64)
    points = np.asarray(contents.points)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"{path}: expected 2D or 3D node coordinates; the file's points have shape {points.shape}")
    if np.any((triangles < 0) | (triangles >= len(points))):
        raise ValueError(f"{path}: triangles index nodes outside the file's {len(points)} nodes")

    # file_to_mesh[i]: the mesh's index of the file's node i, -1 when it is dropped.
    points = points.astype(np.float64)
    if file_format == "stl":
        # + 0.0 makes -0.0 equal to 0.0, as they are as coordinates.
        _, first, inverse = np.unique(points + 0.0, axis=0, return_index=True, return_inverse=True)
        representative = first[inverse.ravel()]  # each node's first copy
        triangles = representative[triangles]
    used = np.zeros(len(points), dtype=bool)
    used[triangles] = True
    file_to_mesh = np.where(used, np.cumsum(used) - 1, -1)
    if file_format == "stl":
        file_to_mesh = file_to_mesh[representative]
    nodes = points[used]
    triangles = file_to_mesh[triangles]
    if nodes.shape[1] == 3 and np.all(nodes[:, 2] == 0):
        nodes = nodes[:, :2]

    if callable(electrodes):
        triangles = _named(path, _oriented, nodes, triangles)
        chains = electrodes(nodes, _named(path, _boundary_edges, triangles))
    else:
        chains = [_named(path, _mesh_indices, index, chain, file_to_mesh) for index, chain in enumerate(electrodes)]
    return _named(path, Mesh, nodes, triangles, tuple(chains))


def _named(path: Path, function: Callable, *arguments):
    """`function(*arguments)`, its `ValueError` naming the file."""
    try:
        return function(*arguments)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def _read_meshio(path: Path):
    """(the format's name, meshio's mesh) of the file; ValueError naming it when no format
    its extension names reads it."""
    import meshio  # imported here: only reading files needs it, and it costs ~0.2 s to import

    formats = []
    extension = ""
    for suffix in reversed(path.suffixes):
        extension = (suffix + extension).lower()
        formats += meshio.extension_to_filetypes.get(extension, [])
    # The formats' own readers: meshio.read prints a failed reader's error and exits the process.
    readers = {name: getattr(meshio, name).read for name in formats if hasattr(getattr(meshio, name, None), "read")}
    if not readers:
        known = sorted(
            extension
            for extension, names in meshio.extension_to_filetypes.items()
            if not extension.endswith(".gz") and any(hasattr(getattr(meshio, name, None), "read") for name in names)
        )
        raise ValueError(f"{path}: no mesh format is known for its extension; meshio reads {', '.join(known)}")
    # ".msh" is ANSYS's and gmsh's: try gmsh's, by far the more common, first.
    failures = []
    for name in sorted(readers, key=lambda name: name != "gmsh"):
        try:
            # Some readers overflow while guessing a variant (STL: ASCII or binary), and say so.
            with np.errstate(all="ignore"):
                return name, readers[name](str(path))
        except Exception as error:  # a reader's failure on a bad file can be of any type
            detail = str(error).strip().splitlines()
            failures.append(f"as {name}: {type(error).__name__}" + (f": {detail[0]}" if detail else ""))
    raise ValueError(f"{path} is damaged or not a mesh file: it does not read {'; '.join(failures)}")


def _oriented(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The triangles oriented as `Mesh` will orient them, so that the boundary edges given to
    an electrode finder are the mesh's."""
    if nodes.shape[1] == 2:
        return np.where((_signed_areas(nodes, triangles) < 0)[:, None], triangles[:, [0, 2, 1]], triangles)
    return _consistently_oriented(triangles)


def _mesh_indices(index: int, chain: ArrayLike, file_to_mesh: np.ndarray) -> np.ndarray:
    """Electrode `index`'s nodes, given in the file's numbering, in the mesh's."""
    chain = np.asarray(chain)
    if chain.ndim != 1 or not np.issubdtype(chain.dtype, np.integer):
        raise ValueError(f"electrode {index} must be a 1D array of node indices; got {chain!r}")
    outside = chain[(chain < 0) | (chain >= len(file_to_mesh))]
    if len(outside):
        raise ValueError(
            f"electrode {index}: nodes {name_indices(outside)} are outside the file's {len(file_to_mesh)} nodes"
        )
    dropped = chain[file_to_mesh[chain] < 0]
    if len(dropped):
        raise ValueError(f"electrode {index}: nodes {name_indices(dropped)} belong to no triangle")
    return file_to_mesh[chain]
