"""The demo: image one touch on a 16-electrode skin from simulated noisy voltages.

`run_demo` images a touch on the flat unit disc (`make demo`); `run_curved_demo` one on a
curved skin (`SKINS`): a forearm (a cylinder patch) or a fingertip (a sphere cap), simulated by
the scene simulator (`diffeit.simulate`) and drawn in 3D.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from . import mesh as meshes
from . import metrics, protocol
from .forward import ForwardModel
from .inverse import OneStep, select_hyperparameter
from .plotting import mesh_projection, plot_elements

BACKGROUND = 0.01  # S/sq, the main skin of the dissertation
CONTACT_IMPEDANCE = 0.01  # ohm m
TOUCH_CENTRE = (0.5, 0.0)  # m, on the unit disc
TOUCH_RADIUS = 0.1  # m
TOUCH_CHANGE = -0.3  # dsigma / sigma: a touch strains the skin and lowers its conductivity
NOISE_PERCENT = 1.0  # of RMS(V_reference) (docs/science.md#noise)
DATA_H, RECONSTRUCTION_H = 0.03, 0.06  # element sizes: data on a finer mesh


@dataclass(frozen=True)
class CurvedSkin:
    """A curved skin of the demo: its `diffeit.scene.Skin` geometry and element sizes, and the
    touch on it (a `Disc` centred on the surface)."""

    geometry: dict  # the Skin's geometry (metres, radians)
    h: float  # m, the reconstruction mesh's element size
    simulation_h: float  # m, the simulation mesh's
    touch_centre: tuple[float, float, float]  # m, on the surface
    touch_radius: float  # m, a chord (`diffeit.scene.Disc`)


# The curved skins of `run_curved_demo`: a forearm (radius 4 cm, 15 cm long, 150 degrees round)
# and a fingertip (a cap of a 1 cm sphere, 70 degrees from its pole).
SKINS = {
    "forearm": CurvedSkin(
        geometry={
            "kind": "cylinder_patch",
            "radius": 0.04,
            "length": 0.15,
            "angle": np.radians(150.0),
            "n_electrodes": 16,
        },
        h=0.008,
        simulation_h=0.004,
        touch_centre=(0.04 * np.cos(np.radians(25.0)), 0.04 * np.sin(np.radians(25.0)), 0.025),
        touch_radius=0.012,
    ),
    "fingertip": CurvedSkin(
        geometry={"kind": "sphere_cap", "radius": 0.01, "polar_angle": np.radians(70.0), "n_electrodes": 16},
        h=0.0012,
        simulation_h=0.0006,
        touch_centre=(0.01 * np.sin(np.radians(30.0)), 0.0, 0.01 * np.cos(np.radians(30.0))),
        touch_radius=0.003,
    ),
}


@dataclass(frozen=True)
class DemoResult:
    position_error: float  # m
    correlation: float
    hyperparameter: float  # chosen by generalised cross-validation
    peak: float  # reconstructed dsigma of largest magnitude, S/sq
    n_data_elements: int
    n_reconstruction_elements: int
    figure: Path


def run_demo(output: str | Path = "demo.png", seed: int = 0) -> DemoResult:
    """Image a touch on the flat unit disc: simulate, reconstruct, save truth beside the image.

    A touch (dsigma/sigma `TOUCH_CHANGE`, radius `TOUCH_RADIUS` m at `TOUCH_CENTRE`) on a
    16-electrode unit disc of `BACKGROUND` S/sq is simulated on a fine mesh (element size
    `DATA_H` m, adjacent protocol, contact impedance `CONTACT_IMPEDANCE` ohm m), with
    `NOISE_PERCENT` of RMS(V_ref) noise on the difference; a one-step NOSER image on the coarser
    reconstruction mesh (`RECONSTRUCTION_H` m; hyperparameter by generalised
    cross-validation) is drawn beside the truth on that mesh and saved to `output` (PNG).

    Arguments:
        output: The PNG to write (replaced if it exists).
        seed: The noise seed.

    Returns:
        The `DemoResult`: the position error is the distance from the touch's centre to the
        image's half-amplitude centroid (metres), the peak in S/sq.
    """
    adjacent = protocol.adjacent(16)
    data_mesh = meshes.disc(16, electrode_width=0.2, h=DATA_H)
    data_model = ForwardModel(data_mesh, adjacent, CONTACT_IMPEDANCE)
    truth_fine = BACKGROUND * TOUCH_CHANGE * meshes.disc_fraction(data_mesh, TOUCH_CENTRE, TOUCH_RADIUS)
    reference = data_model.measure(jnp.full(data_mesh.n_elements, BACKGROUND))
    touched = data_model.measure(BACKGROUND + truth_fine)
    rng = np.random.default_rng(seed)
    noise_std = NOISE_PERCENT / 100 * np.sqrt(np.mean(np.asarray(reference) ** 2))
    difference = np.asarray(touched - reference) + noise_std * rng.standard_normal(reference.shape)

    mesh = meshes.disc(16, electrode_width=0.2, h=RECONSTRUCTION_H)
    model = ForwardModel(mesh, adjacent, CONTACT_IMPEDANCE)
    hyperparameter, image = _one_step(model, difference)
    truth = BACKGROUND * TOUCH_CHANGE * meshes.disc_fraction(mesh, TOUCH_CENTRE, TOUCH_RADIUS)
    error = metrics.position_error(mesh, image, TOUCH_CENTRE)

    figure = Figure(figsize=(10, 4.4), layout="constrained")
    left, right = figure.subplots(1, 2)
    plot_elements(left, data_mesh, truth_fine, label="dsigma (S/sq)")
    left.set_title(
        f"truth: touch r={TOUCH_RADIUS} at {TOUCH_CENTRE}, dsigma/sigma={TOUCH_CHANGE}\n"
        f"data mesh {data_mesh.n_elements} triangles, {NOISE_PERCENT:g}% noise",
        fontsize=9,
    )
    plot_elements(right, mesh, image, label="dsigma (S/sq)")
    centroid = metrics.half_amplitude_centroid(mesh, image)
    for ax in (left, right):
        ax.add_patch(Circle(TOUCH_CENTRE, TOUCH_RADIUS, fill=False, linestyle="--", color="k"))
    right.plot(*centroid, "k+", markersize=12)
    right.set_title(
        f"one-step NOSER, hyperparameter {hyperparameter:.3g} (GCV), {mesh.n_elements} triangles\n"
        f"position error {error:.3f} m (+: half-amplitude centroid)",
        fontsize=9,
    )
    return _saved(figure, output, mesh, data_mesh, truth, image, error, hyperparameter)


def run_curved_demo(skin: str = "forearm", output: str | Path = "demo.png", seed: int = 0) -> DemoResult:
    """Image a touch on a curved skin: simulate, reconstruct, save truth beside the image.

    The scene simulator (`diffeit.simulate`) gives one frame of a touch (dsigma/sigma
    `TOUCH_CHANGE`) on the skin of `SKINS[skin]` meshed finely, with `NOISE_PERCENT` of
    RMS(V_ref) noise on the frame and on the reference; a one-step NOSER image on the coarser
    reconstruction mesh (hyperparameter by generalised cross-validation) is drawn in 3D beside
    the truth on that mesh, and saved to `output` (PNG).

    Arguments:
        skin: The name of a skin in `SKINS`: "forearm" (a cylinder patch) or "fingertip" (a
            sphere cap).
        output: The PNG to write.
        seed: The noise seed.

    Returns:
        The `DemoResult`: the position error is the 3D distance from the touch's centre to the
        image's half-amplitude centroid (metres), the peak in S/sq.

    Raises:
        ValueError: For a skin not in `SKINS`.
    """
    from .scene import Background, Disc, MeasurementNoise, Noise, Scene, Skin, Touch, simulate, touch_field

    if skin not in SKINS:
        raise ValueError(f"unknown demo skin {skin!r}; skins are {sorted(SKINS)} (or the flat default)")
    chosen = SKINS[skin]
    touch = Touch(Disc(chosen.touch_centre, chosen.touch_radius), TOUCH_CHANGE)
    scene = Scene(
        skin=Skin(
            geometry=chosen.geometry,
            h=chosen.h,
            simulation_h=chosen.simulation_h,
            contact_impedance=CONTACT_IMPEDANCE,
        ),
        background=Background(BACKGROUND),
        touches=(touch,),
        frame_rate=1.0,
        duration=1.0,
        effects=(MeasurementNoise(Noise(NOISE_PERCENT, "percent"), seed),),
        name=f"demo {skin}",
    )
    simulation = simulate(scene, progress=False)
    difference = np.asarray(simulation.frames[0] - simulation.reference)
    data_mesh = simulation.mesh

    mesh = scene.reconstruction_mesh()
    model = ForwardModel(mesh, scene.skin.make_protocol(), CONTACT_IMPEDANCE)
    hyperparameter, image = _one_step(model, difference)
    surface = scene.skin.surface
    truth = BACKGROUND * np.asarray(touch_field(mesh, touch, 0.0, surface=surface))
    centroid = metrics.half_amplitude_centroid(mesh, image)
    error = float(np.linalg.norm(centroid - np.asarray(chosen.touch_centre)))

    figure = Figure(figsize=(11, 4.8), layout="constrained")
    left = figure.add_subplot(1, 2, 1, projection=mesh_projection(mesh))
    right = figure.add_subplot(1, 2, 2, projection=mesh_projection(mesh))
    plot_elements(left, mesh, truth, label="dsigma (S/sq)")
    centre_mm = ", ".join(f"{1e3 * x:.0f}" for x in chosen.touch_centre)
    left.set_title(
        f"truth on the {skin}: touch r={1e3 * chosen.touch_radius:g} mm at ({centre_mm}) mm\n"
        f"dsigma/sigma={TOUCH_CHANGE}, data from {data_mesh.n_elements} triangles, {NOISE_PERCENT:g}% noise",
        fontsize=9,
    )
    plot_elements(right, mesh, image, label="dsigma (S/sq)")
    right.plot(*np.asarray(chosen.touch_centre)[:, None], "kx", markersize=9, zorder=5)
    right.plot(*centroid[:, None], "k+", markersize=12, zorder=5)
    right.set_title(
        f"one-step NOSER, hyperparameter {hyperparameter:.3g} (GCV), {mesh.n_elements} triangles\n"
        f"position error {1e3 * error:.1f} mm (x: touch centre, +: half-amplitude centroid)",
        fontsize=9,
    )
    return _saved(figure, output, mesh, data_mesh, truth, image, error, hyperparameter)


def _one_step(model: ForwardModel, difference: np.ndarray) -> tuple[float, np.ndarray]:
    """The hyperparameter generalised cross-validation chooses from the data (never tuned to
    the truth; one at an end of the candidates is still used, throw=False: the demo always
    draws its figure), and the one-step NOSER image (E,) of `difference` at it, S/sq."""
    hyperparameter = select_hyperparameter(model, difference, "gcv", background=BACKGROUND, throw=False).value
    image = np.asarray(OneStep(model, "noser", hyperparameter, BACKGROUND).solve(difference).value)
    return hyperparameter, image


def _saved(
    figure: Figure,
    output: str | Path,
    mesh: meshes.Mesh,
    data_mesh: meshes.Mesh,
    truth: np.ndarray,
    image: np.ndarray,
    error: float,
    hyperparameter: float,
) -> DemoResult:
    """Save `figure` to `output` (PNG) and return the demo's figures of merit."""
    output = Path(output)
    figure.savefig(output, dpi=120)
    return DemoResult(
        position_error=error,
        hyperparameter=hyperparameter,
        correlation=metrics.correlation(mesh, truth, image),
        peak=metrics.peak(image),
        n_data_elements=data_mesh.n_elements,
        n_reconstruction_elements=mesh.n_elements,
        figure=output,
    )
