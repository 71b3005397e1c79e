"""Finite-element assembly of the complete electrode model on P1 triangles.

Unknowns: the nodal potentials u, then the electrode potentials U_0 .. U_(L-1). One node g
(on the last electrode) is grounded, u_g = 0, and dropped, which makes the system symmetric
positive definite. Grounding a node rather than an electrode keeps the nodal potentials at the
scale of the field even when the contact impedance is large (an electrode ground would float
every node by the contact voltage drop, which float32 cannot resolve). With z_l the contact
impedance of electrode l (ohm m) and e_l its boundary segment:

    [K(sigma) + B   C] [u]   [0]
    [C^T            D] [U] = [I]

    K_ij  = sum_e sigma_e int_e grad phi_i . grad phi_j
    B_ij  = sum_l (1/z_l) int_{e_l} phi_i phi_j
    C_il  = -(1/z_l) int_{e_l} phi_i
    D_ll  = |e_l| / z_l

The currents I must sum to zero. The geometry is computed once with NumPy; the values are a
traced JAX function of sigma and z.

Electrodes can move along the boundary: with a margin m > 0, each electrode's entries cover the
boundary edges within m of its ends (its window), and the integrals over e_l are taken over the
part of each edge that a moved electrode [a, b] covers (arc length along the boundary, a and b
within m of the mesh electrode's ends). They are polynomials in the covered fraction of each
edge, so the values are differentiable in a and b: the derivative of an integral with respect to
an end is its integrand there.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import StaticData
from .linear_solve import SparsityPattern
from .mesh import Mesh


def basis_gradients(mesh: Mesh) -> np.ndarray:
    """The gradients of the three P1 basis functions of each triangle of a mesh.

    For nodes in d = 2 dimensions the gradients lie in the plane; on a surface (d = 3) each is
    the gradient within its triangle's plane. Computed with NumPy, once per system.

    Arguments:
        mesh: The mesh, flat ((N, 2) nodes) or a surface in 3D ((N, 3) nodes).

    Returns:
        (E, d, 3) gradients, 1/m: `[e, :, k]` is the gradient of the basis function of corner k
        of triangle e.
    """
    corners = mesh.nodes[mesh.triangles]  # (E, 3, d)
    twice_areas = 2 * mesh.element_areas[:, None, None]
    if mesh.nodes.shape[1] == 2:
        # grad phi_k is the opposite edge x_(k+1) - x_(k+2) turned by -90 degrees, over twice the area.
        opposite = np.roll(corners, -1, axis=1) - np.roll(corners, -2, axis=1)
        gradients = np.stack([opposite[:, :, 1], -opposite[:, :, 0]], axis=1)
        return gradients / twice_areas
    # The same turn within the plane: n x (x_(k+2) - x_(k+1)) over twice the area, with n the
    # unit normal (b - a) x (c - a) / (2 A); for n = +z it is the 2D formula.
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]) / twice_areas[:, :, 0]
    opposite = np.roll(corners, -2, axis=1) - np.roll(corners, -1, axis=1)  # (E, 3 corners, 3 axes)
    gradients = np.cross(normals[:, None, :], opposite)
    return np.swapaxes(gradients, 1, 2) / twice_areas


@dataclass(eq=False)
class _GroundedSystem(StaticData):
    """What both electrode systems hold: the stiffness part of a matrix grounded at one node,
    built from one mesh. Static data for JAX, compared and hashed by that mesh."""

    pattern: SparsityPattern
    n_nodes: int
    n_electrodes: int
    grounded_node: int
    fingerprint: bytes  # of the mesh: the system is a function of it
    triangles: np.ndarray  # (E, 3) node indices
    element_areas: np.ndarray  # (E,) m^2
    gradients: np.ndarray  # (E, d, 3) basis function gradients, 1/m (d = 2, or 3 on a surface)
    unit_stiffness: np.ndarray  # (E, 9): area * grad phi_i . grad phi_j, row-major
    stiffness_table: np.ndarray  # (nnz, k): flat indices into unit_stiffness summed per slot, E*9 pads

    @staticmethod
    def _stiffness_fields(mesh: Mesh, stiffness: _Stiffness, grounded: int) -> dict:
        return {
            "pattern": stiffness.pattern,
            "n_nodes": mesh.n_nodes,
            "n_electrodes": mesh.n_electrodes,
            "grounded_node": grounded,
            "fingerprint": mesh.fingerprint,
            "triangles": mesh.triangles,
            "element_areas": mesh.element_areas,
            "gradients": stiffness.gradients,
            "unit_stiffness": stiffness.unit,
            "stiffness_table": stiffness.table,
        }


@dataclass(eq=False)
class CompleteElectrodeSystem(_GroundedSystem):
    """The fixed structure of the grounded complete-electrode-model matrix of one mesh.

    `values(sigma, z)` returns the (nnz,) matrix values on `pattern`; `values(sigma, z, ends)`
    those with the electrodes moved along the boundary by `ends`, within `electrode_margin`.
    """

    electrode_margin: float  # m: how far an electrode's ends may move along the boundary
    electrode_lengths: np.ndarray  # (L,) the mesh electrodes' lengths along the boundary, m
    electrode_weights: np.ndarray  # (C,) geometric integral of each electrode entry, m
    electrode_of_entry: np.ndarray  # (C,) the electrode whose 1/z scales the entry
    electrode_rows: np.ndarray  # (C,) row and column of each electrode entry in the system
    electrode_cols: np.ndarray
    electrode_slots: np.ndarray  # (C,)
    entry_integral: np.ndarray  # (C,) which integral of `_edge_integrals` the entry is
    entry_edge_start: np.ndarray  # (C,) arc length of the entry's edge's first node, m,
    # from the first node of its mesh electrode (negative before it)
    entry_edge_length: np.ndarray  # (C,) m

    @classmethod
    def from_mesh(cls, mesh: Mesh, electrode_margin: float = 0.0) -> CompleteElectrodeSystem:
        """The system of a mesh, its electrodes free to move along the boundary within a margin.

        With `electrode_margin` m > 0, each electrode's entries also cover the boundary edges
        within m of its ends, so `values` and `contact_forms` can take electrodes moved by up to
        m at either end (`ends`); the larger structure makes another system (another
        fingerprint) than the margin-free one.

        Arguments:
            mesh: The mesh, with its electrodes' boundary chains.
            electrode_margin: How far each end of an electrode may move along the boundary,
                metres, finite and >= 0; 0 fixes the electrodes.

        Returns:
            The `CompleteElectrodeSystem`, grounded at the node of the last electrode nearest
            its midpoint.

        Raises:
            ValueError: For an `electrode_margin` not finite or negative, or one that reaches
                round the whole boundary loop of an electrode.
        """
        if not (np.isfinite(electrode_margin) and electrode_margin >= 0):
            raise ValueError(f"electrode_margin must be finite and >= 0 (metres); got {electrode_margin}")
        n_nodes, n_electrodes = mesh.n_nodes, mesh.n_electrodes
        grounded = _midpoint_node(mesh, mesh.electrodes[-1])
        size = n_nodes - 1 + n_electrodes
        unknown_of_node = _unknown_of_node(n_nodes, grounded, size)
        rows, cols, integral, owner, starts, lengths = [], [], [], [], [], []
        electrode_lengths = []
        for l, chain in enumerate(mesh.electrodes):
            window, first = _window(mesh, chain, electrode_margin)
            edge_length = np.linalg.norm(mesh.nodes[window[1:]] - mesh.nodes[window[:-1]], axis=1)
            arc = np.concatenate([[0.0], np.cumsum(edge_length)])
            electrode_lengths.append(arc[first + len(chain) - 1] - arc[first])
            edge_start = arc[:-1] - arc[first]
            a, b = unknown_of_node[window[:-1]], unknown_of_node[window[1:]]
            u = n_nodes - 1 + l  # the unknown U_l
            for r, c, k in [
                (a, a, 0),
                (b, b, 1),
                (a, b, 2),
                (b, a, 2),
                (a, u, 3),
                (u, a, 3),
                (b, u, 4),
                (u, b, 4),
                (u, u, 5),
            ]:
                r, c, k, _ = np.broadcast_arrays(r, c, k, edge_start)
                rows.append(r)
                cols.append(c)
                integral.append(k)
                owner.append(np.full(len(k), l))
                starts.append(edge_start)
                lengths.append(edge_length)
        rows, cols, integral, owner, starts, lengths = map(
            np.concatenate, (rows, cols, integral, owner, starts, lengths)
        )
        kept = (rows < size) & (cols < size)  # entries of the grounded node are dropped
        rows, cols, integral, owner, starts, lengths = (x[kept] for x in (rows, cols, integral, owner, starts, lengths))
        electrode_lengths = np.array(electrode_lengths)
        stiffness = _Stiffness.from_mesh(mesh, unknown_of_node, rows, cols, size)
        fields = cls._stiffness_fields(mesh, stiffness, grounded)
        if electrode_margin > 0:  # another matrix structure: another system
            fields["fingerprint"] += np.float64(electrode_margin).tobytes()
        nominal = np.stack([np.zeros(n_electrodes), electrode_lengths], axis=1)
        return cls(
            **fields,
            electrode_margin=float(electrode_margin),
            electrode_lengths=electrode_lengths,
            electrode_weights=_entry_weights(integral, starts, lengths, nominal[owner], xp=np),
            electrode_of_entry=owner,
            electrode_rows=rows,
            electrode_cols=cols,
            electrode_slots=stiffness.extra_slots,
            entry_integral=integral,
            entry_edge_start=starts,
            entry_edge_length=lengths,
        )

    def weights(self, ends: jax.Array | None = None) -> jax.Array:
        """The geometric integral of each electrode entry, of the mesh's or of moved electrodes.

        The integrals over the electrode's boundary segment of the products of basis functions
        (and the electrode's constant) that each electrode entry of the matrix holds, before
        the factor 1/z_l. A traced JAX function of `ends`, differentiable in them.

        Arguments:
            ends: (L, 2) how far the start and end of each electrode move along the boundary,
                metres, in the direction of the electrode's nodes, each within
                `electrode_margin` (not checked: beyond it an electrode stops at its window's
                edge); None for the mesh's electrodes.

        Returns:
            (C,) the integral of each electrode entry, metres.
        """
        if ends is None:
            return jnp.asarray(self.electrode_weights)
        extent = jnp.stack([ends[:, 0], self.electrode_lengths + ends[:, 1]], axis=1)
        return _entry_weights(
            self.entry_integral, self.entry_edge_start, self.entry_edge_length, extent[self.electrode_of_entry]
        )

    def values(self, conductivity: jax.Array, contact_impedance: jax.Array, ends: jax.Array | None = None) -> jax.Array:
        """The grounded system matrix's values on `pattern` for a conductivity and contact impedance.

        A traced JAX function of all three arguments: jit, grad and vmap work on it.

        Arguments:
            conductivity: (E,) sheet conductivity per element, S/sq.
            contact_impedance: (L,) contact impedance per electrode, ohm m.
            ends: (L, 2) electrode ends moved along the boundary, metres, as in `weights`;
                None for the mesh's electrodes.

        Returns:
            (nnz,) matrix values, siemens, in the order of `pattern`, in the result dtype of
            `conductivity` and `contact_impedance`.
        """
        dtype = jnp.result_type(conductivity, contact_impedance)
        values = _stiffness_values(conductivity.astype(dtype), self.unit_stiffness, self.stiffness_table)
        electrode = self.weights(ends).astype(dtype) / contact_impedance[self.electrode_of_entry]
        return values.at[self.electrode_slots].add(electrode)

    def current_rhs(self, currents: jax.Array) -> jax.Array:
        """The system's right-hand sides for electrode current patterns.

        The nodal rows are zero and the electrode rows hold the currents.

        Arguments:
            currents: (k, L) k current patterns, amperes (or unit-free weights), each summing
                to zero (not checked).

        Returns:
            (n, k) right-hand sides, n = N - 1 + L unknowns, in the dtype of `currents`.
        """
        nodal = jnp.zeros((self.n_nodes - 1, currents.shape[0]), currents.dtype)
        return jnp.concatenate([nodal, currents.T])

    def split(self, solution: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The nodal and electrode potentials of system solutions, shifted to sum to zero.

        The grounded node's potential (0) is put back, and each solution's potentials are
        shifted so that its electrode potentials sum to zero.

        Arguments:
            solution: (n, k) solutions of the system, n = N - 1 + L unknowns: volts for
                currents in amperes.

        Returns:
            The nodal potentials (k, N) and the electrode potentials (k, L), in the unit of
            `solution`.
        """
        nodal = _with_ground(solution[: self.n_nodes - 1], self.grounded_node)
        electrode = solution[self.n_nodes - 1 :].T
        shift = electrode.mean(axis=1, keepdims=True)
        return nodal - shift, electrode - shift

    def contact_forms(self, first: jax.Array, second: jax.Array, ends: jax.Array | None = None) -> jax.Array:
        """The electrode terms of the energy, int_(e_l) (u - U_l)(v - V_l) ds, per electrode.

        Pairs column j of `first` with column j of `second`. z_l^-2 times this is the derivative
        of the bilinear form u^T A v with respect to -z_l: what the contact impedance Jacobian
        is made of.

        Arguments:
            first: (n, k) system solutions (as solved, not shifted by `split`): volts for
                currents in amperes.
            second: (n, k) system solutions, paired with `first` column by column.
            ends: (L, 2) electrode ends moved along the boundary, metres, as in `weights`;
                None for the mesh's electrodes.

        Returns:
            (k, L) the integrals, in the dtype of `first`: V^2 m for two solutions in volts.
        """
        weights = self.weights(ends).astype(first.dtype)[:, None]
        products = weights * first[self.electrode_rows] * second[self.electrode_cols]  # (C, k)
        return jax.ops.segment_sum(products, self.electrode_of_entry, num_segments=self.n_electrodes).T


def _window(mesh: Mesh, chain: np.ndarray, margin: float) -> tuple[np.ndarray, int]:
    """The boundary nodes an electrode may cover when its ends move up to `margin` metres: its
    chain extended along the boundary at both ends, and the index of its first node in it."""
    following = dict(mesh.boundary_edges.tolist())
    preceding = {b: a for a, b in mesh.boundary_edges.tolist()}
    before, after = [], []
    for nodes, step, end in ((before, preceding, int(chain[0])), (after, following, int(chain[-1]))):
        covered, node = 0.0, end
        while covered < margin:
            node = step[node]
            if node in chain or node in before or node in after:
                raise ValueError(f"electrode_margin {margin} m reaches round the whole boundary loop of an electrode")
            covered += float(np.linalg.norm(mesh.nodes[node] - mesh.nodes[nodes[-1] if nodes else end]))
            nodes.append(node)
    return np.concatenate([before[::-1], chain, after]).astype(np.int64), len(before)


def _edge_integrals(start: jax.Array, end: jax.Array) -> list[jax.Array]:
    """Integrals over t in [start, end] (within [0, 1]) of the products of an edge's two linear
    basis functions (1 - t, t) and the electrode's constant: (1-t)^2, t^2, t(1-t), -(1-t), -t,
    1, in the order of `CompleteElectrodeSystem.entry_integral`."""
    d1 = end - start
    d2 = (end**2 - start**2) / 2
    d3 = (end**3 - start**3) / 3
    return [d1 - 2 * d2 + d3, d3, d2 - d3, d2 - d1, -d2, d1]


def _entry_weights(integral: np.ndarray, start: np.ndarray, length: np.ndarray, extent: jax.Array, xp=jnp) -> jax.Array:
    """(C,) each entry's integral over the part of its edge the electrode [a, b] = `extent`
    (C, 2) covers (arc lengths as `start`), times the edge's length; in NumPy with `xp=np`."""
    fraction = (extent - start[:, None]) / length[:, None]
    # Clipped to [0, 1], the derivative passed at 0 and not at 1: an end on a node moves the
    # integrals of one edge, not of both (the sum over both is continuously differentiable).
    # An end within rounding of a node is on it, whichever side rounding put it.
    near = 1e-9
    covered = xp.where(fraction < -near, 0.0, xp.where(fraction >= 1 - near, 1.0, fraction))
    integrals = xp.stack(_edge_integrals(covered[:, 0], covered[:, 1]))  # (6, C)
    return length * xp.take_along_axis(integrals, xp.asarray(integral)[None], axis=0)[0]


@dataclass(eq=False)
class PointElectrodeSystem(_GroundedSystem):
    """The stiffness matrix of one mesh with point electrodes, grounded at one node.

    Electrode l is the single node `electrode_nodes[l]` (the node of its boundary chain
    nearest the chain's midpoint by arc length); the current of electrode l enters there,
    and its potential is the nodal potential. The node of the last electrode is grounded and
    dropped, which makes the matrix symmetric positive definite. There is no contact
    impedance: `values` ignores it, and derivatives with respect to it are zero. For
    comparison with point-electrode tools (pyEIT); the potential at a point source is
    mesh-dependent (it diverges logarithmically under refinement), so prefer the complete
    model for physics.
    """

    electrode_nodes: np.ndarray  # (L,) node index of each electrode

    @classmethod
    def from_mesh(cls, mesh: Mesh) -> PointElectrodeSystem:
        """The point-electrode system of a mesh.

        Each electrode becomes the node of its boundary chain nearest the chain's midpoint by
        arc length; the last electrode's node is grounded.

        Arguments:
            mesh: The mesh, with its electrodes' boundary chains.

        Returns:
            The `PointElectrodeSystem`.
        """
        electrode_nodes = np.array([_midpoint_node(mesh, chain) for chain in mesh.electrodes])
        grounded = int(electrode_nodes[-1])
        size = mesh.n_nodes - 1
        empty = np.zeros(0, dtype=np.int64)
        stiffness = _Stiffness.from_mesh(mesh, _unknown_of_node(mesh.n_nodes, grounded, size), empty, empty, size)
        return cls(**cls._stiffness_fields(mesh, stiffness, grounded), electrode_nodes=electrode_nodes)

    def values(self, conductivity: jax.Array, contact_impedance: jax.Array) -> jax.Array:
        """The grounded stiffness matrix's values on `pattern` for a conductivity.

        The contact impedance has no part in the point model: it only joins the conductivity
        in setting the dtype. A traced JAX function, as `CompleteElectrodeSystem.values`.

        Arguments:
            conductivity: (E,) sheet conductivity per element, S/sq.
            contact_impedance: Ohm m, scalar or (L,); its values are ignored.

        Returns:
            (nnz,) matrix values, siemens, in the order of `pattern`, in the result dtype of
            `conductivity` and `contact_impedance`.
        """
        dtype = jnp.result_type(conductivity, contact_impedance)
        return _stiffness_values(conductivity.astype(dtype), self.unit_stiffness, self.stiffness_table)

    def current_rhs(self, currents: jax.Array) -> jax.Array:
        """The system's right-hand sides for electrode current patterns.

        Electrode l's current enters at its node; the grounded node's current is implied (the
        currents sum to zero).

        Arguments:
            currents: (k, L) k current patterns, amperes (or unit-free weights), each summing
                to zero (not checked).

        Returns:
            (n, k) right-hand sides, n = N - 1 unknowns, in the dtype of `currents`.
        """
        rows = _unknown_of_node(self.n_nodes, self.grounded_node, self.pattern.size)[self.electrode_nodes]
        rhs = jnp.zeros((self.pattern.size + 1, currents.shape[0]), currents.dtype)
        return rhs.at[rows].add(currents.T)[:-1]

    def split(self, solution: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The nodal and electrode potentials of system solutions, shifted to sum to zero.

        The grounded node's potential (0) is put back, each electrode's potential is its
        node's, and each solution's potentials are shifted so that its electrode potentials sum
        to zero.

        Arguments:
            solution: (n, k) solutions of the system, n = N - 1 unknowns: volts for currents in
                amperes.

        Returns:
            The nodal potentials (k, N) and the electrode potentials (k, L), in the unit of
            `solution`.
        """
        nodal = _with_ground(solution, self.grounded_node)
        electrode = nodal[:, self.electrode_nodes]
        shift = electrode.mean(axis=1, keepdims=True)
        return nodal - shift, electrode - shift

    def contact_forms(self, first: jax.Array, second: jax.Array) -> jax.Array:
        """Zeros: point electrodes have no contact impedance, so no electrode terms.

        Arguments:
            first: (n, k) system solutions; only its shape and dtype are used.
            second: (n, k) system solutions; unused.

        Returns:
            (k, L) zeros, in the dtype of `first`.
        """
        return jnp.zeros((first.shape[1], self.n_electrodes), first.dtype)


ElectrodeSystem = CompleteElectrodeSystem | PointElectrodeSystem


@dataclass(frozen=True)
class _Stiffness:
    """The stiffness part shared by both systems: unit element matrices, the pattern (with
    any extra entries), and the gather table that sums element entries into its slots."""

    pattern: SparsityPattern
    gradients: np.ndarray
    unit: np.ndarray
    table: np.ndarray
    extra_slots: np.ndarray

    @classmethod
    def from_mesh(
        cls, mesh: Mesh, unknown_of_node: np.ndarray, extra_rows: np.ndarray, extra_cols: np.ndarray, size: int
    ) -> _Stiffness:
        gradients = basis_gradients(mesh)
        unit = mesh.element_areas[:, None, None] * np.einsum("exi,exj->eij", gradients, gradients)
        unknowns = unknown_of_node[mesh.triangles]
        rows = np.repeat(unknowns, 3, axis=1).ravel()
        cols = np.tile(unknowns, 3).ravel()
        # Entries of a grounded node have an out-of-range index: they stay out of the pattern.
        kept = (rows < size) & (cols < size)
        pattern, slots = SparsityPattern.from_entries(
            np.concatenate([rows[kept], extra_rows]), np.concatenate([cols[kept], extra_cols]), size
        )
        n_kept = np.count_nonzero(kept)
        table = _gather_table(slots[:n_kept], pattern.nnz)  # indices into the kept entries
        flat_index = np.append(np.flatnonzero(kept), rows.size)  # ... into all E * 9, pad last
        return cls(pattern, gradients, unit.reshape(-1, 9), flat_index[table], slots[n_kept:])


def _stiffness_values(conductivity: jax.Array, unit_stiffness: np.ndarray, table: np.ndarray) -> jax.Array:
    stiffness = (conductivity[:, None] * jnp.asarray(unit_stiffness, conductivity.dtype)).ravel()
    # A gather and a row sum: far faster than a scatter-add of E * 9 entries on CPU.
    return jnp.concatenate([stiffness, jnp.zeros(1, conductivity.dtype)])[table].sum(axis=1)


def _unknown_of_node(n_nodes: int, grounded: int, size: int) -> np.ndarray:
    """The unknown of each node: nodes after the grounded one move up by one; the grounded
    node maps to `size`, out of range, so its entries are dropped."""
    index = np.arange(n_nodes)
    unknown = index - (index > grounded)
    unknown[grounded] = size
    return unknown


def _with_ground(nodal_unknowns: jax.Array, grounded: int) -> jax.Array:
    """(k, N) nodal potentials from the (N - 1, k) nodal unknowns, 0 at the grounded node."""
    zero = jnp.zeros_like(nodal_unknowns[:1])
    return jnp.concatenate([nodal_unknowns[:grounded], zero, nodal_unknowns[grounded:]]).T


def _midpoint_node(mesh: Mesh, chain: np.ndarray) -> int:
    steps = np.linalg.norm(np.diff(mesh.nodes[chain], axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    return int(chain[np.argmin(np.abs(arc - arc[-1] / 2))])


def _gather_table(slots: np.ndarray, n_slots: int) -> np.ndarray:
    """(n_slots, k) indices of the entries that land in each slot, padded with len(slots)."""
    order = np.argsort(slots, kind="stable")
    counts = np.bincount(slots, minlength=n_slots)
    rank = np.arange(len(slots)) - np.repeat(np.cumsum(counts) - counts, counts)
    table = np.full((n_slots, max(counts.max(), 1)), len(slots))
    table[slots[order], rank] = order
    return table
