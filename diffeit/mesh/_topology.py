"""Which elements of a mesh are neighbours, and how far apart they lie along the sheet."""

import functools

import numpy as np

from .._arrays import readonly
from ._mesh import Mesh


@functools.lru_cache(maxsize=16)
def element_adjacency(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of elements that share an edge, and the length of that edge.

    Each interior edge gives one pair; boundary edges give none. Computed once per mesh (by
    content, cached); the arrays are read-only.

    Arguments:
        mesh: The mesh, flat or a surface in 3D.

    Returns:
        `(first, second, lengths)`: (P,) int indices of the two elements of each pair
        (`first < second`) and (P,) the length of their shared edge, metres.
    """
    first, second, edges = _shared_edges(mesh)
    return first, second, readonly(np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1))


def centroid_distances(mesh: Mesh) -> np.ndarray:
    """The distance along the sheet between the centroids of each pair of `element_adjacency`.

    The two triangles are unfolded into one plane about their shared edge and the centroids
    joined by a straight line: the shortest path on the piecewise-flat surface, which a sheet
    bent along mesh edges keeps. On a flat mesh it is the straight line between the centroids;
    on a curved one it is longer than that chord, which cuts through the bend.

    Arguments:
        mesh: The mesh, flat or a surface in 3D.

    Returns:
        (P,) metres, in the order of `element_adjacency`'s pairs.
    """
    first, second, edges = _shared_edges(mesh)
    start = mesh.nodes[edges[:, 0]]
    along = mesh.nodes[edges[:, 1]] - start
    along /= np.linalg.norm(along, axis=1, keepdims=True)

    def coordinates(elements: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each centroid's position along the shared edge and its distance from the edge's line."""
        offset = mesh.element_centroids[elements] - start
        position = np.sum(offset * along, axis=1)
        return position, np.linalg.norm(offset - position[:, None] * along, axis=1)

    (a, d), (b, e) = coordinates(first), coordinates(second)
    return np.hypot(a - b, d + e)  # the centroids lie on either side of the edge once unfolded


@functools.lru_cache(maxsize=16)
def _shared_edges(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P,) first and (P,) second elements of each interior edge, and (P, 2) its nodes; read-only."""
    edges = np.sort(mesh.triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(mesh.n_elements), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    shared = np.flatnonzero(np.all(edges[1:] == edges[:-1], axis=1))  # each interior edge twice
    return readonly(owner[shared]), readonly(owner[shared + 1]), readonly(edges[shared])
