"""The complete-electrode-model forward model: conductivity in, boundary voltages out."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._messages import name_indices
from .assembly import CompleteElectrodeSystem
from .linear_solve import AbstractLinearSolver, HostSparse, relative_residual, solve_spd
from .mesh import Mesh
from .protocol import Protocol


class Potentials(NamedTuple):
    """The solution of every drive of a protocol.

    - `nodal`: (n_drives, N) potentials at the mesh nodes, volts.
    - `electrode`: (n_drives, L) electrode potentials U_l, volts, summing to zero per drive.
    - `relative_residual`: (n_drives,) ||A x - b|| / ||b|| of the linear solve.
    """

    nodal: jax.Array
    electrode: jax.Array
    relative_residual: jax.Array


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _name_elements(mask: np.ndarray) -> str:
    return f"{np.count_nonzero(mask)} element(s) {name_indices(np.flatnonzero(mask))}"


@jax.tree_util.register_pytree_node_class
@dataclass(frozen=True, eq=False)
class ForwardModel:
    """Complete electrode model on a P1 triangle mesh of a sheet.

    `ForwardModel(mesh, protocol, contact_impedance=0.01, drive_current=1e-3)`

    Conventions: sheet conductivity sigma in S/sq, piecewise constant per element; contact
    impedance z in ohm m (2D), a scalar or one per electrode; drive current in amperes, the
    protocol's drive patterns are multiples of it (voltages and Jacobians are linear in it);
    voltages in volts; electrode potentials sum to zero for every drive.

    `measure`, `potentials` and `jacobian` are pure JAX functions of the conductivity (and of
    an optional contact impedance overriding the model's): jit, grad, jvp, vmap and jacrev
    work on them. On concrete inputs they raise `ValueError` for a conductivity of the wrong
    shape, non-finite or non-positive values.

    A model is immutable and a JAX pytree whose one leaf is `contact_impedance`; it hashes by
    identity, so `jax.jit(model.measure)` works.
    """

    mesh: Mesh
    protocol: Protocol
    contact_impedance: jax.Array
    drive_current: float
    solver: AbstractLinearSolver
    system: CompleteElectrodeSystem = field(repr=False)

    def __init__(
        self,
        mesh: Mesh,
        protocol: Protocol,
        contact_impedance: float | jax.Array = 0.01,
        *,
        drive_current: float = 1e-3,
        solver: AbstractLinearSolver | None = None,
    ) -> None:
        if protocol.n_electrodes != mesh.n_electrodes:
            raise ValueError(
                f"the protocol addresses {protocol.n_electrodes} electrodes; the mesh has {mesh.n_electrodes}"
            )
        if not (np.isfinite(drive_current) and drive_current != 0):
            raise ValueError(f"drive_current must be finite and nonzero (amperes); got {drive_current}")
        set_field = object.__setattr__  # frozen: fields are set once, here
        set_field(self, "mesh", mesh)
        set_field(self, "protocol", protocol)
        set_field(self, "drive_current", float(drive_current))
        set_field(self, "solver", HostSparse() if solver is None else solver)
        set_field(self, "system", CompleteElectrodeSystem.from_mesh(mesh))
        set_field(self, "contact_impedance", self._checked_contact_impedance(contact_impedance))

    def tree_flatten(self) -> tuple[tuple[jax.Array], tuple]:
        return (self.contact_impedance,), (self.mesh, self.protocol, self.drive_current, self.solver, self.system)

    @classmethod
    def tree_unflatten(cls, static: tuple, leaves: tuple[jax.Array]) -> ForwardModel:
        model = object.__new__(cls)
        names = ("mesh", "protocol", "drive_current", "solver", "system", "contact_impedance")
        for name, value in zip(names, static + leaves, strict=True):
            object.__setattr__(model, name, value)
        return model

    @property
    def n_measurements(self) -> int:
        return self.protocol.n_measurements

    @property
    def n_elements(self) -> int:
        return self.mesh.n_elements

    def potentials(self, conductivity: jax.Array, contact_impedance: jax.Array | None = None) -> Potentials:
        """Nodal and electrode potentials of every drive (see `Potentials`).

        **Arguments:**

        - `conductivity`: (E,) sheet conductivity per element, S/sq.
        - `contact_impedance`: scalar or (L,) in ohm m; default the model's.
        """
        return _potentials(self, *self._checked_inputs(conductivity, contact_impedance))

    def measure(self, conductivity: jax.Array, contact_impedance: jax.Array | None = None) -> jax.Array:
        """(n_measurements,) voltages of the protocol, volts, for conductivity (E,) in S/sq."""
        return _measure(self, *self._checked_inputs(conductivity, contact_impedance))

    def jacobian(self, conductivity: jax.Array, contact_impedance: jax.Array | None = None) -> jax.Array:
        """(n_measurements, E) derivative of `measure` with respect to the conductivity, V/(S/sq).

        The fast path: one factorisation and one solve per electrode (unit current into
        electrode l, out of the grounded one) give every drive and measurement field; then
        dV/dsigma_e = -area_e grad u_drive . grad u_measure (reciprocity), an element-wise
        contraction. Equals `jax.jacrev(model.measure)` to rounding error.
        """
        return _jacobian(self, *self._checked_inputs(conductivity, contact_impedance))

    def _checked_inputs(self, conductivity, contact_impedance) -> tuple[jax.Array, jax.Array]:
        sigma = jnp.asarray(conductivity)
        if not jnp.issubdtype(sigma.dtype, jnp.floating):
            sigma = sigma.astype(float)
        if sigma.shape != (self.n_elements,):
            raise ValueError(
                f"conductivity has shape {sigma.shape}; expected ({self.n_elements},), one value per element"
            )
        if _is_concrete(conductivity):
            values = np.asarray(sigma)
            if not np.all(np.isfinite(values)):
                raise ValueError(f"conductivity is not finite (NaN or inf) at {_name_elements(~np.isfinite(values))}")
            if np.any(values <= 0):
                raise ValueError(f"conductivity must be positive (S/sq); it is <= 0 at {_name_elements(values <= 0)}")
        z = self.contact_impedance if contact_impedance is None else self._checked_contact_impedance(contact_impedance)
        return sigma, z.astype(sigma.dtype)

    def _checked_contact_impedance(self, contact_impedance) -> jax.Array:
        n = self.mesh.n_electrodes
        z = jnp.asarray(contact_impedance)
        if not jnp.issubdtype(z.dtype, jnp.floating):
            z = z.astype(float)
        if z.shape not in ((), (n,)):
            raise ValueError(f"contact_impedance has shape {z.shape}; expected a scalar or ({n},), one per electrode")
        if _is_concrete(contact_impedance):
            values = np.asarray(z)
            if not np.all(np.isfinite(values)) or np.any(values <= 0):
                raise ValueError(f"contact_impedance must be finite and positive (ohm m); got {values}")
        return jnp.broadcast_to(z, (n,))


# The computations, jitted once per model (hashed by identity), shape and dtype. The methods
# above validate concrete inputs first with messages naming the elements; under an outer jit or
# vmap only `_positive` can see the values.


def _positive(sigma: jax.Array, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The value checks of `_checked_inputs` for traced inputs: an error at run time, never a
    silent NaN or a solve of an indefinite system."""
    sigma = eqx.error_if(sigma, ~jnp.all(jnp.isfinite(sigma) & (sigma > 0)), "conductivity must be finite and positive")
    z = eqx.error_if(z, ~jnp.all(jnp.isfinite(z) & (z > 0)), "contact_impedance must be finite and positive")
    return sigma, z


@jax.jit
def _potentials(model: ForwardModel, sigma: jax.Array, z: jax.Array) -> Potentials:
    system = model.system
    sigma, z = _positive(sigma, z)
    values = system.values(sigma, z)
    currents = model.drive_current * jnp.asarray(model.protocol.drive, sigma.dtype)
    rhs = system.current_rhs(currents)
    solution = solve_spd(system.pattern, values, rhs, model.solver)
    solution = eqx.error_if(
        solution,
        ~jnp.all(jnp.isfinite(solution)),
        "the linear solve failed (non-finite potentials): check the mesh and the conductivity",
    )
    nodal, electrode = system.split(solution)
    residual = relative_residual(system.pattern, values, solution, rhs)
    return Potentials(nodal, electrode, residual)


@jax.jit
def _measure(model: ForwardModel, sigma: jax.Array, z: jax.Array) -> jax.Array:
    electrode = _potentials(model, sigma, z).electrode
    weights = jnp.asarray(model.protocol.measure, electrode.dtype)
    return jnp.sum(weights * electrode[model.protocol.drive_index], axis=-1)


@jax.jit
def _jacobian(model: ForwardModel, sigma: jax.Array, z: jax.Array) -> jax.Array:
    system, protocol = model.system, model.protocol
    sigma, z = _positive(sigma, z)
    n_free = system.n_electrodes - 1
    unit_currents = jnp.eye(n_free, system.n_electrodes, dtype=sigma.dtype)
    basis = solve_spd(system.pattern, system.values(sigma, z), system.current_rhs(unit_currents), model.solver)
    drives = model.drive_current * jnp.asarray(protocol.drive[:, :n_free], sigma.dtype)
    # A reading m of potentials that sum to zero equals one of m - mean(m), a zero-sum pattern.
    patterns = protocol.measure_patterns - protocol.measure_patterns.mean(axis=1, keepdims=True)
    patterns = jnp.asarray(patterns[:, :n_free], sigma.dtype)
    nodal = basis[: system.n_nodes]
    drive_x, drive_y = _element_gradients(system, nodal @ drives.T)  # each (n_drives, E)
    measure_x, measure_y = _element_gradients(system, nodal @ patterns.T)  # each (n_patterns, E)
    products = (
        drive_x[protocol.drive_index] * measure_x[protocol.pattern_index]
        + drive_y[protocol.drive_index] * measure_y[protocol.pattern_index]
    )
    return -jnp.asarray(system.element_areas, sigma.dtype) * products


def _element_gradients(system: CompleteElectrodeSystem, fields: jax.Array) -> tuple[jax.Array, jax.Array]:
    """x and y components, (k, E) each, of the gradients of k nodal fields (N, k) per element.

    Three broadcast products rather than a batched (2 x 3) @ (3 x k) matmul per element, which
    XLA runs slowly on CPU."""
    gradients = jnp.asarray(system.gradients, fields.dtype)  # (E, 2, 3)
    corners = [fields[system.triangles[:, i]].T for i in range(3)]  # each (k, E)
    x = sum(gradients[:, 0, i] * corners[i] for i in range(3))
    y = sum(gradients[:, 1, i] * corners[i] for i in range(3))
    return x, y
