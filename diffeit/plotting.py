"""Figures of element-wise images on meshes and of hyperparameter curves (matplotlib, no
display needed)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib.tri
import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from .mesh import Mesh
from .results import failed, messages

if TYPE_CHECKING:
    from .inverse import HyperparameterSelection


def plot_elements(
    ax: Axes,
    mesh: Mesh,
    values: np.ndarray,
    *,
    cmap: str = "RdBu_r",
    symmetric: bool = True,
    label: str | None = None,
    electrodes: bool = True,
) -> PolyCollection:
    """Draw element values on a mesh into axes, with a colour bar.

    Electrodes are drawn as thick dark lines, electrode 0 numbered.

    Arguments:
        ax: The matplotlib axes.
        mesh: The mesh.
        values: (E,) one value per element, in any unit.
        cmap: The matplotlib colour map.
        symmetric: Centre the colour scale on 0 (from -max |values| to max |values|).
        label: The colour bar's label.
        electrodes: Draw the electrodes.

    Returns:
        The `PolyCollection` of the elements.
    """
    triangulation = matplotlib.tri.Triangulation(mesh.nodes[:, 0], mesh.nodes[:, 1], mesh.triangles)
    values = np.asarray(values, dtype=float)
    limit = np.max(np.abs(values)) if symmetric else None
    artist = ax.tripcolor(
        triangulation,
        facecolors=values,
        cmap=cmap,
        vmin=-limit if symmetric else None,
        vmax=limit if symmetric else None,
    )
    if electrodes:
        for index, chain in enumerate(mesh.electrodes):
            xy = mesh.nodes[chain]
            ax.plot(xy[:, 0], xy[:, 1], color="0.1", linewidth=4, solid_capstyle="butt")
            if index == 0:
                middle = xy[len(xy) // 2] * 1.08
                ax.annotate("0", middle, ha="center", va="center", fontsize=8)
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.figure.colorbar(artist, ax=ax, shrink=0.8, label=label)
    return artist


def plot_image_strip(
    path: str | Path,
    mesh: Mesh,
    images: np.ndarray,
    *,
    times: np.ndarray | None = None,
    max_panels: int = 12,
    title: str | None = None,
    label: str = "dsigma (S/sq)",
) -> np.ndarray:
    """Save a strip of element-wise images on a mesh as a PNG.

    Every k-th frame, at most `max_panels` panels, six to a row, one colour scale centred on 0
    for all. Panel titles give the frame index and, with `times`, its time.

    Arguments:
        path: The PNG file to write.
        mesh: The mesh.
        images: (T, E) the images, in any unit.
        times: (T,) the frames' times, seconds; None leaves them out.
        max_panels: The most panels, at least 1.
        title: The figure's title; None for none.
        label: The colour bar's label.

    Returns:
        The indices of the frames shown.

    Raises:
        ValueError: For images not of shape (T, E), no frame, or `max_panels` below 1.
    """
    images = np.asarray(images, dtype=float)
    if images.ndim != 2 or images.shape[1] != mesh.n_elements:
        raise ValueError(f"images have shape {images.shape}; expected (T, {mesh.n_elements})")
    if max_panels < 1 or len(images) == 0:
        raise ValueError("an image strip needs at least one panel and one frame")
    shown = np.arange(0, len(images), math.ceil(len(images) / max_panels))
    limit = float(np.max(np.abs(images[shown]))) or 1.0
    columns = min(len(shown), 6)
    rows = math.ceil(len(shown) / columns)
    figure = Figure(figsize=(1.7 * columns + 0.9, 1.8 * rows + (0.4 if title else 0)), layout="constrained")
    axes = np.atleast_1d(figure.subplots(rows, columns, squeeze=False)).ravel()
    for ax, frame in zip(axes, shown, strict=False):
        artist = plot_elements(ax, mesh, images[frame], label=None)
        artist.set_clim(-limit, limit)
        artist.colorbar.remove()  # one shared colour bar for the strip instead of one per panel
        when = f", {times[frame]:.2f} s" if times is not None else ""
        ax.set_title(f"frame {frame}{when}", fontsize=7)
    for ax in axes[len(shown) :]:
        ax.set_axis_off()
    figure.colorbar(artist, ax=list(axes), shrink=0.8, label=label)
    if title:
        figure.suptitle(title, fontsize=9)
    figure.savefig(path, dpi=110)
    return shown


def plot_hyperparameter_selection(selection: HyperparameterSelection, path: str | Path | None = None) -> Figure:
    """Plot the curves a hyperparameter was chosen from.

    The criterion against lambda, and the L-curve (residual norm against solution norm), the
    chosen value marked on both; the title names a failed selection's result.

    Arguments:
        selection: The `HyperparameterSelection`.
        path: A PNG file to save the figure to; None does not save it.

    Returns:
        The matplotlib `Figure`.
    """
    figure = Figure(figsize=(10, 4), layout="constrained")
    left, right = figure.subplots(1, 2)
    candidates, chosen = selection.candidates, selection.value
    names = {
        "gcv": "GCV function",
        "lcurve": "L-curve curvature",
        "discrepancy": "residual norm / noise norm",
        "noise_figure": "noise figure",
    }
    left.plot(candidates, selection.criterion, color="C0")
    left.axvline(chosen, color="C3", linestyle="--", label=f"chosen {chosen:.3g}")
    if selection.target is not None:
        left.axhline(selection.target, color="0.5", linestyle=":", label=f"target {selection.target:g}")
    left.set_xscale("log")
    if selection.method in ("gcv", "noise_figure", "discrepancy"):
        left.set_yscale("log")
    left.set_xlabel("hyperparameter (unit-free)")
    left.set_ylabel(names.get(selection.method, selection.method))
    left.legend()
    right.loglog(selection.residual_norm, selection.solution_norm, color="C0")
    index = int(np.argmin(np.abs(np.log(candidates / chosen))))
    right.loglog(selection.residual_norm[index], selection.solution_norm[index], "o", color="C3")
    right.set_xlabel("residual norm ||J x - y||")
    right.set_ylabel("solution norm (prior)")
    right.set_title("L-curve")
    note = f": {messages(selection.result)[0]}" if failed(selection.result) else ""
    figure.suptitle(f"hyperparameter by {selection.method}{note}")
    if path is not None:
        figure.savefig(path, dpi=120)
    return figure
