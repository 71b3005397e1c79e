"""Which elements of a mesh are neighbours."""

import numpy as np

from ._mesh import Mesh


def element_adjacency(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of elements that share an edge: (first, second, shared edge length in metres)."""
    edges = np.sort(mesh.triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(mesh.n_elements), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    shared = np.flatnonzero(np.all(edges[1:] == edges[:-1], axis=1))  # each interior edge twice
    lengths = np.linalg.norm(mesh.nodes[edges[shared, 0]] - mesh.nodes[edges[shared, 1]], axis=1)
    return owner[shared], owner[shared + 1], lengths
