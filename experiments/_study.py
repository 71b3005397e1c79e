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
import numpy as np

jax.config.update("jax_enable_x64", True)  # the studies compute in float64, as diffeit does

import diffeit as de

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


def write_table(path: Path, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Write `rows` (dicts with the same keys) as CSV; floats with 6 significant digits."""
    rows = list(rows)
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: f"{v:.6g}" if isinstance(v, float) else v for k, v in row.items()})
    return path


def machine() -> str:
    """The machine a result was made on, in words (for the results' provenance)."""
    return f"{platform.machine()}, {platform.system()}, Python {platform.python_version()}, JAX {jax.__version__}"


def stamp() -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
