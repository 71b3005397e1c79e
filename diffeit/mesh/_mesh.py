"""The triangle mesh of a sheet, flat (2D) or a surface in 3D, with electrodes on its boundary."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from .._arrays import StaticData, fingerprint, readonly
from .._messages import name_indices

if TYPE_CHECKING:
    import skfem
    from numpy.typing import ArrayLike

# A triangle is degenerate when its area is below this fraction of its longest edge squared.
_DEGENERACY_TOLERANCE = 1e-12


def _signed_areas(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (nodes[triangles[:, k]] for k in range(3))
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


def _surface_areas(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(E,) areas of triangles in 3D: half the norm of the cross product of two edges."""
    a, b, c = (nodes[triangles[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


@dataclass(init=False, eq=False)
class Mesh(StaticData):
    """An immutable P1 triangle mesh of a sheet, with electrodes on its boundary.

    Construct with `Mesh.from_arrays`, `Mesh.from_skfem` or a generator (`diffeit.mesh.disc`,
    `polygon`, `rectangle`, `cylinder_patch`, `sphere_cap`). Construction
    reorients clockwise triangles and refuses meshes a forward model cannot use, with a
    `ValueError` naming the offending triangles, nodes or electrodes.

    A flat sheet has (N, 2) nodes. A sheet lying on a curved surface (a skin on a robot's
    forearm or fingertip) has (N, 3) nodes: the same 2D physics on a surface in space. Such a
    surface has no counter-clockwise; construction instead orients its triangles consistently
    (neighbours traverse their shared edge in opposite directions), keeping the orientation
    of the first triangle, and refuses a non-orientable (Moebius) or closed surface.

    **Fields:**

    - `nodes`: (N, 2) or (N, 3) node coordinates in metres.
    - `triangles`: (E, 3) node indices per element: counter-clockwise in 2D; in 3D
      consistently oriented, the normal (b - a) x (c - a) on one side of the surface.
    - `electrodes`: one integer array per electrode: a chain of at least two boundary nodes,
      consecutive nodes joined by boundary edges, in the direction of `boundary_edges`.
    - `boundary_edges`: (B, 2) boundary edges, each in the direction its triangle traverses
      it: the sheet lies on their left (counter-clockwise along the outer boundary) in 2D,
      and on their left seen from the side the normals point to in 3D.
    - `element_areas`: (E,) triangle areas in m^2.
    - `element_centroids`: (E, 2) or, for a surface, (E, 3) triangle centroids in metres.

    A mesh is static data for JAX: a pytree without leaves. Meshes compare and hash by content
    (nodes, triangles, electrodes), so functions compiled for one mesh serve an equal one; a
    flat mesh and the same mesh given in 3D differ.
    """

    nodes: np.ndarray
    triangles: np.ndarray
    electrodes: tuple[np.ndarray, ...]
    boundary_edges: np.ndarray = field(repr=False)
    element_areas: np.ndarray = field(repr=False)
    element_centroids: np.ndarray = field(repr=False)
    fingerprint: bytes = field(repr=False)

    def __init__(self, nodes: ArrayLike, triangles: ArrayLike, electrodes: Sequence[ArrayLike]) -> None:
        nodes = np.asarray(nodes, dtype=np.float64)
        if nodes.ndim != 2 or nodes.shape[1] not in (2, 3):
            raise ValueError(f"nodes must have shape (N, 2) or, for a surface in 3D, (N, 3); got {nodes.shape}")
        if not np.all(np.isfinite(nodes)):
            bad = np.flatnonzero(~np.all(np.isfinite(nodes), axis=1))
            raise ValueError(f"nodes {name_indices(bad)} have non-finite coordinates")
        triangles = _checked_triangles(triangles, len(nodes))
        if nodes.shape[1] == 2:
            areas = _signed_areas(nodes, triangles)
            triangles = np.where((areas < 0)[:, None], triangles[:, [0, 2, 1]], triangles)
            areas = np.abs(areas)
        else:
            areas = _surface_areas(nodes, triangles)
        _check_nondegenerate(nodes, triangles, areas)
        _check_all_nodes_used(triangles, len(nodes))
        if nodes.shape[1] == 3:
            triangles = _consistently_oriented(triangles)
        boundary_edges = _boundary_edges(triangles)
        if len(boundary_edges) == 0:
            raise ValueError(
                "the mesh is a closed surface (every edge is shared by two triangles): the complete "
                "electrode model needs a boundary to put the electrodes on"
            )
        _check_connected(triangles, len(nodes))
        electrodes = _checked_electrodes(electrodes, boundary_edges, len(nodes))
        self.nodes = readonly(nodes)
        self.triangles = readonly(triangles)
        self.electrodes = tuple(readonly(e) for e in electrodes)
        self.boundary_edges = readonly(boundary_edges)
        self.element_areas = readonly(areas)
        self.element_centroids = readonly(nodes[triangles].mean(axis=1))
        lengths = np.array([len(e) for e in electrodes])
        self.fingerprint = fingerprint(nodes, triangles, lengths, *electrodes)

    @classmethod
    def from_arrays(cls, nodes: np.ndarray, triangles: np.ndarray, electrodes: list) -> Mesh:
        """Build a mesh from external arrays (scikit-fem, EIDORS, gmsh, ...).

        **Arguments:**

        - `nodes`: (N, 2) coordinates in metres, or (N, 3) for a surface in 3D.
        - `triangles`: (E, 3) node indices, either orientation (reoriented counter-clockwise in
          2D, consistently with the first triangle in 3D).
        - `electrodes`: one sequence of boundary node indices per electrode: a contiguous run
          of the boundary, in any order (stored ordered along the boundary); at least two nodes,
          as the complete electrode model needs a width.

        **Raises:** `ValueError` naming degenerate triangles, unused nodes, an edge shared by
        more than two triangles, a non-orientable or closed surface, a disconnected mesh,
        electrodes off the boundary, overlapping electrodes or electrodes of one node.
        """
        return cls(nodes, triangles, tuple(electrodes))

    @classmethod
    def from_skfem(cls, mesh: skfem.MeshTri, electrodes: Sequence[ArrayLike] | None = None) -> Mesh:
        """Build a mesh from a scikit-fem `MeshTri` (node i is `mesh.p[:, i]`, element e is
        `mesh.t[:, e]`, coordinates in metres).

        **Arguments:**

        - `mesh`: a 2D linear triangle mesh.
        - `electrodes`: one sequence of boundary node indices per electrode, as in `from_arrays`.
          Default: the mesh's named boundaries `electrode_0`, `electrode_1`, ... (facet index
          arrays, as `to_skfem` writes them).
        """
        p, t = np.asarray(mesh.p), np.asarray(mesh.t)
        if p.shape[0] != 2 or t.shape[0] != 3:
            raise ValueError(
                f"expected a 2D triangle mesh (p of shape (2, N), t of shape (3, E)); got {p.shape} and {t.shape}"
            )
        if electrodes is None:
            boundaries = mesh.boundaries or {}
            electrodes = []
            while f"electrode_{len(electrodes)}" in boundaries:
                facets = boundaries[f"electrode_{len(electrodes)}"]
                electrodes.append(np.unique(mesh.facets[:, facets]))
            if not electrodes:
                raise ValueError(
                    "the scikit-fem mesh has no boundaries named electrode_0, electrode_1, ...; pass `electrodes`"
                )
        return cls(p.T, t.T, tuple(electrodes))

    def to_skfem(self) -> skfem.MeshTri:
        """The mesh as a scikit-fem `MeshTri`, for reference assembly and post-processing.

        Node i and element e keep their indices (`p = nodes.T`, `t = triangles.T`, triangles
        counter-clockwise); electrode l is the named boundary `electrode_l`, an array of facet
        indices, so `skfem.FacetBasis(m, e, facets="electrode_0")` integrates over it.

        **Raises:** `ValueError` for a surface mesh (3D nodes): a `MeshTri` is flat.
        """
        if self.nodes.shape[1] != 2:
            raise ValueError("to_skfem needs a flat mesh with (N, 2) nodes; this mesh is a surface in 3D")
        import skfem  # imported here: it is only needed for exchange, and costs ~0.5 s to import

        mesh = skfem.MeshTri(np.array(self.nodes.T), np.array(self.triangles.T), sort_t=False)
        # skfem stores each facet as its sorted node pair; look the electrode edges up by that key.
        keys = mesh.facets[0].astype(np.int64) * self.n_nodes + mesh.facets[1]
        order = np.argsort(keys)
        boundaries = {}
        for index, chain in enumerate(self.electrodes):
            pairs = np.sort(np.stack([chain[:-1], chain[1:]]), axis=0)
            wanted = pairs[0] * self.n_nodes + pairs[1]
            boundaries[f"electrode_{index}"] = order[np.searchsorted(keys, wanted, sorter=order)]
        return mesh.with_boundaries(boundaries)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        return len(self.triangles)

    @property
    def n_electrodes(self) -> int:
        return len(self.electrodes)

    def __repr__(self) -> str:
        return f"Mesh(n_nodes={self.n_nodes}, n_elements={self.n_elements}, n_electrodes={self.n_electrodes})"


def _checked_triangles(triangles: np.ndarray, n_nodes: int) -> np.ndarray:
    triangles = np.asarray(triangles)
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"triangles must have shape (E, 3); got {triangles.shape}")
    if len(triangles) == 0:
        raise ValueError("the mesh has no triangles")
    if not np.issubdtype(triangles.dtype, np.integer) and not np.all(np.equal(np.mod(triangles, 1), 0)):
        raise ValueError("triangles must hold integer node indices")
    triangles = triangles.astype(np.int64)
    out_of_range = np.flatnonzero(np.any((triangles < 0) | (triangles >= n_nodes), axis=1))
    if len(out_of_range):
        raise ValueError(f"triangles {name_indices(out_of_range)} index nodes outside [0, {n_nodes})")
    return triangles


def _check_nondegenerate(nodes: np.ndarray, triangles: np.ndarray, areas: np.ndarray) -> None:
    corners = nodes[triangles]
    edges = corners - np.roll(corners, 1, axis=1)
    longest_squared = np.max(np.sum(edges**2, axis=2), axis=1)
    degenerate = np.flatnonzero(areas <= _DEGENERACY_TOLERANCE * longest_squared)
    if len(degenerate):
        raise ValueError(f"degenerate triangles (zero area or repeated vertices): {name_indices(degenerate)}")


def _check_all_nodes_used(triangles: np.ndarray, n_nodes: int) -> None:
    unused = np.setdiff1d(np.arange(n_nodes), triangles)
    if len(unused):
        raise ValueError(f"nodes {name_indices(unused)} belong to no triangle; remove them")


def _directed_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (3E, 2) edges of the triangles in their direction (edge j of triangle e at row
    j * E + e), the index of each one's undirected edge, and how many triangles share that;
    refuses an edge shared by more than two triangles."""
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sharing = counts[inverse]
    if np.any(sharing > 2):
        worst = np.argmax(sharing)
        shared = np.unique(undirected[sharing > 2], axis=0)
        raise ValueError(
            f"non-manifold mesh: the edge between nodes {undirected[worst, 0]} and {undirected[worst, 1]} is "
            f"shared by {sharing[worst]} triangles, at most 2 may share one; all such edges: {shared[:5].tolist()}"
        )
    return directed, inverse, sharing


def _boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """Edges used by exactly one triangle, in that triangle's direction."""
    directed, _, sharing = _directed_edges(triangles)
    return directed[sharing == 1]


def _consistently_oriented(triangles: np.ndarray) -> np.ndarray:
    """The triangles of a surface reoriented so that every two neighbours traverse their
    shared edge in opposite directions: a breadth-first walk over neighbours from the first
    triangle of each edge-connected piece, which keeps its orientation. Refuses a
    non-orientable surface."""
    directed, edge_id, sharing = _directed_edges(triangles)
    n_triangles = len(triangles)
    owner = np.tile(np.arange(n_triangles), 3)
    # The two uses of each interior edge, side by side.
    interior = np.flatnonzero(sharing == 2)
    interior = interior[np.argsort(edge_id[interior], kind="stable")].reshape(-1, 2)
    first, second = owner[interior[:, 0]], owner[interior[:, 1]]
    # Neighbours that traverse their edge in the same direction need opposite flips.
    same_direction = directed[interior[:, 0], 0] == directed[interior[:, 1], 0]
    neighbours = scipy.sparse.coo_matrix((np.ones(len(first)), (first, second)), shape=(n_triangles, n_triangles))
    neighbours = neighbours.tocsr()
    pair_keys = np.minimum(first, second) * n_triangles + np.maximum(first, second)
    pair_order = np.argsort(pair_keys)
    _, labels = scipy.sparse.csgraph.connected_components(neighbours, directed=False)
    flipped = np.zeros(n_triangles, dtype=bool)
    for root in np.unique(labels, return_index=True)[1]:
        order, parent = scipy.sparse.csgraph.breadth_first_order(neighbours, root, directed=False)
        children, parents = order[1:], parent[order[1:]]
        keys = np.minimum(children, parents) * n_triangles + np.maximum(children, parents)
        must_differ = same_direction[pair_order[np.searchsorted(pair_keys, keys, sorter=pair_order)]]
        # Parents come before their children in breadth-first order.
        for child, parent_, differ in zip(children.tolist(), parents.tolist(), must_differ.tolist(), strict=True):
            flipped[child] = flipped[parent_] ^ differ
    conflicting = (flipped[first] ^ flipped[second]) != same_direction
    if np.any(conflicting):
        a, b = directed[interior[np.argmax(conflicting), 0]]
        raise ValueError(
            "the surface is non-orientable (a Moebius strip, or contains one): no orientation of its "
            f"triangles agrees across every shared edge (it fails at the edge between nodes {a} and {b})"
        )
    return np.where(flipped[:, None], triangles[:, [0, 2, 1]], triangles)


def _check_connected(triangles: np.ndarray, n_nodes: int) -> None:
    rows = np.repeat(triangles, 3, axis=1).ravel()
    cols = np.tile(triangles, 3).ravel()
    graph = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_nodes, n_nodes))
    n_components, _ = scipy.sparse.csgraph.connected_components(graph, directed=False)
    if n_components > 1:
        raise ValueError(f"the mesh falls apart into {n_components} disconnected pieces")


def _checked_electrodes(electrodes, boundary_edges: np.ndarray, n_nodes: int) -> list[np.ndarray]:
    if len(electrodes) == 0:
        raise ValueError("the mesh has no electrodes")
    boundary_nodes = np.unique(boundary_edges)
    owner = np.full(n_nodes, -1)
    checked = []
    for index, nodes in enumerate(electrodes):
        nodes = np.asarray(nodes)
        if nodes.ndim != 1 or not np.issubdtype(nodes.dtype, np.integer):
            raise ValueError(f"electrode {index} must be a 1D array of node indices; got {nodes!r}")
        nodes = nodes.astype(np.int64)
        if len(nodes) < 2:
            raise ValueError(
                f"electrode {index} has {len(nodes)} node(s); a complete-electrode-model electrode "
                "needs a chain of at least 2 boundary nodes"
            )
        if np.any((nodes < 0) | (nodes >= n_nodes)):
            raise ValueError(f"electrode {index} indexes nodes outside [0, {n_nodes})")
        if len(np.unique(nodes)) != len(nodes):
            raise ValueError(f"electrode {index} repeats a node: {nodes.tolist()}")
        off_boundary = np.setdiff1d(nodes, boundary_nodes)
        if len(off_boundary):
            raise ValueError(f"electrode {index}: nodes {name_indices(off_boundary)} are not on the boundary")
        chain = _boundary_chain(nodes, boundary_edges)
        if chain is None:
            raise ValueError(
                f"electrode {index}: nodes {name_indices(np.sort(nodes))} do not form one contiguous "
                "piece of the boundary"
            )
        shared = chain[owner[chain] >= 0]
        if len(shared):
            other = owner[shared[0]]
            raise ValueError(f"electrodes {other} and {index} overlap at nodes {name_indices(shared)}")
        owner[chain] = index
        checked.append(chain)
    return checked


def _boundary_chain(nodes: np.ndarray, boundary_edges: np.ndarray) -> np.ndarray | None:
    """`nodes` ordered along the boundary, in the direction of `boundary_edges` (the sheet on
    the left), or None when they are not one contiguous run of boundary edges. Accepts the
    nodes in any order, as EIDORS and other tools list them."""
    inside = np.isin(boundary_edges, nodes).all(axis=1)
    following = dict(boundary_edges[inside].tolist())
    if len(following) != len(nodes) - 1:
        return None
    starts = set(nodes.tolist()) - set(following.values())
    if len(starts) != 1:
        return None
    chain = [starts.pop()]
    while chain[-1] in following and len(chain) < len(nodes):
        chain.append(following[chain[-1]])
    return np.array(chain) if len(chain) == len(nodes) else None


def require_flat(mesh: Mesh, what: str) -> None:
    """Refuse a surface mesh for `what`, which works in the plane (a point locator, polygon
    clipping, a pixel grid): it would read the first two coordinates of a curved skin's nodes
    as a plane and answer wrongly without a word.

    Arguments:
        mesh: The mesh.
        what: What needs the flat mesh, for the message.

    Raises:
        ValueError: For a mesh with (N, 3) nodes.
    """
    if mesh.nodes.shape[1] != 2:
        raise ValueError(f"{what} works on flat meshes ((N, 2) nodes); this mesh is a surface in 3D (a curved skin)")
