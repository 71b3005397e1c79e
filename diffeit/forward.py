"""The complete-electrode-model forward model: conductivity in, boundary voltages out."""

from __future__ import annotations

import functools
import warnings
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import IdentityModule, is_concrete
from ._messages import name_indices
from ._precision import PrecisionWarning, ensure_float64
from .assembly import CompleteElectrodeSystem, ElectrodeSystem, PointElectrodeSystem
from .linear_solve import (
    AbstractLinearSolver,
    HostSparse,
    backward_error,
    relative_residual,
    solve_spd,
    solve_spd_with_result,
    solver_named,
)
from .mesh import Mesh
from .protocol import Protocol
from .results import RESULTS


class Potentials(eqx.Module):
    """The solution of every drive of a protocol: nodal and electrode potentials, and checks.

    `ForwardModel.potentials` returns one. An equinox Module, as every result type.

    Attributes:
        nodal: (n_drives, N) potentials at the mesh nodes, volts.
        electrode: (n_drives, L) electrode potentials U_l, volts, summing to zero per drive.
        relative_residual: (n_drives,) ||A x - b|| / ||b|| of the linear solve.
        backward_error: (n_drives,) componentwise backward error of the linear solve (see
            `diffeit.linear_solve.backward_error`): near machine epsilon for a sound solve even
            when extreme contact impedance or contrast makes the relative residual large.
        result: The solve's `diffeit.results.RESULTS` code: `linear_solve_not_converged` when
            a conjugate-gradient solve with `throw=False` stopped at its iteration limit.
    """

    nodal: jax.Array
    electrode: jax.Array
    relative_residual: jax.Array
    backward_error: jax.Array
    result: RESULTS


# float32 is an opt-in for throughput; beyond this estimated relative voltage error it is not.
FLOAT32_TOLERANCE = 1e-3

JacobianVariable = Literal["conductivity", "log_conductivity", "contact_impedance", "electrode_shift"]


def _name_elements(mask: np.ndarray) -> str:
    return f"{np.count_nonzero(mask)} element(s) {name_indices(np.flatnonzero(mask))}"


class ForwardModel(IdentityModule):
    """Complete electrode model on a P1 triangle mesh of a sheet: conductivity in, voltages out.

    Solves every drive of `protocol` on `mesh` for a sheet conductivity sigma (S/sq, piecewise
    constant per element) and returns the protocol's readings (volts), the potentials, or the
    Jacobian. Contact impedance z is in ohm m (2D); the protocol's drive patterns are multiples
    of the drive current (amperes), so voltages and Jacobians are linear in it; electrode
    potentials sum to zero for every drive. The equations are in docs/science.md#electrode-model.

    `measure`, `potentials` and `jacobian` are pure JAX functions of the conductivity (and of
    an optional contact impedance overriding the model's): jit, grad, jvp, vmap and jacrev
    work on them, and `jax.jit(model.measure)` works. Precision follows the conductivity's
    dtype: float64 by default, float32 on request (docs/conventions.md#precision). A model is
    an immutable `equinox.Module` whose one array leaf is `contact_impedance`; the rest is
    static and compared by content, so a second model on an equal mesh compiles nothing for
    `measure`, `potentials` and `jacobian` while its protocol's shapes agree: the protocol's
    arrays are arguments of their programs (docs/conventions.md#static-data-and-pytrees). A
    model whose electrodes are moved along the boundary (`electrode_shift`, as a calibration
    fits them) holds the shift as a second array leaf, and is differentiable in it.

    Arguments:
        mesh: The triangle mesh of the sheet, with its electrodes.
        protocol: The drives and readings; it must address the mesh's number of electrodes.
        contact_impedance: z, ohm m, a scalar or (L,) one per electrode, finite and positive.
        drive_current: The current of a unit drive pattern, amperes (default 1 mA), finite
            and nonzero.
        solver: A backend of `diffeit.linear_solve` or its name: "host_sparse" (SciPy on the
            host, the CPU default, also for None), "dense_cholesky" (small meshes,
            accelerators) or "conjugate_gradient" (matrix-free, large meshes on accelerators).
        electrode_model: "complete", or "point" (current through one node per electrode, no
            contact impedance; see `diffeit.assembly.PointElectrodeSystem`).
        electrode_shift: How far each electrode lies from the mesh's electrode, metres along
            the boundary in the direction of its nodes (counter-clockwise round the outer
            boundary): (L,) moves each electrode, (L, 2) its start and end apart (a width
            change: end minus start). None (default): the mesh's electrodes. Complete model
            only. The ends may move up to `electrode_margin`.
        electrode_margin: How far, metres, the ends of the electrodes may move along the
            boundary (a static bound: the matrix holds the boundary nodes within it). Default:
            the largest shift given, or 0.

    Attributes:
        mesh: The mesh (static).
        protocol: The protocol (static).
        contact_impedance: (L,) z, ohm m, an array leaf.
        electrode_shift: (L, 2) how far each electrode's start and end lie from the mesh's,
            metres along the boundary, an array leaf; or None.
        drive_current: Amperes (static).
        solver: The linear-solver backend (static).

    Raises:
        ValueError: For a protocol and mesh with different numbers of electrodes, a drive
            current that is zero or not finite, an unknown solver or electrode model, a
            contact impedance of the wrong shape, not finite or not positive; an electrode
            shift of the wrong shape, not finite, beyond the margin, leaving an electrode no
            length, or given to the point model.

    Warns:
        diffeit.PrecisionWarning: When building the first model turns on `jax_enable_x64`.
    """

    mesh: Mesh = eqx.field(static=True)
    protocol: Protocol = eqx.field(static=True)
    contact_impedance: jax.Array
    electrode_shift: jax.Array | None
    drive_current: float = eqx.field(static=True)
    solver: AbstractLinearSolver = eqx.field(static=True)
    system: ElectrodeSystem = eqx.field(static=True, repr=False)

    def __init__(
        self,
        mesh: Mesh,
        protocol: Protocol,
        contact_impedance: float | jax.Array = 0.01,
        *,
        drive_current: float = 1e-3,
        solver: AbstractLinearSolver | str | None = None,
        electrode_model: Literal["complete", "point"] = "complete",
        electrode_shift: jax.Array | None = None,
        electrode_margin: float | None = None,
    ) -> None:
        ensure_float64()
        if protocol.n_electrodes != mesh.n_electrodes:
            raise ValueError(
                f"the protocol addresses {protocol.n_electrodes} electrodes; the mesh has {mesh.n_electrodes}"
            )
        if not (np.isfinite(drive_current) and drive_current != 0):
            raise ValueError(f"drive_current must be finite and nonzero (amperes); got {drive_current}")
        self.mesh = mesh
        self.protocol = protocol
        self.drive_current = float(drive_current)
        if isinstance(solver, str):
            solver = solver_named(solver)
        elif solver is None:
            solver = HostSparse()
        elif not isinstance(solver, AbstractLinearSolver):
            raise ValueError(f"solver must be a diffeit.linear_solve backend or its name; got {solver!r}")
        if electrode_model not in ("complete", "point"):
            raise ValueError(f"electrode_model must be 'complete' or 'point'; got {electrode_model!r}")
        self.solver = solver
        self.contact_impedance = _checked_contact_impedance(contact_impedance, mesh.n_electrodes)
        if electrode_shift is None and electrode_margin is None:
            self.system = _system(mesh, electrode_model, None)
            self.electrode_shift = None
            return
        if electrode_model != "complete":
            raise ValueError("electrode_shift and electrode_margin need the complete electrode model")
        shift = _checked_electrode_shift(electrode_shift, mesh.n_electrodes)
        if electrode_margin is None:
            electrode_margin = float(np.max(np.abs(shift)))
        self.system = _system(mesh, "complete", float(electrode_margin))
        self.electrode_shift = _within_margin(shift, self.system)

    def replace(
        self,
        *,
        protocol: Protocol | None = None,
        contact_impedance: float | jax.Array | None = None,
        electrode_margin: float | None = None,
    ) -> ForwardModel:
        """This model with another protocol, contact impedance or electrode margin.

        The mesh, the electrodes (their shift, when moved), the drive current, the solver and
        the electrode model are this model's.

        Arguments:
            protocol: The drives and readings; None keeps this model's.
            contact_impedance: z, ohm m, a scalar or (L,); None keeps this model's.
            electrode_margin: How far, metres, the electrodes' ends may move from the mesh's
                (complete model only): it frees a model's electrodes to move, or bounds a moved
                model's anew. None keeps this model's (and a model whose electrodes may not
                move stays so).

        Returns:
            The new model. It compiles nothing new where its electrode margin and its
            protocol's shapes are this model's.

        Raises:
            ValueError: As the constructor, for the values given.
        """
        moved = {}
        if self.electrode_shift is not None or electrode_margin is not None:
            moved = {
                "electrode_shift": self.electrode_shift,
                "electrode_margin": self.system.electrode_margin if electrode_margin is None else electrode_margin,
            }
        return ForwardModel(
            self.mesh,
            self.protocol if protocol is None else protocol,
            self.contact_impedance if contact_impedance is None else contact_impedance,
            drive_current=self.drive_current,
            solver=self.solver,
            electrode_model="point" if isinstance(self.system, PointElectrodeSystem) else "complete",
            **moved,
        )

    @property
    def n_measurements(self) -> int:
        """M, the number of readings of the protocol."""
        return self.protocol.n_measurements

    @property
    def n_elements(self) -> int:
        """E, the number of elements of the mesh."""
        return self.mesh.n_elements

    def potentials(self, conductivity: jax.Array, contact_impedance: jax.Array | None = None) -> Potentials:
        """Nodal and electrode potentials of every drive.

        Arguments:
            conductivity: (E,) sheet conductivity per element, S/sq, finite and positive.
            contact_impedance: Scalar or (L,), ohm m, overriding the model's; None uses the
                model's.

        Returns:
            The `Potentials`, in the conductivity's dtype.

        Raises:
            ValueError: For a conductivity or contact impedance of the wrong shape, and (on
                concrete input) not finite or not positive. Under an outer jit or vmap, bad
                values and a failed linear solve raise a runtime error (`equinox.error_if`)
                instead.

        Warns:
            diffeit.PrecisionWarning: For a concrete float32 call whose estimated relative
                voltage error exceeds 1e-3 (docs/conventions.md#precision).
        """
        sigma, z = self._checked_inputs(conductivity, contact_impedance)
        self._check_precision(conductivity, sigma, z)
        return _potentials(_Solves.of(self), self.protocol.drive, sigma, z)

    def measure(self, conductivity: jax.Array, contact_impedance: jax.Array | None = None) -> jax.Array:
        """The protocol's readings, volts, for a conductivity.

        Arguments:
            conductivity: (E,) sheet conductivity per element, S/sq, finite and positive.
            contact_impedance: Scalar or (L,), ohm m, overriding the model's; None uses the
                model's.

        Returns:
            (n_measurements,) voltages, volts, in protocol order and sign, in the
            conductivity's dtype.

        Raises:
            ValueError: As `potentials`.

        Warns:
            diffeit.PrecisionWarning: As `potentials`.
        """
        sigma, z = self._checked_inputs(conductivity, contact_impedance)
        self._check_precision(conductivity, sigma, z)
        return _measure(_Solves.of(self), _ProtocolArrays.of(self.protocol), sigma, z)

    def jacobian(
        self,
        conductivity: jax.Array,
        contact_impedance: jax.Array | None = None,
        *,
        wrt: JacobianVariable = "conductivity",
    ) -> jax.Array:
        """The derivative of `measure`, by the fast adjoint path.

        One factorisation and L-1 solves give every drive and measurement field, and
        reciprocity gives the derivatives (docs/science.md#jacobian); the result equals
        `jax.jacrev` of `measure` to rounding error.

        Arguments:
            conductivity: (E,) sheet conductivity per element, S/sq, finite and positive.
            contact_impedance: Scalar or (L,), ohm m, overriding the model's; None uses the
                model's.
            wrt: What to differentiate by: "conductivity", "log_conductivity",
                "contact_impedance" or "electrode_shift" (a model built with an
                `electrode_shift` or `electrode_margin`).

        Returns:
            For `wrt="conductivity"`, (n_measurements, E) in V/(S/sq); for
            `wrt="log_conductivity"`, (n_measurements, E) in V, dV/d(ln sigma) =
            sigma dV/dsigma; for `wrt="contact_impedance"`, (n_measurements, L) in V/(ohm m),
            one column per electrode (sum the columns for a shared scalar z), zero for point
            electrodes; for `wrt="electrode_shift"`, (n_measurements, L, 2) in V/m, by the
            shift of each electrode's start and end along the boundary (the shape of
            `electrode_shift`): an end moving outward lengthens the electrode. It costs no
            solve beyond the others': the electrode terms' derivative in the ends, contracted
            with the same fields.

        Raises:
            ValueError: For an unknown `wrt`, `wrt="electrode_shift"` of a model whose
                electrodes may not move, and as `potentials` for the inputs.
        """
        if wrt not in JacobianVariable.__args__:
            raise ValueError(f"wrt must be one of {JacobianVariable.__args__}; got {wrt!r}")
        if wrt == "electrode_shift" and self.electrode_shift is None:
            raise ValueError(
                'wrt="electrode_shift" needs a model whose electrodes may move: build it with electrode_margin '
                "(metres) or an electrode_shift"
            )
        sigma, z = self._checked_inputs(conductivity, contact_impedance)
        return _jacobian(_Solves.of(self), _ProtocolArrays.of(self.protocol), sigma, z, wrt)

    def measure_and_jacobian(
        self, conductivity: jax.Array, contact_impedance: jax.Array | None = None
    ) -> tuple[jax.Array, jax.Array]:
        """`measure` and `jacobian` (in the conductivity) together, from the Jacobian's solves.

        The adjoint path's L-1 solves give every drive's field too, so the readings cost no
        solve of their own: for fits that need both at every step (the disc fit of
        `diffeit.touches`). Equal to `measure` and `jacobian` to rounding.

        Arguments:
            conductivity: (E,) sheet conductivity per element, S/sq, finite and positive.
            contact_impedance: Scalar or (L,), ohm m, overriding the model's; None uses the
                model's.

        Returns:
            (n_measurements,) voltages, volts, and (n_measurements, E) their derivative in the
            conductivity, V/(S/sq).

        Raises:
            ValueError: As `potentials` for the inputs.
        """
        sigma, z = self._checked_inputs(conductivity, contact_impedance)
        return _measure_and_jacobian(_Solves.of(self), _ProtocolArrays.of(self.protocol), sigma, z)

    def _checked_inputs(self, conductivity, contact_impedance) -> tuple[jax.Array, jax.Array]:
        sigma = jnp.asarray(conductivity)
        # An explicit dtype also drops JAX's weak type (jnp.full(n, 1.0)), which would compile
        # again. Each conversion costs tens of microseconds a call: only where needed.
        if sigma.weak_type or not jnp.issubdtype(sigma.dtype, jnp.floating):
            sigma = jnp.asarray(sigma, dtype=sigma.dtype if jnp.issubdtype(sigma.dtype, jnp.floating) else float)
        if sigma.shape != (self.n_elements,):
            raise ValueError(
                f"conductivity has shape {sigma.shape}; expected ({self.n_elements},), one value per element"
            )
        if is_concrete(conductivity):
            values = np.asarray(sigma)
            if not np.all(np.isfinite(values)):
                raise ValueError(f"conductivity is not finite (NaN or inf) at {_name_elements(~np.isfinite(values))}")
            if np.any(values <= 0):
                raise ValueError(f"conductivity must be positive (S/sq); it is <= 0 at {_name_elements(values <= 0)}")
        if contact_impedance is None:
            z = self.contact_impedance
        else:
            z = _checked_contact_impedance(contact_impedance, self.mesh.n_electrodes)
        return sigma, z if z.dtype == sigma.dtype and not z.weak_type else z.astype(sigma.dtype)

    def _check_precision(self, conductivity, sigma: jax.Array, z: jax.Array) -> None:
        """Warn when a concrete float32 call cannot hold `FLOAT32_TOLERANCE` (see the class)."""
        leaves = (conductivity, z, *_ends(_Solves.of(self), z.dtype))
        if sigma.dtype != jnp.float32 or not all(map(is_concrete, leaves)):
            return
        error = float(_float32_voltage_error(_Solves.of(self), _ProtocolArrays.of(self.protocol), sigma, z))
        if not error <= FLOAT32_TOLERANCE:
            warnings.warn(
                f"float32 voltages are estimated to be off by {error:.2g} (relative 2-norm), more than "
                f"{FLOAT32_TOLERANCE:g}: use float64 for this case",
                PrecisionWarning,
                stacklevel=3,
            )


@functools.lru_cache(maxsize=32)
def _system(
    mesh: Mesh, electrode_model: str, electrode_margin: float | None
) -> CompleteElectrodeSystem | PointElectrodeSystem:
    """The assembled electrode system of `mesh`, built once per mesh (by content), electrode
    model and margin: models that differ in protocol, contact impedance or solver share it (a
    calibration builds hundreds)."""
    if electrode_model == "point":
        return PointElectrodeSystem.from_mesh(mesh)
    return CompleteElectrodeSystem.from_mesh(mesh, 0.0 if electrode_margin is None else electrode_margin)


def _checked_contact_impedance(contact_impedance, n: int) -> jax.Array:
    """(n,) contact impedance, ohm m, from a scalar or one value per electrode."""
    z = jnp.asarray(contact_impedance)
    if not jnp.issubdtype(z.dtype, jnp.floating):
        z = z.astype(float)
    if z.shape not in ((), (n,)):
        raise ValueError(f"contact_impedance has shape {z.shape}; expected a scalar or ({n},), one per electrode")
    if is_concrete(contact_impedance):
        values = np.asarray(z)
        if not np.all(np.isfinite(values)) or np.any(values <= 0):
            raise ValueError(f"contact_impedance must be finite and positive (ohm m); got {values}")
    return jnp.broadcast_to(z, (n,)).astype(z.dtype)  # not weak-typed (a Python float's): one compiled key


# The computations, jitted once per mesh, drive current and solver (compared by content), shape
# and dtype (`_Solves`): the protocol's arrays are traced (`_ProtocolArrays`). The methods above
# validate concrete inputs first with messages naming the elements; under an outer jit or vmap
# only `_positive` can see the values.
# equinox.filter_jit, not jax.jit: it waits for the run-time checks (an unconverged solve), so
# that a concrete call raises at the call even while other work is in flight (JAX dispatches
# asynchronously, and a plain jitted call would report the error only where an output is read).


def _checked_electrode_shift(electrode_shift, n: int) -> jax.Array:
    """(n, 2) start and end shifts, m, from (n,) or (n, 2) (None: zeros)."""
    shift = jnp.zeros((n, 2)) if electrode_shift is None else jnp.asarray(electrode_shift, dtype=float)
    if shift.shape == (n,):
        shift = jnp.stack([shift, shift], axis=1)
    if shift.shape != (n, 2):
        raise ValueError(
            f"electrode_shift has shape {shift.shape}; expected ({n},), one per electrode, or ({n}, 2), start and end"
        )
    if is_concrete(shift) and not np.all(np.isfinite(np.asarray(shift))):
        raise ValueError(f"electrode_shift is not finite: {np.asarray(shift)}")
    return shift


def _within_margin(shift: jax.Array, system: CompleteElectrodeSystem) -> jax.Array:
    """The shift, checked: finite, within the margin, every electrode left some length. Concrete
    shifts raise ValueError; traced ones a run-time error."""
    margin, lengths = system.electrode_margin, jnp.asarray(system.electrode_lengths)
    # Rounding of the margin a calibration stores and loads again.
    beyond = jnp.abs(shift) > margin * (1 + 1e-9)
    collapsed = lengths + shift[:, 1] - shift[:, 0] <= 0
    if is_concrete(shift):
        if np.any(beyond):
            raise ValueError(
                f"electrode_shift moves electrode(s) {name_indices(np.flatnonzero(np.any(beyond, axis=1)))} "
                f"further than electrode_margin ({margin} m)"
            )
        if np.any(collapsed):
            raise ValueError(
                f"electrode_shift leaves electrode(s) {name_indices(np.flatnonzero(collapsed))} no length "
                "(its end before its start)"
            )
        return shift
    bad = ~jnp.all(jnp.isfinite(shift)) | jnp.any(beyond) | jnp.any(collapsed)
    return eqx.error_if(shift, bad, "electrode_shift must be finite, within electrode_margin and leave length")


@jax.tree_util.register_pytree_node_class
class _Solves:
    """What a model's solves depend on besides the protocol, the key of their compiled programs
    (with the arrays' shapes): models that differ in their protocol's values alone share them. A
    calibration builds hundreds of models, each with the readout it fitted folded into the
    readings; each had compiled its solves again (15 times in one calibration's `measure`, 7.6 s
    of its 54). A plain pytree, its one leaf the electrode shift: made at every call, an
    `equinox.Module` cost 34 us."""

    def __init__(
        self,
        system: ElectrodeSystem,
        drive_current: float,
        solver: AbstractLinearSolver,
        electrode_shift: jax.Array | None,
    ) -> None:
        self.system = system
        self.drive_current = drive_current
        self.solver = solver
        self.electrode_shift = electrode_shift

    @classmethod
    def of(cls, model: ForwardModel) -> _Solves:
        return cls(model.system, model.drive_current, model.solver, model.electrode_shift)

    def tree_flatten(self) -> tuple[tuple[jax.Array | None], tuple]:
        return (self.electrode_shift,), (self.system, self.drive_current, self.solver)

    @classmethod
    def tree_unflatten(cls, static: tuple, leaves: tuple) -> _Solves:
        return cls(*static, *leaves)


class _ProtocolArrays(NamedTuple):
    """A protocol's arrays (`Protocol` for their meaning), traced by the compiled programs:
    NumPy arrays when built (`of`), JAX arrays (tracers) inside them."""

    drive: np.ndarray | jax.Array  # (n_drives, L)
    measure: np.ndarray | jax.Array  # (M, L)
    drive_index: np.ndarray | jax.Array  # (M,)
    measure_patterns: np.ndarray | jax.Array  # (P, L)
    pattern_index: np.ndarray | jax.Array  # (M,)

    @classmethod
    def of(cls, protocol: Protocol) -> _ProtocolArrays:
        return cls(
            protocol.drive, protocol.measure, protocol.drive_index, protocol.measure_patterns, protocol.pattern_index
        )


def _ends(solves: _Solves, dtype) -> tuple[jax.Array, ...]:
    """The electrode shift to pass to the system, as a tuple: empty for the mesh's electrodes."""
    return () if solves.electrode_shift is None else (solves.electrode_shift.astype(dtype),)


def _values(solves: _Solves, sigma: jax.Array, z: jax.Array) -> jax.Array:
    return solves.system.values(sigma, z, *_ends(solves, sigma.dtype))


def _positive(sigma: jax.Array, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The value checks of `_checked_inputs` for traced inputs: an error at run time, never a
    silent NaN or a solve of an indefinite system."""
    sigma = eqx.error_if(sigma, ~jnp.all(jnp.isfinite(sigma) & (sigma > 0)), "conductivity must be finite and positive")
    z = eqx.error_if(z, ~jnp.all(jnp.isfinite(z) & (z > 0)), "contact_impedance must be finite and positive")
    return sigma, z


@eqx.filter_jit
def _potentials(solves: _Solves, drive: jax.Array, sigma: jax.Array, z: jax.Array) -> Potentials:
    system = solves.system
    sigma, z = _positive(sigma, z)
    values = _values(solves, sigma, z)
    rhs = system.current_rhs(solves.drive_current * drive.astype(sigma.dtype))
    solution, result = solve_spd_with_result(system.pattern, values, rhs, solves.solver)
    solution = eqx.error_if(
        solution,
        ~jnp.all(jnp.isfinite(solution)),
        "the linear solve failed (non-finite potentials): the system is singular or, in float32, too "
        "ill-conditioned for the precision; check the mesh, the conductivity and the contact impedance",
    )
    nodal, electrode = system.split(solution)
    return Potentials(
        nodal=nodal,
        electrode=electrode,
        relative_residual=relative_residual(system.pattern, values, solution, rhs),
        backward_error=backward_error(system.pattern, values, solution, rhs),
        result=result,
    )


@eqx.filter_jit
def _measure(solves: _Solves, protocol: _ProtocolArrays, sigma: jax.Array, z: jax.Array) -> jax.Array:
    return _readings(protocol, _potentials(solves, protocol.drive, sigma, z).electrode)


def _readings(protocol: _ProtocolArrays, electrode: jax.Array) -> jax.Array:
    """(n_measurements,) readings of the protocol from electrode potentials (n_drives, L)."""
    return jnp.sum(protocol.measure.astype(electrode.dtype) * electrode[protocol.drive_index], axis=-1)


@jax.jit  # its one number is read at once (float()), so a run-time error surfaces there
def _float32_voltage_error(solves: _Solves, protocol: _ProtocolArrays, sigma: jax.Array, z: jax.Array) -> jax.Array:
    """Estimated relative 2-norm error of float32 voltages: one step of iterative refinement,
    the residual taken in float64, the correction solved with the float32 system."""
    system = solves.system
    values = _values(solves, sigma, z)
    rhs = system.current_rhs(solves.drive_current * protocol.drive.astype(sigma.dtype))
    solution = solve_spd(system.pattern, values, rhs, solves.solver)
    exact_values = _values(solves, sigma.astype(jnp.float64), z.astype(jnp.float64))
    residual = rhs.astype(jnp.float64) - system.pattern.matvec(exact_values, solution.astype(jnp.float64))
    correction = solve_spd(system.pattern, values, residual.astype(sigma.dtype), solves.solver)
    voltages = _readings(protocol, system.split(solution)[1])
    change = _readings(protocol, system.split(correction)[1])
    return jnp.linalg.norm(change.astype(jnp.float64)) / jnp.linalg.norm(voltages.astype(jnp.float64))


@eqx.filter_jit
def _jacobian(
    solves: _Solves, protocol: _ProtocolArrays, sigma: jax.Array, z: jax.Array, wrt: JacobianVariable
) -> jax.Array:
    sigma, z = _positive(sigma, z)
    return _jacobian_of_fields(solves, protocol, sigma, z, wrt, *_adjoint_fields(solves, protocol, sigma, z))


@eqx.filter_jit
def _measure_and_jacobian(
    solves: _Solves, protocol: _ProtocolArrays, sigma: jax.Array, z: jax.Array
) -> tuple[jax.Array, jax.Array]:
    sigma, z = _positive(sigma, z)
    drive_fields, measure_fields = _adjoint_fields(solves, protocol, sigma, z)
    readings = _readings(protocol, solves.system.split(drive_fields)[1])
    return readings, _jacobian_of_fields(solves, protocol, sigma, z, "conductivity", drive_fields, measure_fields)


def _adjoint_fields(
    solves: _Solves, protocol: _ProtocolArrays, sigma: jax.Array, z: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """The system solutions (n, n_drives) of every drive and (n, n_patterns) of every
    measurement pattern, from one factorisation and L-1 solves (docs/science.md#jacobian)."""
    system = solves.system
    n_free = system.n_electrodes - 1
    # Unit current into electrode l < L-1 and out of electrode L-1: every zero-sum pattern is
    # a combination of these with its first L-1 entries as weights.
    unit_currents = jnp.eye(n_free, system.n_electrodes, dtype=sigma.dtype).at[:, -1].set(-1)
    basis = solve_spd(system.pattern, _values(solves, sigma, z), system.current_rhs(unit_currents), solves.solver)
    drives = solves.drive_current * protocol.drive[:, :n_free].astype(sigma.dtype)
    # A reading m of potentials that sum to zero equals one of m - mean(m), a zero-sum pattern.
    patterns = protocol.measure_patterns - protocol.measure_patterns.mean(axis=1, keepdims=True)
    patterns = patterns[:, :n_free].astype(sigma.dtype)
    drive_fields = basis @ drives.T  # (n, n_drives) system solutions of every drive
    measure_fields = basis @ patterns.T  # (n, n_patterns) ... of every measurement pattern
    return drive_fields, measure_fields


def _jacobian_of_fields(
    solves: _Solves,
    protocol: _ProtocolArrays,
    sigma: jax.Array,
    z: jax.Array,
    wrt: JacobianVariable,
    drive_fields: jax.Array,
    measure_fields: jax.Array,
) -> jax.Array:
    """The Jacobian by reciprocity from the drive and measurement fields (`_adjoint_fields`)."""
    system = solves.system
    if wrt in ("contact_impedance", "electrode_shift"):
        drives, patterns = drive_fields[:, protocol.drive_index], measure_fields[:, protocol.pattern_index]
        ends = _ends(solves, z.dtype)
        if wrt == "contact_impedance":
            return system.contact_forms(drives, patterns, *ends) / z**2  # (n_measurements, L)
        # The electrode terms hold weights(ends) / z: dV/d end = -(d forms / d end) / z. Electrode l's
        # forms depend on its own ends alone, so one tangent moves every start (then every end).
        shift = ends[0]
        along = [
            jax.jvp(lambda e: system.contact_forms(drives, patterns, e), (shift,), (tangent,))[1]
            for tangent in (jnp.zeros_like(shift).at[:, side].set(1.0) for side in (0, 1))
        ]
        return -jnp.stack(along, axis=-1) / z[:, None]  # (n_measurements, L, 2)
    drive_gradients = _element_gradients(system, system.split(drive_fields)[0])  # each (n_drives, E)
    measure_gradients = _element_gradients(system, system.split(measure_fields)[0])  # each (n_patterns, E)
    products = sum(
        drive[protocol.drive_index] * measure[protocol.pattern_index]
        for drive, measure in zip(drive_gradients, measure_gradients, strict=True)
    )
    jacobian = -jnp.asarray(system.element_areas, sigma.dtype) * products
    return jacobian * sigma if wrt == "log_conductivity" else jacobian


def _element_gradients(system: ElectrodeSystem, nodal: jax.Array) -> tuple[jax.Array, ...]:
    """The components along each coordinate axis (x, y and, on a surface, z), (k, E) each, of
    the gradients of k nodal fields (k, N) per element.

    Three broadcast products per component rather than a batched (d x 3) @ (3 x k) matmul per
    element, which XLA runs slowly on CPU."""
    gradients = jnp.asarray(system.gradients, nodal.dtype)  # (E, d, 3)
    corners = [nodal[:, system.triangles[:, i]] for i in range(3)]  # each (k, E)
    return tuple(sum(gradients[:, axis, i] * corners[i] for i in range(3)) for axis in range(gradients.shape[1]))
