"""Figures of element-wise images on meshes (matplotlib, no display needed)."""

from __future__ import annotations

import matplotlib.tri
import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection

from .mesh import Mesh


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
    """Draw element values on `mesh` into `ax`, electrodes as thick dark lines with electrode
    0 numbered; a colour bar labelled `label`. `symmetric` centres the colour scale on 0."""
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
