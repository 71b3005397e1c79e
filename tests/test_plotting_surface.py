"""Pictures on skins on curved surfaces: element images drawn in 3D axes, the electrodes marked."""

import dataclasses
import types

import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d import Axes3D
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

import diffeit as de
from diffeit.cli._fit import plot_fit
from diffeit.plotting import mesh_projection, plot_elements, plot_image_strip
from diffeit.results import RESULTS

N_ELECTRODES = 16


def _touch_image(mesh: de.Mesh, centre: np.ndarray, radius: float) -> np.ndarray:
    """A one-step image (dsigma, S/sq) of a press lowering the conductivity of the elements
    within `radius` of `centre` (metres, straight-line distance) by half."""
    model = de.ForwardModel(mesh, de.protocol.adjacent(mesh.n_electrodes), contact_impedance=0.01)
    background = jnp.ones(mesh.n_elements)
    pressed = np.linalg.norm(mesh.element_centroids - centre, axis=1) < radius
    differences = model.measure(background * (1 - 0.5 * pressed)) - model.measure(background)
    return np.asarray(de.inverse.OneStep(model, "noser", 0.05).solve(differences).value)


@pytest.fixture(scope="module")
def dome():
    mesh = de.mesh.sphere_cap(1.0, 0.4 * np.pi, N_ELECTRODES, 0.2)
    return mesh, _touch_image(mesh, np.array([0.4, 0.2, np.sqrt(0.8)]), 0.3)


@pytest.fixture(scope="module")
def forearm():
    mesh = de.mesh.cylinder_patch(1.0, 2.0, 0.8 * np.pi, N_ELECTRODES, 0.2)
    return mesh, _touch_image(mesh, np.array([np.cos(0.3), np.sin(0.3), 0.3]), 0.35)


def _draw(path, mesh, image):
    figure = Figure(figsize=(5, 4.5), layout="constrained")
    ax = figure.add_subplot(projection=mesh_projection(mesh))
    artist = plot_elements(ax, mesh, image, label="dsigma (S/sq)")
    figure.savefig(path, dpi=110)
    return ax, artist


@pytest.mark.parametrize("skin", ["dome", "forearm"])
def test_a_touch_on_a_curved_skin_is_drawn_in_3d(skin, request, tmp_path):
    mesh, image = request.getfixturevalue(skin)
    assert image.min() < -0.3 * np.abs(image).max()  # a press lowers the conductivity
    ax, artist = _draw(tmp_path / "skin.png", mesh, image)

    assert isinstance(ax, Axes3D) and isinstance(artist, Poly3DCollection)
    assert len(artist.get_paths()) == mesh.n_elements
    low, high = artist.get_clim()
    assert low == pytest.approx(-np.abs(image).max()) and high == -low  # symmetric, as flat
    # The pressed triangle's colour is not an untouched one's, and both are on the surface drawn.
    colours = artist.to_rgba(artist.get_array())
    pressed, untouched = np.argmin(image), np.argmin(np.abs(image))
    assert np.abs(colours[pressed] - colours[untouched]).max() > 0.3
    drawn = artist.get_facecolor()  # depth-sorted by the draw
    for colour in (colours[pressed], colours[untouched]):
        assert np.any(np.all(np.isclose(drawn, colour), axis=1))

    lines = [line for line in ax.get_lines() if line.get_label().startswith("electrode ")]
    assert len(lines) == mesh.n_electrodes
    in_front = [line for line in lines if line.get_linewidth() == 4]
    assert len(in_front) >= mesh.n_electrodes // 2  # the default view sees the skin from outside
    assert [text.get_text() for text in ax.texts] == ["0"]
    box = np.asarray(ax.get_box_aspect())
    ranges = np.ptp(mesh.nodes, axis=0)
    np.testing.assert_allclose(box / box.max(), ranges / ranges.max(), rtol=1e-6)  # equal aspect

    picture = matplotlib.image.imread(tmp_path / "skin.png")
    height, width = picture.shape[:2]
    inked = np.any(picture[..., :3] < 0.9, axis=2)
    rows, columns = np.flatnonzero(inked.any(axis=1)), np.flatnonzero(inked.any(axis=0))
    assert np.ptp(rows) > 0.6 * height and np.ptp(columns) > 0.6 * width  # not blank, not a speck
    blue = (picture[..., 2] - picture[..., 0]) > 0.3  # the press, in RdBu_r
    assert blue.sum() > 0.005 * height * width


def test_a_curved_skin_needs_3d_axes(dome):
    mesh, image = dome
    ax = Figure().add_subplot()
    with pytest.raises(ValueError, match='projection="3d"'):
        plot_elements(ax, mesh, image)


def test_the_flat_skin_is_still_drawn_in_2d():
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.3)
    assert mesh_projection(mesh) is None
    ax = Figure().add_subplot()
    artist = plot_elements(ax, mesh, np.linspace(-1, 2, mesh.n_elements))
    assert not isinstance(artist, Poly3DCollection) and artist.get_clim() == (-2, 2)
    assert len(ax.get_lines()) == 16 and [text.get_text() for text in ax.texts] == ["0"]


def test_an_image_strip_of_a_curved_skin_has_3d_panels(dome, tmp_path):
    mesh, image = dome
    images = np.outer([0.0, 0.5, 1.0], image)
    shown = plot_image_strip(tmp_path / "strip.png", mesh, images, times=np.arange(3.0), title="dome")
    np.testing.assert_array_equal(shown, [0, 1, 2])
    picture = matplotlib.image.imread(tmp_path / "strip.png")
    assert picture.shape[1] > 2 * picture.shape[0]
    # Touches marked in 3D: points on the dome (NaN where a frame has fewer), drawn as +.
    points = np.full((3, 2, 3), np.nan)
    points[1:, 0] = mesh.element_centroids[np.argmax(image)]
    marked = tmp_path / "marked.png"
    plot_image_strip(marked, mesh, images, times=np.arange(3.0), title="dome", points=points)
    assert np.abs(matplotlib.image.imread(marked) - matplotlib.image.imread(tmp_path / "strip.png")).max() > 0.1
    with pytest.raises(ValueError, match=r"points have shape \(3, 2, 2\); expected \(3, K, 3\)"):
        plot_image_strip(marked, mesh, images, points=points[..., :2])


@dataclasses.dataclass
class _Memory:
    gain: float = 0.5


def test_the_fit_figure_of_a_curved_skin_draws_in_3d(forearm, tmp_path):
    mesh, image = forearm
    frames = np.outer([0.0, 1.0, 0.5], image)
    fit = types.SimpleNamespace(
        background=np.full(mesh.n_elements, 2.0) + 0.1 * image,
        stimulus=0.9 * frames,
        contact_impedance=np.full(mesh.n_electrodes, 0.01),
        memory=_Memory(),
        misfit=0.01,
        history=types.SimpleNamespace(objective=np.array([1.0, 0.1])),
        result=RESULTS.successful,
        settings=types.SimpleNamespace(memory_fitted=()),
    )
    shown = plot_fit(tmp_path / "fit.png", mesh, fit, frames, times=np.arange(3.0) / 10)
    np.testing.assert_array_equal(shown, [0, 1, 2])
    assert matplotlib.image.imread(tmp_path / "fit.png").shape[0] > 500
