"""Mesh generators for skins on curved surfaces: a patch of a cylinder (a forearm) and a cap
of a sphere (a fingertip), meshed flat in their parameter domain and mapped onto the surface."""

from __future__ import annotations

import numpy as np

from ._generate import disc, rectangle
from ._mesh import Mesh


def cylinder_patch(
    radius: float,
    length: float,
    angle: float,
    n_electrodes: int,
    h: float,
    electrode_width: float | None = None,
) -> Mesh:
    """A skin on part of a cylinder's surface, with electrodes spaced evenly round its rim.

    The cylinder's axis is the z axis. The patch spans azimuths [-angle/2, angle/2] (radians,
    counter-clockwise from the x axis seen from +z) and z in [-length/2, length/2]. It is
    `rectangle(radius * angle, length, ...)` rolled onto the cylinder: the flat point (s, t)
    goes to (radius cos(s / radius), radius sin(s / radius), t). Rolling preserves lengths, so
    the patch carries the physics of the flat rectangle it unrolls to, and electrode positions
    and widths are arc lengths along the rim as in `rectangle`: electrode k is centred
    (k + 1/2) P / n_electrodes along the rim (of length P = 2 (radius * angle + length)) from
    the corner at azimuth -angle/2, z = -length/2, running first along the lower edge with
    increasing azimuth. The mesh's straight edges are chords of the curved rim, so an
    electrode on the lower or upper edge is shorter than its arc by a relative
    (a / radius)^2 / 24, a the length of its edges (about h / 2).

    Arguments:
        radius: The cylinder's radius, m.
        length: The patch's extent along the axis, m.
        angle: The patch's extent round the axis, radians, in (0, 2 pi): a whole turn would
            join the patch to itself.
        n_electrodes: The number of electrodes, at least 2.
        h: The target element edge length away from the electrodes, m (h / 2 at them).
        electrode_width: The arc length of each electrode along the rim, m; default half the
            spacing, P / (2 n_electrodes).

    Returns:
        The `Mesh`, nodes (N, 3) on the cylinder, its triangles' normals pointing away from
        the axis and its electrodes numbered along the rim as above (the direction of
        `boundary_edges`).

    Raises:
        ValueError: For a non-positive radius or length, an angle outside (0, 2 pi), and as
            `rectangle` for the electrodes and `h`.
    """
    if not (radius > 0 and length > 0):
        raise ValueError(f"radius and length must be positive (metres); got radius={radius}, length={length}")
    if not 0 < angle < 2 * np.pi:
        raise ValueError(f"angle must lie in (0, 2 pi) radians; got {angle}")
    flat = rectangle(radius * angle, length, n_electrodes, electrode_width, h)
    azimuth = flat.nodes[:, 0] / radius
    nodes = np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth), flat.nodes[:, 1]], axis=1)
    return Mesh(nodes, flat.triangles, flat.electrodes)


def sphere_cap(
    radius: float,
    polar_angle: float,
    n_electrodes: int,
    h: float,
    electrode_width: float | None = None,
) -> Mesh:
    """A skin on the cap of a sphere, with electrodes spaced evenly round its rim.

    The sphere is centred at the origin and the cap is the part within `polar_angle` of its
    pole (0, 0, radius): the rim is the circle at that polar angle, of length
    C = 2 pi radius sin(polar_angle). Electrode k is centred at azimuth 2 pi k / n_electrodes
    (radians, counter-clockwise from the x axis seen from +z); its width is its arc length
    along the rim. The mesh is a `disc` of radius radius * polar_angle mapped onto the sphere
    by the azimuthal equidistant map (a point at distance r from the disc's centre goes to
    the point at geodesic distance r from the pole, at the same azimuth). That map keeps
    distances from the pole but shortens the circles round it by sin(theta) / theta at polar
    angle theta: elements near the rim are narrower along it than `h` by that factor
    (0.64 for a hemisphere), and the rim of the flat disc is meshed with the electrode
    widths scaled up by its inverse so that they come out right on the sphere. As in `disc`,
    the boundary is the inscribed polygon through the rim nodes, so an electrode of the mesh
    is slightly shorter than its arc.

    Arguments:
        radius: The sphere's radius, m.
        polar_angle: The cap's angular radius seen from the sphere's centre, radians, in
            (0, pi): pi would close the sphere.
        n_electrodes: The number of electrodes, at least 2.
        h: The target element edge length away from the electrodes, m, measured in the flat
            disc (radially it is the length on the sphere); h / 2 at the electrodes.
        electrode_width: The arc length of each electrode along the rim, m; default half the
            spacing, C / (2 n_electrodes).

    Returns:
        The `Mesh`, nodes (N, 3) on the sphere, its triangles' normals pointing away from the
        centre and its electrodes numbered counter-clockwise seen from +z.

    Raises:
        ValueError: For a non-positive radius, a polar angle outside (0, pi), fewer than 2
            electrodes, electrodes that do not fit on the rim with gaps between them, and as
            `disc` for `h`.
    """
    if not radius > 0:
        raise ValueError(f"radius must be positive (metres); got {radius}")
    if not 0 < polar_angle < np.pi:
        raise ValueError(f"polar_angle must lie in (0, pi) radians; got {polar_angle}")
    if n_electrodes < 2:
        raise ValueError(f"a sphere cap needs at least 2 electrodes; got {n_electrodes}")
    rim_length = 2 * np.pi * radius * np.sin(polar_angle)
    if electrode_width is None:
        electrode_width = rim_length / (2 * n_electrodes)
    if not 0 < electrode_width * n_electrodes < rim_length:
        raise ValueError(
            f"{n_electrodes} electrodes of width {electrode_width} do not fit on a rim of length "
            f"{rim_length:.4g} with gaps between them"
        )
    rim_shrinkage = np.sin(polar_angle) / polar_angle  # rim length on the sphere over that in the disc
    flat = disc(n_electrodes, electrode_width / rim_shrinkage, h, radius=radius * polar_angle)
    theta = np.linalg.norm(flat.nodes, axis=1) / radius
    azimuth = np.arctan2(flat.nodes[:, 1], flat.nodes[:, 0])
    nodes = radius * np.stack([np.sin(theta) * np.cos(azimuth), np.sin(theta) * np.sin(azimuth), np.cos(theta)], axis=1)
    return Mesh(nodes, flat.triangles, flat.electrodes)
