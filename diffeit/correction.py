"""The spatial correction ("scaling matrix"): position-dependent factors for the intensity and
the size of reconstructed targets, calibrated on simulated touches (the tactile-skin dissertation's
Figs. 5.4, 5.5 and 5.9).

A linear reconstruction does not image a touch the same everywhere: at the working point (one-step
NOSER, hyperparameter 0.05, medium noise) a touch near the rim comes out with a larger peak and a
smaller half-amplitude set than the same touch at the centre. The correction measures this once,
on simulated data (`calibrate`), and undoes it (`correct`):

    intensity factor  g_I(p_j) = geometric mean over settings s of P_s0 / P_sj,
    size factor       g_S(p_j) = geometric mean over settings s of R_s0 / R_sj,
    corrected image   x'(y) = g_I x(c_j + (y - c_j) / g_S)  within target j,

P and R the peak and the half-amplitude equivalent radius of a touch at position p_j (j = 0 the
reference), c_j a target's half-amplitude centroid. `Calibration.save` and `load` keep a
calibration in a versioned `.npz` file. The method in full is in docs/science.md#spatial-correction,
its use and the file in docs/tutorials/calibration.md#the-spatial-correction.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import typing
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.interpolate
from tqdm.auto import tqdm

from . import metrics
from ._threads import host_algebra
from .forward import ForwardModel
from .inverse import OneStep
from .mesh import Mesh, element_sample_points, locate, nearest_element, onto_surface
from .scene import Disc, Noise, Touch, add_noise, touch_field

SCHEMA = "diffeit.calibration"
VERSION = 2
# Default calibration positions: the centre and rings at these fractions of the domain's
# half-size; the outer ring stays a touch's radius inside a unit disc's rim.
_DEFAULT_RING_FRACTIONS = (0.0, 0.25, 0.45, 0.6, 0.72)
# A half-amplitude component is a target when its area is at least this fraction of the largest.
_TARGET_AREA_FRACTION = 0.25
# The warp averages each corrected element over 4^2 sub-triangles: point sampling at the centroid
# alone quantises a stretch of a few elements' size (a factor 1.1 changed nothing on h = 0.1).
_WARP_LEVEL = 4


@dataclass(frozen=True)
class CalibrationSettings:
    """What a calibration was made with (stored in its file).

    Attributes:
        prior: The one-step reconstruction's prior.
        hyperparameter: Its hyperparameter (unit-free).
        backgrounds: The simulated backgrounds, S/sq.
        intensities: The simulated intensities, dsigma/sigma under the touch (> -1).
        radii: The simulated touch radii, m (every combination of the three is simulated).
        noise_percent: Gaussian noise, percent of RMS(V_ref) (docs/science.md#noise).
        noise_draws: Noise draws per touch.
        seed: The seed of the draws.
        n_elements: The reconstruction mesh's size.
        n_data_elements: The simulation mesh's size.
    """

    prior: str
    hyperparameter: float
    backgrounds: tuple[float, ...]
    intensities: tuple[float, ...]
    radii: tuple[float, ...]
    noise_percent: float
    noise_draws: int
    seed: int
    n_elements: int
    n_data_elements: int


class Calibration(eqx.Module):
    """Position-dependent correction factors for the intensity and size of imaged touches.

    Made by `calibrate`, applied by `correct`, kept by `save` and `load`
    (docs/science.md#spatial-correction).

    Attributes:
        positions: (P, D) m, the calibration positions (true touch centres; D = 3, points on
            the surface, on a curved skin); row 0 the reference.
        intensity_factor: (P,) g_I there (1 at the reference).
        size_factor: (P,) g_S there (1 at the reference).
        intensity_table: (B, I, R, P) the intensity ratios of each setting (backgrounds x
            intensities x radii of `settings`) whose geometric mean `intensity_factor` is.
        size_table: (B, I, R, P) likewise for `size_factor`.
        settings: `CalibrationSettings` (static).
        image_positions: (P, D) m, where the touches at `positions` appear, the mean
            half-amplitude centroid of their images (default: `positions`). `factors` is looked
            up by a reconstructed centroid, so it interpolates over these.

    Raises:
        ValueError: For positions that are not finite (P, 2) or (P, 3), P >= 3, spanning a plane, and
            factors or tables of the wrong shape or not finite and positive.
    """

    positions: np.ndarray
    intensity_factor: np.ndarray
    size_factor: np.ndarray
    intensity_table: np.ndarray
    size_table: np.ndarray
    settings: CalibrationSettings = eqx.field(static=True)
    image_positions: np.ndarray

    def __init__(
        self,
        positions: np.ndarray,
        intensity_factor: np.ndarray,
        size_factor: np.ndarray,
        intensity_table: np.ndarray,
        size_table: np.ndarray,
        settings: CalibrationSettings,
        image_positions: np.ndarray | None = None,
    ) -> None:
        checked = _checked_positions(positions)
        self.positions = positions
        self.intensity_factor = intensity_factor
        self.size_factor = size_factor
        self.intensity_table = intensity_table
        self.size_table = size_table
        self.settings = settings
        self.image_positions = checked if image_positions is None else image_positions

    def __check_init__(self) -> None:
        positions = np.asarray(self.positions, dtype=float)
        if np.shape(self.image_positions) != positions.shape:
            raise ValueError(f"image_positions has shape {np.shape(self.image_positions)}; expected {positions.shape}")
        _checked_positions(self.image_positions)
        n = len(positions)
        shape = (len(self.settings.backgrounds), len(self.settings.intensities), len(self.settings.radii), n)
        for name, expected in (
            ("intensity_factor", (n,)),
            ("size_factor", (n,)),
            ("intensity_table", shape),
            ("size_table", shape),
        ):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != expected:
                raise ValueError(f"{name} has shape {value.shape}; expected {expected}")
            if not np.all(np.isfinite(value) & (value > 0)):
                raise ValueError(f"{name} must be finite and positive")

    @host_algebra
    def factors(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The correction factors for targets imaged at `points`.

        Linear between the calibration's `image_positions`, the nearest one's outside their
        hull; on a curved skin in the plane of their two principal directions (`_chart`),
        where a dome of up to 90 degrees or a cylinder patch of up to 180 lies one to one.

        Arguments:
            points: (N, D) or one point, metres, D the positions' dimension.

        Returns:
            (intensity g_I (N,), size g_S (N,)).

        Raises:
            ValueError: For points that are not finite points of the positions' dimension.
        """
        points = np.atleast_2d(np.asarray(points, dtype=float))
        dimension = np.shape(self.image_positions)[1]
        if points.ndim != 2 or points.shape[1] != dimension or not np.all(np.isfinite(points)):
            pairs = "(x, y) pairs" if dimension == 2 else "(x, y, z) points"
            raise ValueError(f"points must be finite {pairs}, shape (N, {dimension}); got shape {np.shape(points)}")
        values = np.column_stack([self.intensity_factor, self.size_factor])
        known = np.asarray(self.image_positions, dtype=float)
        if dimension == 3:
            origin, axes = _chart(known)
            known, points = (known - origin) @ axes.T, (points - origin) @ axes.T
        linear = scipy.interpolate.LinearNDInterpolator(known, values)(points)
        nearest = scipy.interpolate.NearestNDInterpolator(known, values)(points)
        result = np.where(np.isnan(linear), nearest, linear)
        return result[:, 0], result[:, 1]

    def save(self, path: str | Path) -> Path:
        """Write the calibration to `path`.

        An `.npz` archive (no pickles) with the schema, the format version, the arrays and the
        settings as JSON (docs/tutorials/calibration.md#the-spatial-correction).

        Arguments:
            path: The file to write (replaced if it exists).

        Returns:
            The path written.
        """
        path = Path(path)
        with path.open("wb") as file:
            np.savez(
                file,
                schema=np.array(SCHEMA),
                version=np.array(VERSION),
                settings=np.array(json.dumps(dataclasses.asdict(self.settings))),
                **{name: np.asarray(getattr(self, name)) for name in _ARRAYS},
            )
        return path


_ARRAYS = ("positions", "intensity_factor", "size_factor", "intensity_table", "size_table", "image_positions")


def load(path: str | Path) -> Calibration:
    """Read a calibration saved by `Calibration.save`.

    Version 1 files (no `image_positions`) still load: their factors are looked up at
    `positions`.

    Arguments:
        path: The `.npz` file.

    Returns:
        The `Calibration`.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file, for one that is not a calibration (not an .npz archive,
            another schema), of a format version this diffeit does not read (a newer one named
            by its number), or damaged: cut short or a changed byte (the archive is read whole,
            so every member's CRC-32 is checked), members missing, unknown or of another dtype
            or shape, settings that are not `CalibrationSettings`' fields and types.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no calibration file {path}")
    try:
        return _calibration(_npz_members(path.read_bytes()))
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def _npz_members(data: bytes) -> dict[str, np.ndarray]:
    """The arrays of an .npz archive by name (without ".npy"); every member read whole (its
    CRC-32 checked), no Python objects."""
    try:
        # From memory: a damaged size field cannot make zipfile allocate or wait for bytes.
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            contents = {info.filename: archive.read(info) for info in archive.infolist()}
    except Exception as error:  # zipfile raises many kinds on damage (BadZipFile, zlib.error, RuntimeError, ...)
        raise ValueError(f"not a readable .npz archive: {type(error).__name__}: {error}") from None
    members = {}
    for filename, content in contents.items():
        name = filename.removesuffix(".npy")
        if name == filename:
            raise ValueError(f"member {filename!r} is not a .npy array")
        members[name] = _npy_array(content, filename)
    return members


def _npy_array(content: bytes, filename: str) -> np.ndarray:
    """The array of a .npy member, its header checked against its length before reading."""
    stream = io.BytesIO(content)
    try:
        version = np.lib.format.read_magic(stream)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in read_header:
            raise ValueError(f".npy format version {version}")
        shape, fortran_order, dtype = read_header[version](stream)
    except ValueError as error:
        raise ValueError(f"member {filename!r} is not a readable .npy array: {error}") from None
    if dtype.hasobject:
        raise ValueError(f"member {filename!r} holds Python objects, which are not read")
    size = math.prod(shape) * dtype.itemsize
    if len(content) - stream.tell() != size:
        raise ValueError(
            f"member {filename!r} holds {len(content) - stream.tell()} bytes of values; its header "
            f"({dtype}, shape {shape}) needs {size}"
        )
    values = np.frombuffer(content, dtype, math.prod(shape), stream.tell())
    return values.reshape(shape, order="F" if fortran_order else "C").copy()


def _calibration(members: dict[str, np.ndarray]) -> Calibration:
    """The calibration in the members of its .npz archive, each checked."""
    schema = members.get("schema")
    if schema is None or schema.shape != () or schema.dtype.kind != "U" or str(schema) != SCHEMA:
        raise ValueError(f"not a diffeit calibration (schema {schema!r}, expected {SCHEMA!r})")
    version = members.get("version")
    if version is None or version.shape != () or version.dtype.kind not in "iu":
        raise ValueError(f"no format version (an integer); found {version!r}")
    if int(version) not in (1, VERSION):
        newer = ", a newer diffeit's" if int(version) > VERSION else ""
        raise ValueError(f"a calibration of format version {int(version)}{newer}; this diffeit reads 1..{VERSION}")
    # Version 1 had no image positions: its factors were looked up at the true positions.
    required = _ARRAYS if int(version) == VERSION else _ARRAYS[:-1]
    missing = [name for name in (*required, "settings") if name not in members]
    unknown = sorted(set(members) - {*required, "settings", "schema", "version"})
    if missing:
        raise ValueError(f"a version {int(version)} calibration lacks {missing}")
    if unknown:
        raise ValueError(f"a version {int(version)} calibration has no members {unknown}")
    arrays = {}
    for name in required:
        if members[name].dtype.kind not in "fiu":
            raise ValueError(f"{name} holds {members[name].dtype} values, not real numbers")
        arrays[name] = members[name].astype(np.float64)
    return Calibration(settings=_settings(members["settings"]), **arrays)


def _settings(stored: np.ndarray) -> CalibrationSettings:
    """`CalibrationSettings` from their JSON text, each field's type checked."""
    if stored.shape != () or stored.dtype.kind != "U":
        raise ValueError(f"settings are not one text (JSON); found {stored.dtype} of shape {stored.shape}")
    try:
        raw = json.loads(str(stored))
    except json.JSONDecodeError as error:
        raise ValueError(f"settings are not JSON: {error}") from None
    kinds = typing.get_type_hints(CalibrationSettings)
    if not isinstance(raw, dict) or set(raw) != set(kinds):
        raise ValueError(f"settings are not the fields {sorted(kinds)}: {str(stored)[:200]}")
    values = {}
    for name, kind in kinds.items():
        value = raw[name]
        if kind is str:
            valid = isinstance(value, str)
        elif kind is int:
            valid = isinstance(value, int) and not isinstance(value, bool)
        elif kind is float:
            valid = _is_number(value)
        else:  # tuple[float, ...], a JSON list
            valid = isinstance(value, list) and all(map(_is_number, value))
        if not valid:
            raise ValueError(f"setting {name} = {value!r} is not {kind.__name__ if isinstance(kind, type) else kind}")
        if isinstance(value, list):
            value = tuple(map(float, value))
        elif kind is float:
            value = float(value)
        values[name] = value
    return CalibrationSettings(**values)


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _checked_positions(positions: np.ndarray) -> np.ndarray:
    """(P, 2) finite calibration positions, or (P, 3) on a curved skin, P >= 3, not all on one
    line (the factors are interpolated on their Delaunay triangles)."""
    positions = np.asarray(positions, dtype=float)
    shaped = positions.ndim == 2 and positions.shape[1] in (2, 3) and len(positions) >= 3
    if not shaped or not np.all(np.isfinite(positions)):
        raise ValueError(
            f"positions must be finite, shape (P, 2) (or (P, 3) on a curved skin) with P >= 3 (metres); "
            f"got shape {positions.shape}"
        )
    if np.linalg.matrix_rank(positions[1:] - positions[0]) < 2:
        raise ValueError("positions all lie on one line: the factors need positions spanning the plane")
    return positions


def _chart(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean (D,) of points (P, D) on a curved skin and their two principal directions
    (2, D), orthonormal: the plane the skin is seen in from above."""
    origin = points.mean(axis=0)
    _, _, directions = np.linalg.svd(points - origin, full_matrices=False)
    return origin, directions[:2]


def default_positions(mesh: Mesh) -> np.ndarray:
    """The default calibration positions on a mesh: its centroid, then rings about it.

    The rings sit at 0.25, 0.45, 0.6 and 0.72 of the half-size R (half the largest side of the
    bounding box), with about one position per 0.45 R of circumference (at least 6 a ring),
    each ring turned half a step against the previous.

    On a curved skin the rings are drawn in the plane of the nodes' two principal directions
    (`_chart`) through the centroid and taken onto the surface (`diffeit.mesh.onto_surface`).

    Arguments:
        mesh: The mesh of the domain.

    Returns:
        (P, D) positions, metres (D = 3 on a curved skin): the area-weighted centroid first,
        then ring by ring.
    """
    centre = mesh.element_areas @ mesh.element_centroids / mesh.element_areas.sum()
    size = 0.5 * float(np.max(mesh.nodes.max(axis=0) - mesh.nodes.min(axis=0)))
    axes = np.eye(2) if mesh.nodes.shape[1] == 2 else _chart(mesh.nodes)[1]
    points = [centre]
    for ring, fraction in enumerate(_DEFAULT_RING_FRACTIONS[1:]):
        count = max(6, math.ceil(2 * np.pi * fraction / 0.45))
        angles = 2 * np.pi * (np.arange(count) + 0.5 * (ring % 2)) / count
        points.extend(centre + fraction * size * np.column_stack([np.cos(angles), np.sin(angles)]) @ axes)
    return onto_surface(mesh, np.array(points))


@host_algebra
def calibrate(
    model: ForwardModel,
    data_model: ForwardModel,
    *,
    prior: str = "noser",
    hyperparameter: float = 0.05,
    backgrounds: Sequence[float] = (0.01,),
    intensities: Sequence[float] = (-0.5,),
    radii: Sequence[float] = (0.15, 0.25),
    positions: np.ndarray | None = None,
    noise_percent: float = 0.5,
    noise_draws: int = 8,
    seed: int = 0,
    progress: bool = True,
) -> Calibration:
    """Calibrate the spatial correction factors for one-step reconstructions with `model`.

    Touches (smooth-edged discs) are simulated with `data_model` at every position for every
    combination of background, intensity and radius, with noise, reconstructed by `OneStep` on
    `model`, and the ratios of their peaks and half-amplitude radii to the reference's are
    tabulated where the touches appear in the images (docs/science.md#spatial-correction).

    Arguments:
        model: The reconstruction model (its mesh is the reconstruction mesh).
        data_model: The simulation model: the same domain and protocol, meshed finer (data from
            the reconstruction mesh itself would be an inverse crime).
        prior: The prior of the reconstruction to calibrate (`OneStep`), one per background.
        hyperparameter: Its hyperparameter (unit-free).
        backgrounds: Background conductivities, S/sq, > 0.
        intensities: Touch intensities dsigma/sigma, in (-1, 0) or > 0.
        radii: Touch radii, m, > 0.
        positions: (P, D) m (D the mesh's dimension: points on the surface of a curved skin),
            row 0 the reference; default `default_positions(model.mesh)`.
        noise_percent: Gaussian noise, percent of RMS(V_ref), >= 0 (0.5 is "medium").
        noise_draws: Noise draws per touch (>= 1): the reference is the noisiest position and
            its error enters every factor; 8 draws keep it to a few percent at medium noise.
        seed: The seed of the draws.
        progress: Show a tqdm bar over the settings.

    Returns:
        The `Calibration`.

    Raises:
        ValueError: For empty or invalid backgrounds, intensities or radii, a negative noise,
            noise draws that are not a positive integer, models of different protocols, invalid
            positions (or of another dimension than the mesh's), and a setting whose targets
            are lost (a peak of the wrong sign on average, so no positive factor: raise the
            intensity or the hyperparameter, or lower the noise).
    """
    backgrounds, intensities, radii = (tuple(float(v) for v in values) for values in (backgrounds, intensities, radii))
    for name, values, valid in (
        ("backgrounds", backgrounds, lambda v: v > 0),
        ("intensities", intensities, lambda v: v > -1 and v != 0),
        ("radii", radii, lambda v: v > 0),
    ):
        if not values or not all(np.isfinite(v) and valid(v) for v in values):
            raise ValueError(f"{name} must be a non-empty list of valid finite values; got {values}")
    if not (np.isfinite(noise_percent) and noise_percent >= 0):
        raise ValueError(f"noise_percent must be finite and >= 0; got {noise_percent}")
    if not (isinstance(noise_draws, int) and noise_draws >= 1):
        raise ValueError(f"noise_draws must be a positive integer; got {noise_draws!r}")
    if model.protocol.n_measurements != data_model.protocol.n_measurements:
        raise ValueError("model and data_model must share the protocol (the same number of measurements)")
    positions = default_positions(model.mesh) if positions is None else _checked_positions(positions)
    if positions.shape[1] != model.mesh.nodes.shape[1]:
        raise ValueError(
            f"positions have {positions.shape[1]} coordinates; the mesh's nodes have {model.mesh.nodes.shape[1]}"
        )

    mesh, data_mesh = model.mesh, data_model.mesh
    measure = jax.jit(jax.vmap(data_model.measure))
    shape = (len(backgrounds), len(intensities), len(radii), len(positions))
    intensity_table, size_table = np.empty(shape), np.empty(shape)
    image_positions = np.zeros(positions.shape)
    settings = [(b, a, r) for b in range(len(backgrounds)) for a in range(len(intensities)) for r in range(len(radii))]
    key = jax.random.key(seed)
    reconstructions = {}
    for index, (b, a, r) in enumerate(tqdm(settings, desc="calibration settings", disable=not progress)):
        background = backgrounds[b]
        if b not in reconstructions:
            reconstructions[b] = OneStep(model, prior, hyperparameter, background=background)
        fields = _touch_fields(data_mesh, jnp.asarray(positions), radii[r], intensities[a])  # (P, E_data)
        reference = data_model.measure(jnp.full(data_mesh.n_elements, background))
        clean = measure(background * (1 + fields)) - reference  # (P, M)
        frames = jnp.broadcast_to(clean, (noise_draws, *clean.shape)).reshape(-1, clean.shape[-1])
        if noise_percent > 0:
            frames = add_noise(frames, reference, Noise.percent(noise_percent), jax.random.fold_in(key, index))
        images = np.asarray(reconstructions[b].solve(frames).value).reshape(noise_draws, len(positions), -1)
        peaks = np.array([[metrics.peak(image) for image in draw] for draw in images]).mean(axis=0)
        sizes = np.array([[metrics.equivalent_radius(mesh, image) for image in draw] for draw in images]).mean(axis=0)
        centroids = [[metrics.half_amplitude_centroid(mesh, image) for image in draw] for draw in images]
        image_positions += np.mean(centroids, axis=0) / len(settings)
        intensity_table[b, a, r] = peaks[0] / peaks
        size_table[b, a, r] = sizes[0] / sizes
        lost = np.flatnonzero(np.sign(peaks) != np.sign(intensities[a]))  # the reference's too
        if len(lost):
            raise ValueError(
                f"targets lost in the noise (mean peak of the wrong sign) at positions {positions[lost].tolist()}"
                f"{' (row 0: the reference)' if lost[0] == 0 else ''} "
                f"for background {background}, intensity {intensities[a]}, radius {radii[r]}: raise the intensity "
                "or the hyperparameter, or lower the noise"
            )
    return Calibration(
        positions=positions,
        image_positions=image_positions,
        intensity_factor=np.exp(np.log(intensity_table).mean(axis=(0, 1, 2))),
        size_factor=np.exp(np.log(size_table).mean(axis=(0, 1, 2))),
        intensity_table=intensity_table,
        size_table=size_table,
        settings=CalibrationSettings(
            prior=prior if isinstance(prior, str) else repr(prior),
            hyperparameter=float(hyperparameter),
            backgrounds=backgrounds,
            intensities=intensities,
            radii=radii,
            noise_percent=float(noise_percent),
            noise_draws=noise_draws,
            seed=seed,
            n_elements=mesh.n_elements,
            n_data_elements=data_mesh.n_elements,
        ),
    )


def _touch_fields(mesh: Mesh, centres: jax.Array, radius: float, intensity: float) -> jax.Array:
    """(P, E) dsigma/sigma of smooth-edged disc touches at `centres` (P, D), one vmapped field."""
    return jax.vmap(lambda centre: touch_field(mesh, Touch(Disc(centre, radius), intensity), 0.0))(centres)


@host_algebra
def correct(calibration: Calibration, mesh: Mesh, image: np.ndarray) -> np.ndarray:
    """Correct an element image for the position dependence of the reconstruction.

    Each half-amplitude target is scaled by g_I in amplitude and g_S in extent about its
    centroid, with the factors at that centroid; every element moves with the target whose
    centroid is nearest (docs/science.md#spatial-correction).

    Arguments:
        calibration: The `Calibration`, made for this reconstruction.
        mesh: The mesh of the image.
        image: An element image (E,) or a batch (T, E), in any unit.

    Returns:
        The corrected image(s), same shape and unit.

    Raises:
        ValueError: For an image that is not (E,) or (T, E) on `mesh`, or a mesh of another
            dimension than the calibration's positions.
    """
    if mesh.nodes.shape[1] != np.shape(calibration.positions)[1]:
        raise ValueError(
            f"the calibration's positions have {np.shape(calibration.positions)[1]} coordinates; "
            f"the mesh's nodes have {mesh.nodes.shape[1]}"
        )
    images = np.asarray(image, dtype=float)
    if images.ndim not in (1, 2) or images.shape[-1] != mesh.n_elements:
        raise ValueError(f"image has shape {images.shape}; expected ({mesh.n_elements},) or (T, {mesh.n_elements})")
    corrected = np.stack([_correct_one(calibration, mesh, frame) for frame in np.atleast_2d(images)])
    return corrected.reshape(images.shape)


def _correct_one(calibration: Calibration, mesh: Mesh, image: np.ndarray) -> np.ndarray:
    components = metrics.amplitude_components(mesh, image)
    # Specks of noise in the half-amplitude set are no targets: they move with the nearest one.
    centroids = components.centroids[components.areas >= _TARGET_AREA_FRACTION * components.areas[0]]
    intensity, size = calibration.factors(centroids)
    # The warped image averaged over each element: sample points on `_WARP_LEVEL`^2
    # sub-triangles, each pulled back to where its value comes from in the uncorrected image.
    points = element_sample_points(mesh, _WARP_LEVEL)  # (E, S, D)
    owner = np.argmin(np.linalg.norm(mesh.element_centroids[:, None, :] - centroids[None], axis=2), axis=1)
    centre = centroids[owner][:, None, :]
    sources = (centre + (points - centre) / size[owner, None, None]).reshape(-1, points.shape[-1])
    element = locate(mesh, sources) if mesh.nodes.shape[1] == 2 else _located_on_surface(mesh, sources)
    values = np.where(element >= 0, image[np.maximum(element, 0)], 0.0).reshape(points.shape[:2])
    return intensity[owner] * values.mean(axis=1)


def _located_on_surface(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """(P,) the element of a curved skin holding each point (P, 3) once taken onto the surface:
    the one whose centroid is nearest, -1 (off the mesh) where that is farther than any
    element's corner from its own centroid."""
    element, distance, _ = nearest_element(mesh, onto_surface(mesh, points))
    reach = float(np.max(np.linalg.norm(mesh.nodes[mesh.triangles] - mesh.element_centroids[:, None], axis=2)))
    return np.where(distance <= reach, element, -1)
