"""How a board turns electrode potentials into readings: mixing and gains (`Readout`).

A protocol's reading m of drive d is `sum_l W_ml U_dl`, W = `protocol.measure` (+1 and -1 on
the measuring pair). Real boards depart from it in two ways that calibration fits and scenes
simulate:

- **Mixing.** The multiplexer and the amplifier's common-mode error add a little of other
  electrodes' potentials: reading m becomes `sum_l (W_ml + X_ml) U_dl` with
  `X_m = source * e_s(d) + sink * e_k(d) + sum_j offsets[j] * e_((p_m + j) mod L)`:
  s(d) and k(d) are the electrodes the drive puts current in through and takes it out through,
  p_m the measuring pair's positive electrode, and `offsets[j]` weighs the electrode j places
  on from it (j = L/2 is the far electrode). Weights are relative to the pair's (1). The
  electrode potentials sum to zero, so a weight added to every electrode changes nothing.
- **Gains.** Each reading is multiplied by `gains[m]` (1 nominal): a channel's amplifier, a
  drive's current.

A board that reports magnitudes takes |reading| after both.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from ._arrays import is_concrete
from .protocol import Protocol


class Readout(eqx.Module):
    """A board's readout: mixing weights and per-reading gains (module docstring).

    Reading m of drive d is `gains[m] * sum_l (W_ml + X_ml) U_dl`, U the electrode potentials
    in volts. Every field is an array leaf (differentiable). Weights and gains are unit-free.

    Arguments:
        protocol: The protocol whose readings it forms (for the shapes; not kept).
        source: The source electrode's weight (default 0: the ideal readout).
        sink: The sink electrode's weight (default 0).
        offsets: (L,) or a scalar for all, the weights by place from the measuring pair's
            positive electrode (default 0).
        gains: (M,) or a scalar for all, each reading's gain (default 1).

    Attributes:
        source: The weight of the drive's current-source electrode, relative to the pair's.
        sink: The weight of the drive's current-sink electrode.
        offsets: (L,) the weight of the electrode j places on from the measuring pair's
            positive electrode (counter-clockwise in electrode order).
        gains: (M,) each reading's gain, unit-free.

    Raises:
        ValueError: For a source or sink weight that is not one number, offsets or gains
            that do not broadcast to (L,) and (M,), or (concrete) weights and gains that are
            not finite.
    """

    source: jax.Array
    sink: jax.Array
    offsets: jax.Array
    gains: jax.Array

    def __init__(
        self,
        protocol: Protocol,
        source: ArrayLike = 0.0,
        sink: ArrayLike = 0.0,
        offsets: ArrayLike = 0.0,
        gains: ArrayLike = 1.0,
    ) -> None:
        n, m = protocol.n_electrodes, protocol.n_measurements
        self.source = jnp.asarray(source, float)
        self.sink = jnp.asarray(sink, float)
        self.offsets = jnp.broadcast_to(jnp.asarray(offsets, float), (n,))
        self.gains = jnp.broadcast_to(jnp.asarray(gains, float), (m,))
        for name, value in (("source", self.source), ("sink", self.sink)):
            if value.shape != ():
                raise ValueError(f"the readout's {name} weight is one number; got shape {value.shape}")
        leaves = (self.source, self.sink, self.offsets, self.gains)
        if all(is_concrete(leaf) for leaf in leaves) and not all(np.all(np.isfinite(leaf)) for leaf in leaves):
            raise ValueError("the readout's weights and gains must be finite")

    def mixing(self, protocol: Protocol) -> jax.Array:
        """The weights X added to `protocol.measure` (module docstring).

        Arguments:
            protocol: The protocol (the one the readout was built for).

        Returns:
            (M, L) X, unit-free.
        """
        source, sink, offset = roles(protocol)
        return self.source * source + self.sink * sink + jnp.einsum("j,jml->ml", self.offsets, offset)

    def folded(self, protocol: Protocol) -> Protocol:
        """The protocol with the mixing folded into its reading weights (W + X).

        A forward model on it reads as this board does, but for the gains. Needs concrete
        weights.

        Arguments:
            protocol: The protocol (the one the readout was built for).

        Returns:
            A new `Protocol`, its drives unchanged.
        """
        weights = np.asarray(protocol.measure) + np.asarray(self.mixing(protocol))
        return Protocol(protocol.drive, [weights[protocol.drive_index == d] for d in range(protocol.n_drives)])

    def readings(self, protocol: Protocol, electrode: jax.Array) -> jax.Array:
        """The board's readings of electrode potentials: `gains * sum_l (W + X)_ml U_(d(m), l)`.

        Signed: take |.| for a board that reports magnitudes.

        Arguments:
            protocol: The protocol (the one the readout was built for).
            electrode: (n_drives, L) the electrode potentials U, volts.

        Returns:
            (M,) the readings, volts.
        """
        weights = jnp.asarray(protocol.measure) + self.mixing(protocol)
        return self.gains * jnp.sum(weights * electrode[protocol.drive_index], axis=-1)


def roles(protocol: Protocol) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The electrodes each reading's mixing weights act on, one-hot.

    The source and sink of a drive are its largest and smallest pattern entries; the pair's
    positive electrode is the largest entry of its reading weights.

    Arguments:
        protocol: The protocol.

    Returns:
        ((M, L) the drive's source, (M, L) its sink, (L, M, L) the electrode j places on from
        the measuring pair's positive electrode, for j = 0 .. L - 1).
    """
    n = protocol.n_electrodes
    drive = protocol.drive[protocol.drive_index]
    eye = np.eye(n)
    source = eye[np.argmax(drive, axis=1)]
    sink = eye[np.argmin(drive, axis=1)]
    positive = np.argmax(protocol.measure, axis=1)
    offset = np.stack([eye[(positive + j) % n] for j in range(n)])
    return source, sink, offset
