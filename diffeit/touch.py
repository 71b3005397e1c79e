"""From images to touches: where the skin was touched, how large the contact was and how hard.

`touches(recording)` (`diffeit.touches`) reads every image of a reconstructed recording (`diffeit.reconstruct`);
`read(mesh, images)` is the same on bare arrays.

## The rule

A touch lowers the sheet's conductivity (`polarity=-1`; +1 for a sheet whose conductivity a
touch raises): in each image a = polarity * change, the touches are the hills of a.

1. **Is the frame touched?** With a calibration that knows the readings' noise (from its
   reference frames), a frame is touched when its differences dv (in the calibrated model's
   units) stand out of that noise: z > `detection` (default 5), z the standardised sum over
   the readings of (dv_m / s_m)^2 / (1 + 1/n), each F(1, n - 1) distributed for an untouched
   frame (s_m estimated from n reference frames, dv against their mean). A
   touched frame reports its strongest hill however low, and the others above `low`
   (default 3) robust standard deviations of its image; an untouched frame reports none.
   Without it, a hill counts when its peak exceeds `threshold` (default 6) robust standard
   deviations of the image: sigma_t = 1.4826 * MAD of a over the elements (a touch covers few
   of them, so this is the image's noise and artefacts).
2. **Hills.** The local maxima of a (at least every element sharing an edge), highest
   first. Each claims the connected elements at or above half its peak (its half-amplitude
   set). A maximum whose half-amplitude set reaches a set already claimed is the same touch
   (two maxima whose valley stays above half the lower peak merge); otherwise it is a touch of
   its own, up to `max_touches`.
3. **Readout.** Position: the centroid of the half-amplitude set, weighted by a times area,
   m, mapped by the calibration's `PositionMap` when there is one; radius: sqrt(area / pi) of
   the set, m; depth: the peak relative change (negative for a press with polarity -1);
   pressure, kPa, from the depth through a foam stack's map
   (`diffeit.scene.pressure_to_change`) when one is given.
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import numpy as np
import scipy.sparse
from numpy.typing import ArrayLike
from scipy.sparse.csgraph import breadth_first_order

from .io import Recording
from .mesh import Mesh
from .scene import FoamStack

# A hill counts when its peak exceeds this many robust standard deviations of the image; in a
# frame the voltage test finds touched, a further hill needs LOW of them.
THRESHOLD, LOW = 6.0, 3.0
# The voltage test's statistic z above which a frame is touched.
DETECTION = 5.0


class Touches(eqx.Module):
    """The touches of each frame, at most `max_touches`, strongest first.

    Attributes:
        count: (T,) int, the touches found in each frame.
        position: (T, K, 2) centres, m, in the skin's frame (the labels' frame after a
            calibration's position map); NaN where a frame has fewer than K touches.
        radius: (T, K) contact radius, m: sqrt(area / pi) of the half-amplitude set.
        depth: (T, K) the peak relative conductivity change dsigma / sigma (negative for a
            touch that lowers it).
        pressure: (T, K) kPa through the given foam stack's map, or None.
        noise: (T,) the robust standard deviation of each image, in relative change.
    """

    count: np.ndarray
    position: np.ndarray
    radius: np.ndarray
    depth: np.ndarray
    pressure: np.ndarray | None
    noise: np.ndarray

    def lines(self, frame: int) -> list[str]:
        """Frame `frame`'s touches, a line each: position in mm, radius in mm, depth (and pressure)."""
        lines = []
        for k in range(int(self.count[frame])):
            x, y = 1e3 * self.position[frame, k]
            line = f"touch {k}: ({x:+.1f}, {y:+.1f}) mm, radius {1e3 * self.radius[frame, k]:.1f} mm, "
            line += f"depth {self.depth[frame, k]:+.3f}"
            if self.pressure is not None:
                line += f", {self.pressure[frame, k]:.1f} kPa"
            lines.append(line)
        return lines


def touches(
    recording: Recording,
    calibration: Any = None,
    *,
    max_touches: int = 6,
    threshold: float = THRESHOLD,
    detection: float = DETECTION,
    polarity: int | None = None,
    stack: FoamStack | None = None,
) -> Touches:
    """The touches of every image of a reconstructed recording (module docstring, "The rule").

    Arguments:
        recording: A recording with images (`diffeit.reconstruct`'s result), relative changes
            or conductivity changes (then divided by the calibrated level in its provenance).
        calibration: A `diffeit.calibration.SkinCalibration` whose position map (from labelled
            presses) maps the positions into the labels' frame; None reads them in the mesh's.
        max_touches: The most touches reported per frame.
        threshold: Without the calibration's noise, a touch's peak must exceed this many
            robust standard deviations of its image.
        detection: With it, the voltage test's z above which a frame is touched.
        polarity: -1 when a touch lowers the conductivity, +1 when it raises it; None: the
            calibration's (found from its presses), else -1.
        stack: The skin's foam stack (`diffeit.scene.FoamStack`): pressures are then read
            from the depths.

    Returns:
        The `Touches`.

    Raises:
        ValueError: For a recording without images, or a bad option.
    """
    if not isinstance(recording, Recording) or recording.images is None or recording.mesh is None:
        raise ValueError("touches reads a reconstructed recording (diffeit.reconstruct's result, with images)")
    images = np.asarray(recording.images, np.float64)
    if recording.image_quantity == "conductivity change":
        level = recording.provenance.get("metadata", {}).get("calibration", {}).get("conductivity")
        if level is None:
            raise ValueError("the recording's images are conductivity changes without the level they are relative to")
        images = images / level
    mapping = None if calibration is None else calibration.position_map
    if polarity is None:
        polarity = -1 if calibration is None else calibration.polarity
    return read(
        recording.mesh,
        images,
        max_touches=max_touches,
        threshold=threshold,
        polarity=polarity,
        position_map=mapping,
        stack=stack,
        touched=_touched(recording, calibration, detection),
    )


def _touched(recording: Recording, calibration: Any, detection: float) -> np.ndarray | None:
    """(T,) bool, the frames whose differences stand out of the calibration's noise (module
    docstring, step 1), or None when the calibration knows no noise."""
    noise = None if calibration is None else getattr(calibration, "noise", None)
    if noise is None or recording.reference is None:
        return None
    dv = calibration.signed(recording.frames) - calibration.signed(recording.reference)
    # Each reading's variance is estimated from n frames: (dv / s)^2 / (1 + 1/n) is F(1, n - 1)
    # distributed for an untouched frame against the mean of those frames.
    n = calibration.noise_frames
    freedom = n - 1
    mean = freedom / (freedom - 2)
    variance = 2 * freedom**2 * (freedom - 1) / ((freedom - 2) ** 2 * (freedom - 4))
    ratios = (dv / noise) ** 2 / (1 + 1 / n)
    statistic = (np.sum(ratios, axis=1) - dv.shape[1] * mean) / np.sqrt(dv.shape[1] * variance)
    return statistic > detection


def read(
    mesh: Mesh,
    images: ArrayLike,
    *,
    max_touches: int = 6,
    threshold: float = THRESHOLD,
    polarity: int = -1,
    position_map: Any = None,
    stack: FoamStack | None = None,
    touched: np.ndarray | None = None,
) -> Touches:
    """The touches of relative-change images on a mesh (module docstring, "The rule").

    Arguments:
        mesh: The sheet the images are on.
        images: (T, E) or (E,) relative conductivity changes dsigma / sigma per element.
        max_touches: The most touches reported per frame.
        threshold: A touch's peak must exceed this many robust standard deviations of its image.
        polarity: -1 when a touch lowers the conductivity, +1 when it raises it.
        position_map: A callable from (..., 2) read positions to the labels' frame
            (`diffeit.calibration.PositionMap`), or None.
        stack: A foam stack whose map gives pressures from depths, or None.
        touched: (T,) bool, which frames are touched (a test on the voltages, module
            docstring): a touched frame reports its strongest hill and the others above `LOW`
            robust standard deviations, an untouched one none; None applies `threshold` alone.

    Returns:
        The `Touches` (T = 1 for one image).

    Raises:
        ValueError: For images of the wrong shape or not finite, or a bad option.
    """
    images = np.atleast_2d(np.asarray(images, np.float64))
    if images.ndim != 2 or images.shape[1] != mesh.n_elements:
        raise ValueError(f"images have shape {images.shape}; expected (T, {mesh.n_elements}), one value per element")
    if not np.all(np.isfinite(images)):
        raise ValueError("images hold non-finite values (NaN or inf): no touches can be read")
    if int(max_touches) != max_touches or max_touches < 1:
        raise ValueError(f"max_touches must be a positive integer; got {max_touches}")
    if polarity not in (-1, 1):
        raise ValueError(f"polarity must be -1 (a touch lowers the conductivity) or +1; got {polarity}")
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number of standard deviations; got {threshold}")
    count = np.zeros(len(images), int)
    position = np.full((len(images), max_touches, 2), np.nan)
    radius = np.full((len(images), max_touches), np.nan)
    depth = np.full((len(images), max_touches), np.nan)
    noise = np.zeros(len(images))
    if touched is not None and np.shape(touched) != (len(images),):
        raise ValueError(f"touched has shape {np.shape(touched)}; expected ({len(images)},), one per image")
    for t, image in enumerate(images):
        if touched is None:
            hills, noise[t] = _hills(mesh, polarity * image, max_touches, threshold)
        elif touched[t]:
            hills, noise[t] = _hills(mesh, polarity * image, max_touches, LOW, strongest=True)
        else:
            hills, noise[t] = [], _robust_std(polarity * image)
        count[t] = len(hills)
        for k, (centre, size, peak) in enumerate(hills):
            position[t, k], radius[t, k], depth[t, k] = centre, size, polarity * peak
    if position_map is not None:
        position = position_map(position)
    pressure = None if stack is None else _pressure(depth, stack)
    return Touches(count, position, radius, depth, pressure, noise)


def _robust_std(values: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def _hills(
    mesh: Mesh, values: np.ndarray, max_touches: int, threshold: float, strongest: bool = False
) -> tuple[list, float]:
    """The touches of one image `values` (a touch positive): (centre, radius, peak) each, and
    the image's robust standard deviation; with `strongest`, the highest hill counts whatever
    its height (when it is positive)."""
    noise = _robust_std(values)
    adjacency = _adjacency(mesh)
    neighbour_max = _neighbour_max(adjacency, values)
    floor = threshold * noise
    if strongest:
        floor = min(floor, float(np.max(values)))
    maxima = np.flatnonzero((values >= neighbour_max) & (values > 0) & (values >= floor))
    claimed = np.zeros(len(values), bool)
    areas, centroids = mesh.element_areas, mesh.element_centroids
    hills = []
    for element in maxima[np.argsort(-values[maxima])]:
        if claimed[element] or len(hills) == max_touches:
            continue
        peak = values[element]
        above = values >= 0.5 * peak
        order = breadth_first_order(_restricted(adjacency, above), element, directed=False, return_predecessors=False)
        if claimed[order].any():
            claimed[order] = True
            continue
        claimed[order] = True
        weight = values[order] * areas[order]
        centre = weight @ centroids[order] / weight.sum()
        hills.append((centre, float(np.sqrt(areas[order].sum() / np.pi)), float(peak)))
    return hills, noise


def _restricted(adjacency: scipy.sparse.csr_matrix, keep: np.ndarray) -> scipy.sparse.csr_matrix:
    """The adjacency with the edges of elements outside `keep` removed."""
    mask = scipy.sparse.diags(keep.astype(float))
    return (mask @ adjacency @ mask).tocsr()


def _neighbour_max(adjacency: scipy.sparse.csr_matrix, values: np.ndarray) -> np.ndarray:
    """(E,) the largest value among each element's edge neighbours."""
    rows = np.repeat(np.arange(adjacency.shape[0]), np.diff(adjacency.indptr))
    result = np.full(len(values), -np.inf)
    np.maximum.at(result, rows, values[adjacency.indices])
    return result


@functools.lru_cache(maxsize=16)
def _adjacency(mesh: Mesh) -> scipy.sparse.csr_matrix:
    """(E, E) the elements sharing an edge."""
    edges = np.sort(mesh.triangles[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)
    owner = np.repeat(np.arange(mesh.n_elements), 3)
    key = edges[:, 0] * mesh.n_nodes + edges[:, 1]
    order = np.argsort(key, kind="stable")
    shared = np.flatnonzero(key[order][1:] == key[order][:-1])
    a, b = owner[order][shared], owner[order][shared + 1]
    matrix = scipy.sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(mesh.n_elements,) * 2)
    return (matrix + matrix.T).tocsr()


def _pressure(depth: np.ndarray, stack: FoamStack) -> np.ndarray:
    """kPa from relative changes dsigma / sigma through the stack's bilinear map (the inverse
    of `diffeit.scene.pressure_to_change`); 0 for a depth that is not a decrease."""
    x = np.maximum(-depth / (1.0 + depth), 0.0)
    knee = float(stack.knee) * float(stack.sensitivity)
    below = x / float(stack.sensitivity)
    above = float(stack.knee) + (x - knee) / float(stack.sensitivity_above)
    return np.where(x <= knee, below, above)
