"""What every study shares: the `Study` record, its findings, the physical skin, noise levels,
simulated touches and the writing of tables and figures."""

from __future__ import annotations

import csv
import dataclasses
import platform
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

jax.config.update("jax_enable_x64", True)  # the studies compute in float64, as diffeit does

import diffeit as de
from diffeit.plotting import plot_elements

# The skin: a disc of radius 0.08 m (the dissertation's figures use a unit disc: lengths below
# are also given as fractions of the radius), 16 electrodes each 0.2 R wide, 0.01 S/sq.
RADIUS = 0.08
ELECTRODE_WIDTH = 0.2 * RADIUS
BACKGROUND = 0.01
CONTACT_IMPEDANCE = 0.01 * RADIUS  # ohm m: 0.01 ohm m on the unit disc, scaled with the lengths
# Noise, percent of RMS(V_ref) (docs/science.md#noise): the dissertation names the levels only.
NOISE_LEVELS = {"noise-free": 0.0, "low": 0.1, "medium": 0.5, "high": 2.0}


@dataclasses.dataclass(frozen=True)
class Findings:
    """A study's headline numbers (`values`, JSON-serialisable), the sentences that state its
    findings (`statements`), and the files it wrote."""

    values: dict[str, Any]
    statements: tuple[str, ...]
    files: tuple[Path, ...]


@dataclasses.dataclass(frozen=True)
class Study:
    """A study: `name` (the CLI's), `figure` (the dissertation's figure numbers), `title`, and
    `run(folder, small=..., progress=...) -> Findings`."""

    name: str
    figure: str
    title: str
    run: Callable[..., Findings]


def skin(h_fraction: float) -> de.Mesh:
    """The skin's mesh with element size `h_fraction` R."""
    return de.mesh.disc(16, electrode_width=ELECTRODE_WIDTH, h=h_fraction * RADIUS, radius=RADIUS)


def model(mesh: de.Mesh) -> de.ForwardModel:
    return de.ForwardModel(mesh, de.protocol.adjacent(16), contact_impedance=CONTACT_IMPEDANCE)


def disc_change(mesh: de.Mesh, centres: Sequence[Sequence[float]], radius: float, amplitude: float) -> np.ndarray:
    """(E,) the relative change dsigma/sigma of discs of `radius` (m) at `centres` (m), each
    `amplitude` (a touch: negative) over the area it covers."""
    change = np.zeros(mesh.n_elements)
    for centre in centres:
        change += amplitude * de.mesh.disc_fraction(mesh, tuple(centre), radius)
    return change


def noisy(clean: np.ndarray, reference: np.ndarray, percent: float, seed: int) -> np.ndarray:
    """`clean` plus Gaussian noise of `percent` % of RMS(`reference`), seeded."""
    scale = percent / 100 * np.sqrt(np.mean(reference**2))
    return clean + np.random.default_rng(seed).normal(0.0, scale, np.shape(clean))


def is_clean(figures: de.metrics.TargetFigures) -> bool:
    """Whether a half-amplitude image is clean: one component per touch, each matched to its
    touch, and no artifact."""
    return bool(figures.matched.all()) and figures.n_artifacts == 0


def clean_range(clean: np.ndarray, min_run: int = 3) -> tuple[int | None, int | None]:
    """The image-based optimum on a grid of hyperparameters: (first, last) index of the longest
    run of consecutive clean values (`clean`, ascending hyperparameters; the lower one of equal
    runs), or (None, None) when no run is `min_run` long (a lucky draw is not a range).

    The first index is the image-based optimal hyperparameter (the sharpest clean image); the
    last is where the blurred touches merge or the far lobe of the smoothest mode passes half
    the peak."""
    best, start = (None, None), None
    for k, value in enumerate([*np.asarray(clean, bool), False]):
        if value and start is None:
            start = k
        elif not value and start is not None:
            if k - start >= min_run and (best[0] is None or k - 1 - start > best[1] - best[0]):
                best = (start, k - 1)
            start = None
    return best


def write_table(path: Path, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Write `rows` (dicts with the same keys) as CSV; floats with 6 significant digits."""
    rows = list(rows)
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: f"{v:.6g}" if isinstance(v, float) else v for k, v in row.items()})
    return path


def save_figure(figure: Figure, path: Path, dpi: int = 100) -> Path:
    """Save `figure` as a PNG at `path` (laid out tightly unless it has a layout engine of its
    own), close it, and return `path`."""
    if figure.get_layout_engine() is None:
        figure.tight_layout()
    figure.savefig(path, dpi=dpi)
    plt.close(figure)
    return path


def draw_image(
    ax: Any, mesh: de.Mesh, image: np.ndarray, truths: Sequence[Sequence[float]], radius: float, title: str
) -> None:
    """Draw one relative-change image (E,) on `ax` with its colour bar, circle each true touch
    (centres `truths`, radius `radius`, m) and title it."""
    plot_elements(ax, mesh, image, label="dsigma/sigma", electrodes=False)
    for centre in truths:
        ax.add_patch(plt.Circle(tuple(centre), radius, fill=False, color="k", linewidth=0.8))
    ax.set_title(title, fontsize=8)
    ax.set_aspect("equal")


def machine() -> str:
    """The machine a result was made on, in words (for the results' provenance)."""
    return f"{platform.machine()}, {platform.system()}, Python {platform.python_version()}, JAX {jax.__version__}"


def stamp() -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
