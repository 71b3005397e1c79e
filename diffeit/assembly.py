"""Finite-element assembly of the complete electrode model on P1 triangles.

Unknowns: the N nodal potentials, then the electrode potentials U_0 .. U_(L-2); U_(L-1) is
grounded (fixed to 0 and dropped), which makes the system symmetric positive definite. With
z_l the contact impedance of electrode l (ohm m) and e_l its boundary segment:

    [K(sigma) + B   C] [u]   [0]
    [C^T            D] [U] = [I]

    K_ij  = sum_e sigma_e int_e grad phi_i . grad phi_j
    B_ij  = sum_l (1/z_l) int_{e_l} phi_i phi_j
    C_il  = -(1/z_l) int_{e_l} phi_i
    D_ll  = |e_l| / z_l

The geometry is computed once with NumPy; the values are a traced JAX function of sigma and z.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .linear_solve import SparsityPattern
from .mesh import Mesh


def basis_gradients(mesh: Mesh) -> np.ndarray:
    """(E, 2, 3) gradients of the three P1 basis functions of each triangle, in 1/m."""
    corners = mesh.nodes[mesh.triangles]  # (E, 3, 2)
    # grad phi_k is the opposite edge x_(k+1) - x_(k+2) turned by -90 degrees, over twice the area.
    opposite = np.roll(corners, -1, axis=1) - np.roll(corners, -2, axis=1)
    gradients = np.stack([opposite[:, :, 1], -opposite[:, :, 0]], axis=1)
    return gradients / (2 * mesh.element_areas[:, None, None])


@dataclass(frozen=True, eq=False)
class CompleteElectrodeSystem:
    """The fixed structure of the grounded complete-electrode-model matrix of one mesh.

    `values(sigma, z)` returns the (nnz,) matrix values on `pattern`. Static data for JAX.
    """

    pattern: SparsityPattern
    n_nodes: int
    n_electrodes: int
    triangles: np.ndarray  # (E, 3) node indices
    element_areas: np.ndarray  # (E,) m^2
    gradients: np.ndarray  # (E, 2, 3) basis function gradients, 1/m
    unit_stiffness: np.ndarray  # (E, 9): area * grad phi_i . grad phi_j, row-major
    stiffness_table: np.ndarray  # (nnz, k): flat indices into unit_stiffness summed per slot, E*9 pads
    electrode_weights: np.ndarray  # (C,) geometric integral of each electrode entry, m
    electrode_of_entry: np.ndarray  # (C,) the electrode whose 1/z scales the entry
    electrode_slots: np.ndarray  # (C,)

    @classmethod
    def from_mesh(cls, mesh: Mesh) -> CompleteElectrodeSystem:
        n_nodes, n_electrodes = mesh.n_nodes, mesh.n_electrodes
        gradients = basis_gradients(mesh)
        unit = mesh.element_areas[:, None, None] * np.einsum("exi,exj->eij", gradients, gradients)
        stiffness_rows = np.repeat(mesh.triangles, 3, axis=1)
        stiffness_cols = np.tile(mesh.triangles, 3)

        rows, cols, weights, owner = [], [], [], []
        for l, chain in enumerate(mesh.electrodes):
            a, b = chain[:-1], chain[1:]
            length = np.linalg.norm(mesh.nodes[b] - mesh.nodes[a], axis=1)
            u = n_nodes + l  # row of U_l (dropped below when l is the grounded electrode)
            entries = [
                (a, a, length / 3),
                (b, b, length / 3),
                (a, b, length / 6),
                (b, a, length / 6),
                (a, u, -length / 2),
                (u, a, -length / 2),
                (b, u, -length / 2),
                (u, b, -length / 2),
                (u, u, length),
            ]
            for r, c, w in entries:
                r, c, w = np.broadcast_arrays(r, c, w)
                rows.append(r)
                cols.append(c)
                weights.append(w)
                owner.append(np.full(len(w), l))
        rows, cols, weights, owner = map(np.concatenate, (rows, cols, weights, owner))
        size = n_nodes + n_electrodes - 1
        kept = (rows < size) & (cols < size)
        rows, cols, weights, owner = rows[kept], cols[kept], weights[kept], owner[kept]

        pattern, slots = SparsityPattern.from_entries(
            np.concatenate([stiffness_rows.ravel(), rows]),
            np.concatenate([stiffness_cols.ravel(), cols]),
            size,
        )
        n_stiffness = stiffness_rows.size
        return cls(
            pattern=pattern,
            n_nodes=n_nodes,
            n_electrodes=n_electrodes,
            triangles=mesh.triangles,
            element_areas=mesh.element_areas,
            gradients=gradients,
            unit_stiffness=unit.reshape(-1, 9),
            stiffness_table=_gather_table(slots[:n_stiffness], pattern.nnz),
            electrode_weights=weights,
            electrode_of_entry=owner,
            electrode_slots=slots[n_stiffness:],
        )

    def values(self, conductivity: jax.Array, contact_impedance: jax.Array) -> jax.Array:
        """(nnz,) matrix values for element-wise `conductivity` (E,) in S/sq and per-electrode
        `contact_impedance` (L,) in ohm m."""
        dtype = jnp.result_type(conductivity, contact_impedance)
        stiffness = (conductivity[:, None] * jnp.asarray(self.unit_stiffness, dtype)).ravel()
        # A gather and a row sum: far faster than a scatter-add of E * 9 entries on CPU.
        values = jnp.concatenate([stiffness, jnp.zeros(1, dtype)])[self.stiffness_table].sum(axis=1)
        electrode = jnp.asarray(self.electrode_weights, dtype) / contact_impedance[self.electrode_of_entry]
        return values.at[self.electrode_slots].add(electrode)

    def current_rhs(self, currents: jax.Array) -> jax.Array:
        """(n, k) right-hand sides for k electrode current patterns `currents` (k, L) in A."""
        nodal = jnp.zeros((self.n_nodes, currents.shape[0]), currents.dtype)
        return jnp.concatenate([nodal, currents[:, : self.n_electrodes - 1].T])

    def split(self, solution: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Nodal (k, N) and electrode (k, L) potentials from solutions (n, k), shifted so the
        electrode potentials of each solution sum to zero."""
        electrode = jnp.concatenate([solution[self.n_nodes :], jnp.zeros_like(solution[:1])]).T
        shift = electrode.mean(axis=1, keepdims=True)
        return solution[: self.n_nodes].T - shift, electrode - shift


jax.tree_util.register_static(CompleteElectrodeSystem)


def _gather_table(slots: np.ndarray, n_slots: int) -> np.ndarray:
    """(n_slots, k) indices of the entries that land in each slot, padded with len(slots)."""
    order = np.argsort(slots, kind="stable")
    counts = np.bincount(slots, minlength=n_slots)
    rank = np.arange(len(slots)) - np.repeat(np.cumsum(counts) - counts, counts)
    table = np.full((n_slots, max(counts.max(), 1)), len(slots))
    table[slots[order], rank] = order
    return table
