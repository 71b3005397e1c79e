"""Labelled presses of a calibration session: where the skin was pressed, how wide, and when."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from numpy.typing import ArrayLike

from .._arrays import frame_period


class Presses(eqx.Module):
    """Presses at known places (a robot or an indenter), for `diffeit.calibrate`.

    Arguments:
        centres: (K, 2) where each press was centred, metres, in the labels' frame (which may
            be rotated, scaled and offset against the mesh's: calibration fits the map); on a
            curved skin (K, 3), points on its surface in the mesh's frame.
        radius: The contact radius, metres: one for all presses or (K,) one each.
        times: (K,) the instant each press is held, seconds on the recording's clock, or
            (K, 2) the start and end of each hold. An instant is read from the one frame
            nearest it; a hold from every frame within it (their mean), and holds of 3 frames
            or more let `diffeit.calibrate` fit the skin's memory. The presses may be some of
            a session's: frames outside them are not taken for rest where a press changes
            them.

    Attributes:
        centres: (K, 2) or (K, 3) float64, metres.
        radius: (K,) float64, metres.
        times: (K, 2) float64, seconds: each hold's start and end (equal for an instant).

    Raises:
        ValueError: For shapes that do not match, values that are not finite, a radius that
            is not positive, or a hold that ends before it starts.
    """

    centres: np.ndarray
    radius: np.ndarray
    times: np.ndarray

    def __init__(self, centres: ArrayLike, radius: ArrayLike, times: ArrayLike) -> None:
        centres = np.array(centres, dtype=np.float64)
        if centres.ndim != 2 or centres.shape[1] not in (2, 3) or len(centres) == 0:
            raise ValueError(
                f"presses: centres has shape {centres.shape}; expected (K, 2), or (K, 3) on a curved skin, "
                "K >= 1, metres"
            )
        count = len(centres)
        radius = np.array(radius, dtype=np.float64)
        if radius.ndim > 1 or (radius.ndim == 1 and radius.shape != (count,)):
            raise ValueError(f"presses: radius has shape {radius.shape}; expected one value or ({count},)")
        times = np.array(times, dtype=np.float64)
        if times.shape == (count,):
            times = np.stack([times, times], axis=1)
        if times.shape != (count, 2):
            raise ValueError(f"presses: times has shape {times.shape}; expected ({count},) or ({count}, 2), seconds")
        for name, values in (("centres", centres), ("radius", radius), ("times", times)):
            bad = ~np.isfinite(values.reshape(count, -1) if values.ndim else values[None]).all(axis=-1)
            if bad.any():
                raise ValueError(
                    f"presses: {name} is not finite (NaN or inf) at press(es) {np.flatnonzero(bad).tolist()}"
                )
        radius = np.broadcast_to(radius, (count,)).copy()
        if np.any(radius <= 0):
            raise ValueError(
                f"presses: radius must be positive, metres; it is not at {np.flatnonzero(radius <= 0).tolist()}"
            )
        if np.any(times[:, 1] < times[:, 0]):
            raise ValueError(
                f"presses: a hold ends before it starts at {np.flatnonzero(times[:, 1] < times[:, 0]).tolist()}"
            )
        for array in (centres, radius, times):
            array.flags.writeable = False
        self.centres, self.radius, self.times = centres, radius, times

    @property
    def n_presses(self) -> int:
        """K, the number of presses."""
        return len(self.centres)

    def frames(self, times: np.ndarray) -> list[np.ndarray]:
        """The frames of each press: those within its hold, or the frame nearest its middle.

        An instant (or a hold no frame falls in) gets the one frame nearest to it. A frame within
        1e-6 of the frames' median period of a hold's end is within it: labels and frame times
        computed apart (an end of 4.0 s against a clock's 4.000000000000001 s) had left a
        held press a frame short, and the memory fit, which needs every press held over three
        frames, was not made.

        Arguments:
            times: (T,) the frames' times, seconds on the recording's clock.

        Returns:
            K arrays of frame indices, one per press, none empty.
        """
        times = np.asarray(times, np.float64)
        slack = 1e-6 * frame_period(times)
        chosen = []
        for start, end in self.times:
            inside = np.flatnonzero((times >= start - slack) & (times <= end + slack))
            chosen.append(inside if len(inside) else np.array([int(np.argmin(np.abs(times - 0.5 * (start + end))))]))
        return chosen

    def select(self, which: ArrayLike) -> Presses:
        """Some of these presses.

        Arguments:
            which: Indices, a slice or a boolean mask (K,) of the presses to keep.

        Returns:
            A new `Presses`.

        Raises:
            ValueError: When the selection leaves no press.
        """
        return Presses(self.centres[which], self.radius[which], self.times[which])
