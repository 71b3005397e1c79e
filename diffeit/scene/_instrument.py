"""The instrument's effects: measurement noise, common-mode drift, contact impedance drift, open
electrodes, electrode position error, readout mixing and reading gains.

Each effect is a small pure JAX function of its own parameters, and an `equinox.Module` that a
scene declares (`MeasurementNoise`, `CommonModeDrift`, `ContactDrift`, `OpenElectrodes`,
`ElectrodePositionError`, `ReadoutMixing`, `ReadingGains`); every continuous parameter (noise
scale, drift offsets and rates, contact impedances and their rates, mixing weights, gains) is a
leaf, so `jax.grad` differentiates through it. Units: voltages in volts, times in seconds,
contact impedance in ohm m (as `diffeit.ForwardModel`), rates per second; mixing weights and
gains are unit-free.

## Measurement noise (docs/science.md#noise)
"p%" noise is independent Gaussian noise of standard deviation sigma = p/100 x RMS(V_ref) on
every reading, RMS(V_ref) = sqrt(mean(V_ref^2)) over the reference frame's readings. A `Noise`
is given as a percentage, an SNR in dB (SNR = 20 log10(RMS(V_ref) / sigma), so
sigma = RMS(V_ref) 10^(-SNR/20)), a standard deviation in volts, or a named level. The named
levels, defined once in `NOISE_LEVELS` as percentages of RMS(V_ref):

| level | percent | SNR |
|---|---|---|
| "low" | 0.1% | 60 dB |
| "medium" | 0.5% | 46 dB |
| "high" | 2% | 34 dB |

"low" is a well-averaged EIT front end, "medium" the order of the strip readout's rms noise at
rest, "high" a noisy, unshielded skin; where the levels come from is in docs/science.md#noise.

## Common-mode drift
All readings of a frame at time t move together: V'(t) = gain(t) V(t) + offset(t), with
offset(t) = offset + rate t + amplitude sin(2 pi t / period + phase) (volts) and
gain(t) = 1 + gain_rate t (gain_rate: relative change per second). With every parameter 0 the
frames come back bit for bit.

## Contact impedance drift
Per electrode l: z_l(t) = z0_l exp(rate_l t) ("exponential", the default: stays positive) or
z0_l (1 + rate_l t) ("linear"), rate in 1/s, z0_l the skin's contact impedance.
`contact_impedance` returns (T, L), one row per frame, to pass frame by frame to
`ForwardModel.measure(conductivity, z)` (for example under `jax.vmap`).

## Open (broken) electrode
An open electrode carries no current: it is modelled by multiplying its contact impedance by
`OPEN_FACTOR` = 1e6 (`open_contact_impedance`), so it no longer shunts current past the sheet
under it and the other readings change as they physically would. Its readings are lost: every
reading that weights the open electrode, and every reading of a drive that sends current through
it (a current source into an open circuit rails, its voltages are garbage), is replaced by
`fill` (0 V by default; never NaN, so frames stay finite for any downstream code), and
`open_electrodes` returns the boolean mask (M,) of these lost readings, True where lost, so
reconstructions can drop them. The fault is discrete: the mask has no gradient.

## Electrode position error
The electrodes of the simulation mesh sit along the boundary off their nominal positions by
given offsets (metres, counter-clockwise), while the reconstruction mesh keeps the nominal ones.
It changes the mesh, so it has no gradient.

## Readout mixing and reading gains
The board's readout as `diffeit.readout.Readout` models it (its module docstring has the
formula). Mixing: reading m of drive d becomes `sum_l (W_ml + X_ml) U_dl` instead of the
protocol's `sum_l W_ml U_dl`, U the electrode potentials (volts), with
`X_m = source e_s(d) + sink e_k(d) + sum_j offsets[j] e_((p_m + j) mod L)`: a little of the
drive's current-source electrode s(d), its sink k(d), and the electrode j places on from the
measuring pair's positive electrode p_m (`offsets[L // 2]`, the far electrode); weights relative
to the pair's (1). Gains: reading m is multiplied by `gains[m]` (1 nominal). The simulator
applies them in the board's order: mixing of the potentials, then gains, then noise (its scale
the reference as the board reads it). The simulator's readings are signed; a board that
reports magnitudes takes |.| after the gains and before the noise. All zero mixing weights and
unit gains: the protocol's readings, to rounding (formed from the electrode potentials rather
than by `ForwardModel.measure`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import concrete_floats
from ..protocol import Protocol
from ..readout import Readout

ArrayLike = float | jax.Array | np.ndarray

# The sources leave the levels undefined. The one figure of the hardware (the tactile-skin
# dissertation's strip readout) is its rms noise at rest, dR/R0 = 0.0055, about 0.5% of the
# signal: "medium" is that instrument. "low" (0.1%, 60 dB) is a well-averaged EIT front end, the
# order of commercial systems; "high" (2%, 34 dB) a noisy, unshielded skin, where small touches
# drown in the noise.
NOISE_LEVELS: dict[str, float] = {"low": 0.1, "medium": 0.5, "high": 2.0}
"""The named noise levels, percent of RMS(V_ref) (see the module docstring)."""

OPEN_FACTOR: float = 1e6
"""An open electrode's contact impedance, relative to its intact value."""

NoiseKind = Literal["percent", "snr_db", "volts"]
ContactDriftKind = Literal["exponential", "linear"]


# --- Measurement noise ---------------------------------------------------------------------------


class Noise(eqx.Module):
    """Measurement noise: independent Gaussian noise of one standard deviation on every reading.

    Percent and dB noise are relative to RMS(V_ref), the RMS of the reference frame's readings
    (`rms`; docs/science.md#noise). Build with `Noise.percent(p)`, `Noise.snr_db(s)`,
    `Noise.volts(v)` or `Noise.level(name)` (a name of `NOISE_LEVELS`).

    Attributes:
        value: A scalar in the unit `kind` names: percent of RMS(V_ref) (>= 0), dB (any finite
            number) or volts (the standard deviation, >= 0). A leaf (differentiable).
        kind: "percent" (default), "snr_db" or "volts" (static).

    Raises:
        ValueError: For an unknown kind, a value that is not one finite number, or a negative
            percentage or voltage.
    """

    value: ArrayLike
    kind: NoiseKind = eqx.field(default="percent", static=True)

    def __check_init__(self) -> None:
        if self.kind not in ("percent", "snr_db", "volts"):
            raise ValueError(f"Noise.kind must be 'percent', 'snr_db' or 'volts'; got {self.kind!r}")
        value = concrete_floats(self.value, "Noise.value")
        if value is not None and value.shape != ():
            raise ValueError(f"Noise.value must be a scalar; got shape {value.shape}")
        if value is not None and self.kind != "snr_db" and value < 0:
            unit = "percent of RMS(V_ref)" if self.kind == "percent" else "volts"
            raise ValueError(f"Noise.value ({self.kind}) must be >= 0 ({unit}); got {float(value)}")

    @classmethod
    def percent(cls, percent: ArrayLike) -> Noise:
        """Noise of standard deviation percent/100 x RMS(V_ref).

        Arguments:
            percent: p, percent of RMS(V_ref), >= 0.

        Returns:
            The `Noise`.

        Raises:
            ValueError: For a value that is not one finite number >= 0.
        """
        return cls(percent, "percent")

    @classmethod
    def snr_db(cls, snr_db: ArrayLike) -> Noise:
        """Noise of signal-to-noise ratio 20 log10(RMS(V_ref) / sigma) = snr_db.

        Arguments:
            snr_db: The SNR, dB, any finite number.

        Returns:
            The `Noise`.

        Raises:
            ValueError: For a value that is not one finite number.
        """
        return cls(snr_db, "snr_db")

    @classmethod
    def volts(cls, volts: ArrayLike) -> Noise:
        """Noise of a standard deviation given in volts.

        Arguments:
            volts: The standard deviation, volts, >= 0.

        Returns:
            The `Noise`.

        Raises:
            ValueError: For a value that is not one finite number >= 0.
        """
        return cls(volts, "volts")

    @classmethod
    def level(cls, name: str) -> Noise:
        """A named level of `NOISE_LEVELS`, as a percentage.

        Arguments:
            name: "low" (0.1%), "medium" (0.5%) or "high" (2%).

        Returns:
            The `Noise`, of kind "percent".

        Raises:
            ValueError: For any other name.
        """
        if name not in NOISE_LEVELS:
            raise ValueError(f"Noise.level must be one of {sorted(NOISE_LEVELS)}; got {name!r}")
        return cls(NOISE_LEVELS[name], "percent")

    def std(self, reference: ArrayLike) -> jax.Array:
        """The standard deviation of the noise, volts.

        Arguments:
            reference: (M,) the reference frame, volts (read for percent and dB noise only).

        Returns:
            () sigma, volts.
        """
        if self.kind == "volts":
            return jnp.asarray(self.value, dtype=float)
        scale = rms(reference)
        if self.kind == "percent":
            return self.value / 100.0 * scale
        return scale * 10.0 ** (-jnp.asarray(self.value, dtype=float) / 20.0)


def rms(reference: ArrayLike) -> jax.Array:
    """RMS(V_ref) = sqrt(mean(V_ref^2)) of a reference frame: the scale of percent and dB noise.

    Arguments:
        reference: (M,) the reference frame, volts.

    Returns:
        () the RMS, volts.
    """
    reference = jnp.asarray(reference)
    return jnp.sqrt(jnp.mean(reference**2))


def add_noise(frames: ArrayLike, reference: ArrayLike, noise: Noise, key: jax.Array) -> jax.Array:
    """Frames plus independent Gaussian noise of `noise.std(reference)` volts per reading.

    The same key gives the same noise. Differentiable in `noise.value`.

    Arguments:
        frames: (T, M) readings, volts (integers are converted to floats).
        reference: (M,) the reference frame, volts: it sets the scale of percent and dB noise.
        noise: The `Noise`.
        key: A `jax.random` key.

    Returns:
        (T, M) the noisy frames, volts, in the frames' float dtype.
    """
    frames = jnp.asarray(frames)
    if not jnp.issubdtype(frames.dtype, jnp.floating):
        frames = frames.astype(float)
    std = noise.std(reference).astype(frames.dtype)
    return frames + std * jax.random.normal(key, frames.shape, frames.dtype)


class MeasurementNoise(eqx.Module):
    """The effect "noise": Gaussian noise on every reading of every frame and of the reference.

    The scale of percent and dB noise is the noise-free, drift-free reference
    (docs/science.md#noise).

    Attributes:
        noise: The `Noise`.
        seed: The seed of `jax.random.key` the noise is drawn from (static, default 0).

    Raises:
        ValueError: For a `noise` that is not a `Noise` or a seed that is not an integer.
    """

    noise: Noise
    seed: int = eqx.field(default=0, static=True)

    def __check_init__(self) -> None:
        if not isinstance(self.noise, Noise):
            raise ValueError(f"effects.noise needs a Noise; got {self.noise!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool):
            raise ValueError(f"effects.noise.seed must be an integer; got {self.seed!r}")


# --- Common-mode drift ---------------------------------------------------------------------------


class CommonModeDrift(eqx.Module):
    """Drift common to all readings: V'(t) = (1 + gain_rate t) V(t) + offset(t).

    offset(t) = offset + rate t + amplitude sin(2 pi t / period + phase), volts, t in seconds.
    Every field is a scalar leaf (differentiable). All zero (the defaults): no change.

    Attributes:
        offset: Constant offset, volts.
        rate: Linear offset drift, volts per second.
        amplitude: The sinusoid's amplitude, volts.
        period: The sinusoid's period, seconds, > 0 (default 1).
        phase: The sinusoid's phase, radians.
        gain_rate: Relative gain drift, 1/s: the gain is 1 + gain_rate t.

    Raises:
        ValueError: Naming the field, for a value that is not numbers or not finite, or a
            period that is not positive.
    """

    offset: ArrayLike = 0.0
    rate: ArrayLike = 0.0
    amplitude: ArrayLike = 0.0
    period: ArrayLike = 1.0
    phase: ArrayLike = 0.0
    gain_rate: ArrayLike = 0.0

    def __check_init__(self) -> None:
        for f in dataclasses.fields(self):
            concrete_floats(getattr(self, f.name), f"CommonModeDrift.{f.name}")
        period = concrete_floats(self.period, "CommonModeDrift.period")
        if period is not None and not np.all(period > 0):
            raise ValueError(f"CommonModeDrift.period must be positive (seconds); got {period}")

    def offset_at(self, times: ArrayLike) -> jax.Array:
        """The common offset at the given times.

        Arguments:
            times: (T,) seconds.

        Returns:
            (T,) offset(t), volts.
        """
        t = jnp.asarray(times, dtype=float)
        return self.offset + self.rate * t + self.amplitude * jnp.sin(2 * jnp.pi * t / self.period + self.phase)

    def gain_at(self, times: ArrayLike) -> jax.Array:
        """The common gain at the given times.

        Arguments:
            times: (T,) seconds.

        Returns:
            (T,) 1 + gain_rate t, unit-free.
        """
        return 1.0 + self.gain_rate * jnp.asarray(times, dtype=float)


def add_drift(frames: ArrayLike, times: ArrayLike, drift: CommonModeDrift) -> jax.Array:
    """Frames with the common-mode drift applied: gain(t) V + offset(t).

    Arguments:
        frames: (T, M) readings, volts (integers are converted to floats).
        times: (T,) their times, seconds.
        drift: The `CommonModeDrift`.

    Returns:
        (T, M) the drifted frames, volts, in the frames' float dtype.

    Raises:
        ValueError: For times not of shape (T,).
    """
    frames = jnp.asarray(frames)
    if not jnp.issubdtype(frames.dtype, jnp.floating):
        frames = frames.astype(float)
    times = jnp.asarray(times, dtype=frames.dtype)
    if times.shape != frames.shape[:1]:
        raise ValueError(f"times has shape {times.shape}; expected ({frames.shape[0]},), one per frame")
    gain = drift.gain_at(times).astype(frames.dtype)
    offset = drift.offset_at(times).astype(frames.dtype)
    return gain[:, None] * frames + offset[:, None]


# --- Contact impedance drift ---------------------------------------------------------------------


class ContactDrift(eqx.Module):
    """How the contact impedance of every electrode drifts in time.

    The skin holds its value z0 (ohm m) at t = 0; at t seconds electrode l has
    z0_l exp(rate_l t) ("exponential", stays positive) or z0_l (1 + rate_l t) ("linear"; keep
    1 + rate t > 0 over the scene). A rate of 0: no change. See `contact_impedance`.

    Attributes:
        rate: 1/s, a scalar or (L,) one per electrode; a leaf (differentiable).
        kind: "exponential" (default) or "linear" (static).

    Raises:
        ValueError: For an unknown kind, or a rate that is not finite numbers or has more than
            one dimension.
    """

    rate: ArrayLike = 0.0
    kind: ContactDriftKind = eqx.field(default="exponential", static=True)

    def __check_init__(self) -> None:
        if self.kind not in ("exponential", "linear"):
            raise ValueError(f"ContactDrift.kind must be 'exponential' or 'linear'; got {self.kind!r}")
        rate = concrete_floats(self.rate, "ContactDrift.rate")
        if rate is not None and rate.ndim > 1:
            raise ValueError(f"ContactDrift.rate must be a scalar or one rate per electrode (L,); got {rate.shape}")


def contact_impedance(initial: ArrayLike, times: ArrayLike, drift: ContactDrift) -> jax.Array:
    """Drifted contact impedances, one row per frame.

    Feed row k to `ForwardModel.measure(conductivity_k, z[k])` (for example under
    `jax.vmap`).

    Arguments:
        initial: (L,) the contact impedances at t = 0, ohm m.
        times: (T,) seconds.
        drift: The `ContactDrift`.

    Returns:
        (T, L) z, ohm m.

    Raises:
        ValueError: For `initial` not of shape (L,).
    """
    initial = jnp.asarray(initial, dtype=float)
    if initial.ndim != 1:
        raise ValueError(f"initial contact impedance must have one value per electrode, (L,); got {initial.shape}")
    t = jnp.asarray(times, dtype=float)[:, None]
    rate = jnp.broadcast_to(jnp.asarray(drift.rate, dtype=float), initial.shape)
    if drift.kind == "exponential":
        return initial * jnp.exp(rate * t)
    return initial * (1.0 + rate * t)


# --- Open electrodes -----------------------------------------------------------------------------


def _checked_electrodes(electrodes: int | Sequence[int], n_electrodes: int) -> np.ndarray:
    index = np.atleast_1d(np.asarray(electrodes))
    if index.ndim != 1 or not (index.size == 0 or np.issubdtype(index.dtype, np.integer)):
        raise ValueError(f"electrodes must be an electrode index or a sequence of them; got {electrodes!r}")
    bad = index[(index < 0) | (index >= n_electrodes)]
    if bad.size:
        raise ValueError(f"electrodes {bad.tolist()} out of range: the skin has electrodes 0..{n_electrodes - 1}")
    return index.astype(int)


def open_contact_impedance(
    contact_impedance: ArrayLike, electrodes: int | Sequence[int], factor: float = OPEN_FACTOR
) -> jax.Array:
    """Contact impedances with those of the open electrodes multiplied by `factor`.

    An open electrode then carries no current: it no longer shunts current past the sheet
    under it.

    Arguments:
        contact_impedance: (..., L) z, ohm m.
        electrodes: The open electrodes: an index or a sequence of indices in [0, L).
        factor: The multiple, finite and positive (default `OPEN_FACTOR`, 1e6).

    Returns:
        (..., L) z, ohm m.

    Raises:
        ValueError: For a scalar `contact_impedance`, a factor that is not finite and
            positive, or electrodes that are not integers in [0, L).
    """
    z = jnp.asarray(contact_impedance, dtype=float)
    if z.ndim == 0:
        raise ValueError("contact_impedance must have one value per electrode, shape (..., L); got a scalar")
    if not (np.isfinite(factor) and factor > 0):
        raise ValueError(f"factor must be finite and positive; got {factor}")
    index = _checked_electrodes(electrodes, z.shape[-1])
    scale = np.ones(z.shape[-1])
    scale[index] = factor
    return z * jnp.asarray(scale)


def lost_readings(protocol: Protocol, electrodes: int | Sequence[int]) -> np.ndarray:
    """The readings the open electrodes lose: those weighting them and those of drives through them.

    Arguments:
        protocol: The skin's protocol.
        electrodes: The open electrodes: an index or a sequence of indices.

    Returns:
        (M,) boolean, True where lost.

    Raises:
        ValueError: For electrodes that are not integers in [0, L).
    """
    index = _checked_electrodes(electrodes, protocol.n_electrodes)
    reads = np.any(protocol.measure[:, index] != 0, axis=1)
    drives = np.any(protocol.drive[:, index] != 0, axis=1)[protocol.drive_index]
    return reads | drives


def open_electrodes(
    frames: ArrayLike, protocol: Protocol, electrodes: int | Sequence[int], fill: float = 0.0
) -> tuple[jax.Array, np.ndarray]:
    """Frames with the readings lost to open electrodes replaced, and the mask of lost readings.

    Lost readings are those of `lost_readings`. The fault is discrete: the mask has no
    gradient.

    Arguments:
        frames: (T, M) or (M,) readings, volts.
        protocol: The skin's protocol.
        electrodes: The open electrodes: an index or a sequence of indices.
        fill: The value of a lost reading, volts, finite (default 0; never NaN, so frames stay
            finite).

    Returns:
        (the frames with lost readings set to `fill`, the shape of `frames`; the (M,) boolean
        mask, True where lost).

    Raises:
        ValueError: For a fill that is not finite, frames whose last axis is not M, or
            electrodes that are not integers in [0, L).
    """
    if not np.isfinite(fill):
        raise ValueError(f"fill must be a finite voltage (NaN is not allowed); got {fill}")
    frames = jnp.asarray(frames)
    if frames.shape[-1:] != (protocol.n_measurements,):
        raise ValueError(f"frames has shape {frames.shape}; expected (T, {protocol.n_measurements})")
    mask = lost_readings(protocol, electrodes)
    return jnp.where(jnp.asarray(mask), jnp.asarray(fill, frames.dtype), frames), mask


def _electrode_indices(electrodes: Any) -> tuple[int, ...]:
    """The open electrodes as a tuple of Python integers (static, hashable)."""
    index = np.atleast_1d(np.asarray(electrodes))
    if index.ndim != 1 or index.size == 0 or not np.issubdtype(index.dtype, np.integer):
        raise ValueError(f"effects.open_electrode.electrodes must be electrode indices; got {electrodes!r}")
    return tuple(int(e) for e in index)


class OpenElectrodes(eqx.Module):
    """The effect "open_electrode": electrodes that carry no current.

    Their contact impedance is multiplied by `OPEN_FACTOR`, and their readings are replaced by
    `fill` and flagged (`Simulation.lost`). Static: the fault is discrete.

    Attributes:
        electrodes: The open electrodes' indices, a tuple of at least one (static).
        fill: The value of a lost reading, volts, finite (static, default 0).

    Raises:
        ValueError: For electrodes that are not integer indices, or a fill that is not a
            finite number.
    """

    electrodes: tuple[int, ...] = eqx.field(static=True, converter=_electrode_indices)
    fill: float = eqx.field(default=0.0, static=True)

    def __check_init__(self) -> None:
        if not (isinstance(self.fill, int | float) and math.isfinite(self.fill)):
            raise ValueError(f"effects.open_electrode.fill must be a finite voltage; got {self.fill!r}")


# --- Electrode position error --------------------------------------------------------------------


def _offsets(offsets: Any) -> tuple[float, ...]:
    """The offsets as a tuple of Python floats (static, hashable)."""
    values = concrete_floats(offsets, "effects.electrode_position_error.offsets")
    if values is None or values.ndim != 1:
        raise ValueError("effects.electrode_position_error.offsets must be one number per electrode (metres)")
    return tuple(float(v) for v in values)


class ElectrodePositionError(eqx.Module):
    """The effect "electrode_position_error": the simulation mesh's electrodes off their places.

    Every electrode of the simulation mesh is moved along the boundary, while the
    reconstruction mesh keeps the nominal positions. Static: it changes the mesh, so it has no
    gradient.

    Attributes:
        offsets: One offset per electrode, metres along the boundary, counter-clockwise
            positive (static).

    Raises:
        ValueError: For offsets that are not a 1-D sequence of finite numbers.
    """

    offsets: tuple[float, ...] = eqx.field(static=True, converter=_offsets)

    @classmethod
    def random(cls, n_electrodes: int, std: float, seed: int = 0) -> ElectrodePositionError:
        """Independent Gaussian offsets, from `numpy.random.default_rng(seed)`.

        Arguments:
            n_electrodes: L, the number of electrodes.
            std: The standard deviation, metres, >= 0.
            seed: The seed of the random generator.

        Returns:
            The `ElectrodePositionError`.

        Raises:
            ValueError: For a `std` that is negative or not finite.
        """
        if not (math.isfinite(std) and std >= 0):
            raise ValueError(f"effects.electrode_position_error.std must be >= 0 (metres); got {std}")
        return cls(tuple(np.random.default_rng(seed).normal(0.0, std, n_electrodes)))


# --- Readout mixing and reading gains ------------------------------------------------------------


def _float_array(value: Any) -> Any:
    """Numbers and lists of them as one float64 NumPy array leaf, as in code, whatever JAX's
    precision setting (JAX arrays, traced or not, and anything else pass through, for
    `__check_init__` to refuse with the field's name)."""
    if isinstance(value, bool) or not isinstance(value, int | float | list | tuple | np.ndarray | np.generic):
        return value
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return value


class ReadoutMixing(eqx.Module):
    """The effect "readout_mixing": each reading mixes in other electrodes' potentials.

    The model is `diffeit.readout.Readout` (its module docstring, and this module's): reading m
    of drive d becomes `sum_l (W_ml + X_ml) U_dl`, U the electrode potentials in volts. Every
    field is a float array leaf (differentiable). All zero: the protocol's readings.

    Attributes:
        source: The weight of the drive's current-source electrode, relative to the measuring
            pair's (1); unit-free, a scalar.
        sink: The weight of the drive's current-sink electrode; unit-free, a scalar.
        offsets: (L,) the weight of the electrode j places on from the measuring pair's
            positive electrode (counter-clockwise in electrode order); `offsets[L // 2]` is
            the far electrode. Unit-free.

    Raises:
        ValueError: Naming the field, for a source or sink that is not one number, offsets
            that are not one number per electrode (a 1-D array of at least 2), or any value
            that is not finite. The scene checks that there is one offset per electrode.
    """

    source: ArrayLike = eqx.field(converter=_float_array)
    sink: ArrayLike = eqx.field(converter=_float_array)
    offsets: ArrayLike = eqx.field(converter=_float_array)

    def __check_init__(self) -> None:
        for name in ("source", "sink"):
            value = concrete_floats(getattr(self, name), f"effects.readout_mixing.{name}")
            if value is not None and value.shape != ():
                raise ValueError(f"effects.readout_mixing.{name} must be one number; got shape {value.shape}")
        offsets = concrete_floats(self.offsets, "effects.readout_mixing.offsets")
        if offsets is not None and (offsets.ndim != 1 or len(offsets) < 2):
            raise ValueError(
                f"effects.readout_mixing.offsets must be one weight per electrode, (L,); got shape {offsets.shape}"
            )

    @classmethod
    def random(cls, n_electrodes: int, largest: float = 0.3, seed: int = 0) -> ReadoutMixing:
        """A random mixing of the source's and the far electrode's weights, the largest in practice.

        Draws, from `numpy.random.default_rng(seed)`, first `source` and then the far
        electrode's weight `offsets[n_electrodes // 2]`, each uniform in [0, largest); the sink
        and every other offset are 0.

        Arguments:
            n_electrodes: L, the number of electrodes (>= 2).
            largest: The largest weight, unit-free (relative to the measuring pair's), >= 0.
            seed: The seed of the random generator (an integer).

        Returns:
            The `ReadoutMixing`.

        Raises:
            ValueError: For fewer than 2 electrodes or a `largest` that is negative or not
                finite.
        """
        if not isinstance(n_electrodes, int | np.integer) or isinstance(n_electrodes, bool) or n_electrodes < 2:
            raise ValueError(f"effects.readout_mixing: n_electrodes must be an integer >= 2; got {n_electrodes!r}")
        if not (isinstance(largest, int | float | np.floating) and math.isfinite(largest) and largest >= 0):
            raise ValueError(f"effects.readout_mixing.largest must be finite and >= 0 (unit-free); got {largest}")
        rng = np.random.default_rng(seed)
        source, far = rng.uniform(0.0, largest, 2)
        offsets = np.zeros(int(n_electrodes))
        offsets[n_electrodes // 2] = far
        return cls(float(source), 0.0, offsets)

    def readout(self, protocol: Protocol) -> Readout:
        """The `diffeit.readout.Readout` of this mixing on `protocol` (unit gains).

        Arguments:
            protocol: The protocol whose readings it mixes; L electrodes.

        Returns:
            The `Readout`.

        Raises:
            ValueError: For offsets not one per electrode of `protocol`.
        """
        offsets = jnp.asarray(self.offsets)
        if offsets.shape != (protocol.n_electrodes,):
            raise ValueError(
                f"effects.readout_mixing.offsets has shape {offsets.shape}; the protocol has "
                f"{protocol.n_electrodes} electrodes"
            )
        return Readout(protocol, self.source, self.sink, offsets)


class ReadingGains(eqx.Module):
    """The effect "reading_gains": every reading multiplied by a unit-free gain of its own.

    A channel's amplifier, a drive's current: `gains[m]` multiplies reading m (1 nominal), after
    the readout mixing and before the noise. `gains` is a float array leaf (differentiable).
    All 1: no change.

    Attributes:
        gains: (M,) one gain per reading of the skin's protocol, unit-free; any sign (a
            negative gain is a reversed channel).

    Raises:
        ValueError: Naming the field, for gains that are not a 1-D array or not finite. The
            scene checks that there is one gain per reading.
    """

    gains: ArrayLike = eqx.field(converter=_float_array)

    def __check_init__(self) -> None:
        gains = concrete_floats(self.gains, "effects.reading_gains.gains")
        if gains is not None and (gains.ndim != 1 or len(gains) == 0):
            raise ValueError(f"effects.reading_gains.gains must be one gain per reading, (M,); got shape {gains.shape}")

    @classmethod
    def random(cls, n_measurements: int, spread: float = 0.2, seed: int = 0) -> ReadingGains:
        """Independent gains, uniform in [1 - spread, 1 + spread) (linear, not log-uniform).

        Arguments:
            n_measurements: M, the number of readings of the skin's protocol (>= 1).
            spread: The largest relative departure from 1, unit-free, in [0, 1) so that every
                gain is positive.
            seed: The seed of `numpy.random.default_rng`.

        Returns:
            The `ReadingGains`.

        Raises:
            ValueError: For fewer than one reading or a `spread` outside [0, 1).
        """
        if not isinstance(n_measurements, int | np.integer) or isinstance(n_measurements, bool) or n_measurements < 1:
            raise ValueError(f"effects.reading_gains: n_measurements must be an integer >= 1; got {n_measurements!r}")
        if not (isinstance(spread, int | float | np.floating) and math.isfinite(spread) and 0 <= spread < 1):
            raise ValueError(f"effects.reading_gains.spread must be in [0, 1) (unit-free); got {spread}")
        return cls(np.random.default_rng(seed).uniform(1.0 - spread, 1.0 + spread, int(n_measurements)))
