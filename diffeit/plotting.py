"""Figures of element-wise images on meshes and of hyperparameter curves (matplotlib, no
display needed). A flat mesh is drawn in 2D axes, a surface mesh ((N, 3) nodes: a skin on a
curved surface) in 3D axes (projection="3d")."""

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

    Electrodes are drawn as thick dark lines, electrode 0 numbered. A flat mesh is drawn with
    `tripcolor` into 2D axes. A surface mesh ((N, 3) nodes) needs 3D axes (projection="3d", see
    `mesh_projection`): its triangles are drawn as a `Poly3DCollection` on the same colour
    scale with faint edges, the axes' box given the data's proportions, seen (without
    perspective) from the side its triangles' normals point to: from outside for
    `cylinder_patch` and `sphere_cap`. Its electrodes are drawn over the surface, those behind
    it in that view thin and faint; changing the view later does not redraw them.

    Arguments:
        ax: The matplotlib axes: 3D axes for a surface mesh.
        mesh: The mesh.
        values: (E,) one value per element, in any unit.
        cmap: The matplotlib colour map.
        symmetric: Centre the colour scale on 0 (from -max |values| to max |values|).
        label: The colour bar's label.
        electrodes: Draw the electrodes.

    Returns:
        The `PolyCollection` of the elements (a `Poly3DCollection` for a surface mesh).

    Raises:
        ValueError: For a surface mesh and axes that are not 3D.
    """
    if mesh.nodes.shape[1] == 3:
        return _plot_surface_elements(
            ax, mesh, values, cmap=cmap, symmetric=symmetric, label=label, electrodes=electrodes
        )
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


def mesh_projection(mesh: Mesh) -> str | None:
    """The matplotlib projection of the axes that `plot_elements` draws a mesh into.

    Pass it as `projection` to `add_subplot` or in `subplot_kw` to `subplots`.

    Arguments:
        mesh: The mesh.

    Returns:
        "3d" for a surface mesh ((N, 3) nodes), None (plain 2D axes) for a flat one.
    """
    return "3d" if mesh.nodes.shape[1] == 3 else None


def _subplot_kw(mesh: Mesh) -> dict:
    """`subplot_kw` for axes to draw the mesh into: empty for a flat mesh, as before surfaces."""
    projection = mesh_projection(mesh)
    return {} if projection is None else {"projection": projection}


def _plot_surface_elements(
    ax: Axes, mesh: Mesh, values: np.ndarray, *, cmap: str, symmetric: bool, label: str | None, electrodes: bool
) -> PolyCollection:
    """`plot_elements` for a surface mesh, into 3D axes."""
    from mpl_toolkits.mplot3d import Axes3D
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if not isinstance(ax, Axes3D):
        raise ValueError(
            'a surface mesh ((N, 3) nodes) is drawn in 3D: pass axes made with projection="3d" '
            '(e.g. figure.add_subplot(projection="3d"), or subplot_kw={"projection": "3d"})'
        )
    values = np.asarray(values, dtype=float)
    nodes = np.asarray(mesh.nodes, dtype=float)
    # Faint edges show the surface's shape where the colours are near white.
    artist = Poly3DCollection(nodes[mesh.triangles], cmap=cmap, edgecolors=(0, 0, 0, 0.12), linewidths=0.3)
    artist.set_array(values)
    if symmetric:
        limit = np.max(np.abs(values))
        artist.set_clim(-limit, limit)
    else:
        artist.set_clim(np.min(values), np.max(values))
    ax.add_collection3d(artist, autolim=False)
    low, high = nodes.min(axis=0), nodes.max(axis=0)
    ranges = high - low
    size = float(np.max(ranges))
    ranges = np.maximum(ranges, 0.02 * size)  # a flat patch in 3D keeps some box height
    centre = (low + high) / 2
    ax.set_xlim(centre[0] - ranges[0] / 2, centre[0] + ranges[0] / 2)
    ax.set_ylim(centre[1] - ranges[1] / 2, centre[1] + ranges[1] / 2)
    ax.set_zlim(centre[2] - ranges[2] / 2, centre[2] + ranges[2] / 2)
    ax.set_box_aspect(tuple(ranges), zoom=1.1)
    elevation, azimuth = _outside_view(mesh)
    ax.view_init(elevation, azimuth)
    ax.set_proj_type("ortho")  # no perspective distortion, and `_hidden` is exact
    if electrodes:
        # mplot3d sorts whole artists by depth, which would hide a line on the surface behind
        # it or draw one behind the surface over it: the surface is drawn first, then the
        # electrodes in front of it (in this view) thick and dark, those behind it thin and faint.
        ax.computed_zorder = False
        artist.set_zorder(1)
        corners = nodes[mesh.triangles]
        towards_viewer = _view_direction(elevation, azimuth)
        for index, chain in enumerate(mesh.electrodes):
            xyz = nodes[chain]
            behind = np.mean(_hidden(xyz, corners, towards_viewer, 1e-3 * size)) > 0.5
            style = {"color": "0.5", "linewidth": 1.0, "alpha": 0.5} if behind else {"color": "0.1", "linewidth": 4}
            ax.plot(*xyz.T, solid_capstyle="butt", zorder=2 if behind else 3, label=f"electrode {index}", **style)
            if index == 0:
                middle = xyz[len(xyz) // 2]
                touching = np.isin(mesh.triangles, chain).any(axis=1)
                outward = middle - corners[touching].mean(axis=(0, 1))
                outward /= np.linalg.norm(outward) or 1.0
                ax.text(*(middle + 0.07 * size * outward), "0", ha="center", va="center", fontsize=8, zorder=4)
    ax.set_axis_off()
    ax.figure.colorbar(artist, ax=ax, shrink=0.8, label=label)
    return artist


def _outside_view(mesh: Mesh) -> tuple[float, float]:
    """(elevation, azimuth), degrees, of a view of a surface mesh from the side its triangles'
    normals point to on average: from 50 degrees above (below) the horizontal when that side is up
    (down), as for a dome, else from 25 degrees above it (a cylinder patch), to show the
    curvature without hiding much of the rim."""
    a, b, c = (mesh.nodes[mesh.triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a).sum(axis=0)  # area-weighted
    length = np.linalg.norm(normal)
    if length == 0:
        return 30.0, -60.0  # matplotlib's default view
    normal /= length
    elevation = np.degrees(np.arcsin(np.clip(normal[2], -1, 1)))
    if abs(elevation) > 60:
        return float(np.sign(elevation) * 50), -60.0
    azimuth = np.degrees(np.arctan2(normal[1], normal[0]))
    return float(elevation + 25), float(azimuth)


def _view_direction(elevation: float, azimuth: float) -> np.ndarray:
    """(3,) the unit vector from the scene towards the viewer of a 3D axes' view, degrees."""
    elevation, azimuth = np.radians(elevation), np.radians(azimuth)
    return np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])


def _hidden(points: np.ndarray, corners: np.ndarray, towards_viewer: np.ndarray, tolerance: float) -> np.ndarray:
    """(P,) whether each of `points` (P, 3) is behind a triangle of `corners` (E, 3, 3) seen from
    far along `towards_viewer`: whether the ray from it towards the viewer meets one further
    than `tolerance` (metres) from it (Moeller-Trumbore, all pairs at once)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    ab, ac = b - a, c - a
    cross = np.cross(towards_viewer, ac)  # (E, 3)
    determinant = np.einsum("ij,ij->i", ab, cross)
    usable = np.abs(determinant) > 1e-12 * np.einsum("ij,ij->i", ab, ab)  # not seen edge-on
    inverse = np.where(usable, 1 / np.where(usable, determinant, 1), 0)
    offset = points[:, None, :] - a[None]  # (P, E, 3)
    u = np.einsum("pij,ij->pi", offset, cross) * inverse
    q = np.cross(offset, ab[None])
    v = (q @ towards_viewer) * inverse
    t = np.einsum("pij,ij->pi", q, ac) * inverse
    hits = usable & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > tolerance)
    return hits.any(axis=1)


def plot_image_strip(
    path: str | Path,
    mesh: Mesh,
    images: np.ndarray,
    *,
    times: np.ndarray | None = None,
    max_panels: int = 12,
    title: str | None = None,
    label: str = "dsigma (S/sq)",
    points: np.ndarray | None = None,
) -> np.ndarray:
    """Save a strip of element-wise images on a mesh as a PNG.

    Every k-th frame, at most `max_panels` panels, six to a row, one colour scale centred on 0
    for all. Panel titles give the frame index and, with `times`, its time. A surface mesh is
    drawn in 3D panels (see `plot_elements`). With `points`, each panel marks its frame's
    points with a +.

    Arguments:
        path: The PNG file to write.
        mesh: The mesh.
        images: (T, E) the images, in any unit.
        times: (T,) the frames' times, seconds; None leaves them out.
        max_panels: The most panels, at least 1.
        title: The figure's title; None for none.
        label: The colour bar's label.
        points: (T, K, d) points to mark on each frame (`Touches.position`: metres, d the mesh's
            dimension), NaN where a frame has fewer; None marks none.

    Returns:
        The indices of the frames shown.

    Raises:
        ValueError: For images not of shape (T, E), no frame, `max_panels` below 1, or points
            not of shape (T, K, d).
    """
    images = np.asarray(images, dtype=float)
    if images.ndim != 2 or images.shape[1] != mesh.n_elements:
        raise ValueError(f"images have shape {images.shape}; expected (T, {mesh.n_elements})")
    dimension = mesh.nodes.shape[1]
    if points is not None and (np.ndim(points) != 3 or np.shape(points)[::2] != (len(images), dimension)):
        raise ValueError(f"points have shape {np.shape(points)}; expected ({len(images)}, K, {dimension})")
    if max_panels < 1 or len(images) == 0:
        raise ValueError("an image strip needs at least one panel and one frame")
    shown = np.arange(0, len(images), math.ceil(len(images) / max_panels))
    limit = float(np.max(np.abs(images[shown]))) or 1.0
    columns = min(len(shown), 6)
    rows = math.ceil(len(shown) / columns)
    figure = Figure(figsize=(1.7 * columns + 0.9, 1.8 * rows + (0.4 if title else 0)), layout="constrained")
    axes = np.atleast_1d(figure.subplots(rows, columns, squeeze=False, subplot_kw=_subplot_kw(mesh))).ravel()
    for ax, frame in zip(axes, shown, strict=False):
        artist = plot_elements(ax, mesh, images[frame], label=None)
        artist.set_clim(-limit, limit)
        artist.colorbar.remove()  # one shared colour bar for the strip instead of one per panel
        when = f", {times[frame]:.2f} s" if times is not None else ""
        ax.set_title(f"frame {frame}{when}", fontsize=7)
        if points is not None:
            marked = np.asarray(points[frame], dtype=float)
            marked = marked[np.all(np.isfinite(marked), axis=1)]
            ax.plot(*marked.T, "+", color="k", markersize=8, markeredgewidth=1.2)
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
