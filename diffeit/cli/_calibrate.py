"""`diffeit calibrate SESSION.h5 [--presses PRESSES.csv] -o SKIN.cal.h5`: calibrate a skin and
board from a calibration session, and write the calibration file and its figure."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._errors import reporting_user_errors

if TYPE_CHECKING:
    import matplotlib.figure

    from ..calibration import SkinCalibration
    from ..io import Presses


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `calibrate` to the subcommands `commands` of the `diffeit` parser."""
    calibrate = commands.add_parser(
        "calibrate",
        help="calibrate a skin and board from a session file (and labelled presses): write SKIN.cal.h5",
        description="diffeit.calibrate on a session's recording: the first stage (level, orientation, broken "
        "readings) on its untouched frames, then the contact impedance of every electrode, the readout's mixing "
        "and its drive and channel gains, with standard errors; with --presses, the presses are imaged and read "
        "and a position map from read to labelled positions is fitted. Prints the calibration's report, writes "
        "the calibration file OUT (pass it to `diffeit reconstruct --calibration`) and a figure beside it "
        "(OUT with .png for .h5): the mesh and its electrodes (and their fitted centres), the mixing weights and "
        "the gains with their standard errors, and, with presses, each labelled position with an arrow to where it "
        "was read (through the position map). Exit status 2 for bad input or options.",
    )
    calibrate.add_argument("session", help="the session: a diffeit frames file (.h5), untouched frames first")
    calibrate.add_argument(
        "--presses",
        help="labelled presses, CSV: a header x_m,y_m,radius_m,time_s (or start_s,end_s for holds), one press a "
        "row, times on the session's clock (diffeit.io.read_presses)",
    )
    calibrate.add_argument("-o", "--output", required=True, help="the calibration file to write (SKIN.cal.h5)")
    calibrate.add_argument(
        "--reference-frame", type=int, help="calibrate on this frame instead of the file's reference"
    )
    calibrate.add_argument("--h", type=float, help="element size (m) of the mesh built from the file's geometry")
    calibrate.add_argument(
        "--background-map",
        choices=("auto", "yes", "no"),
        default="auto",
        help="a smooth map of the sheet's conductivity fitted to the reference: auto (the default) fits it with "
        "20 or more presses and keeps it when they are read significantly closer through it; yes fits and keeps "
        "it; no does not fit it",
    )
    calibrate.add_argument("--overwrite", action="store_true", help="replace existing output files")
    calibrate.set_defaults(run=reporting_user_errors("calibrate", _calibrate_file))


def _calibrate_file(arguments: argparse.Namespace) -> int:
    from .. import io
    from ..calibration import calibrate

    output = Path(arguments.output)
    figure = output.with_suffix(".png") if output.suffix.lower() == ".h5" else output.with_name(output.name + ".png")
    for path in (output, figure):
        if path.exists() and not arguments.overwrite:
            raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
    recording = io.read_frames(arguments.session)
    presses = None if arguments.presses is None else io.read_presses(arguments.presses)
    background_map = {"auto": None, "yes": True, "no": False}[arguments.background_map]
    calibration = calibrate(
        recording, presses, h=arguments.h, reference_frame=arguments.reference_frame, background_map=background_map
    )
    calibration.save(output, overwrite=arguments.overwrite)
    plot_calibration(figure, calibration, presses)
    print("\n".join([*calibration.lines(), f"wrote {output} and {figure}"]))
    return 0


def _fitted(calibration: SkinCalibration, group: str) -> bool:
    """Whether the calibration fitted `group` at some stage (the reference's or the presses')."""
    return any(group in groups for groups in calibration.fitted.values())


def plot_calibration(
    path: str | Path,
    calibration: SkinCalibration,
    presses: Presses | None = None,
) -> Path:
    """The figure of a calibration: its mesh with the electrodes (coloured by the background map
    when it has one; the fitted electrode centres marked on it when the positions were fitted),
    the readout's mixing weights and the drive and channel gains (with one-standard-error bars;
    a group not fitted is titled so), and, with `presses`, every labelled position with an
    arrow to its read position (through the position map). A curved skin is drawn seen along z
    (its x and y).

    Arguments:
        path: The PNG to write.
        calibration: The calibration.
        presses: The session's labelled presses, or None.

    Returns:
        The path written.
    """
    _calibration_figure(calibration, presses).savefig(path, dpi=110)
    return Path(path)


def _calibration_figure(calibration: SkinCalibration, presses: Presses | None) -> matplotlib.figure.Figure:
    """`plot_calibration`'s figure."""
    import matplotlib.ticker
    from matplotlib.figure import Figure

    values, errors = calibration.values, calibration.standard_errors
    mesh = calibration.model.mesh
    panels = 4 if presses is not None else 3
    figure = Figure(figsize=(4.2 * panels, 4.2), layout="constrained")
    axes = figure.subplots(1, panels)
    if calibration.background_map is None:
        axes[0].triplot(mesh.nodes[:, 0], mesh.nodes[:, 1], mesh.triangles, color="0.75", linewidth=0.3)
    else:
        relative = calibration.background_map / calibration.conductivity
        sheet = axes[0].tripcolor(mesh.nodes[:, 0], mesh.nodes[:, 1], mesh.triangles, facecolors=relative)
        bar = figure.colorbar(sheet, ax=axes[0], location="bottom", shrink=0.8, label="background map / level")
        bar.locator = matplotlib.ticker.MaxNLocator(4)
    for index, chain in enumerate(mesh.electrodes):
        xy = mesh.nodes[chain, :2]
        axes[0].plot(xy[:, 0], xy[:, 1], color="0.1", linewidth=4, solid_capstyle="butt")
        axes[0].annotate(str(index), 1.1 * xy[len(xy) // 2], ha="center", va="center", fontsize=7)
    title = f"mesh: {mesh.n_elements} triangles, {len(mesh.electrodes)} electrodes"
    if "electrode_positions" in values:  # the fitted centres against the mesh's electrodes
        points = calibration.electrode_points
        axes[0].plot(points[:, 0], points[:, 1], "o", color="C3", markersize=4, label="fitted centres")
        axes[0].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 0.0))  # below: clear of the numbers
        title += f"\nfitted centres moved by up to {1e3 * np.max(np.abs(values['electrode_positions'])):.2g} mm"
    axes[0].set_aspect("equal")
    axes[0].set_axis_off()
    axes[0].set_title(title, fontsize=9)

    mixing = np.asarray(values["mixing"])
    axes[1].bar(np.arange(len(mixing)), mixing, yerr=np.asarray(errors["mixing"]), capsize=2, color="C0")
    # Weights 0 and 1 are the drive's source's and sink's, then offset j's (`diffeit.readout.roles`).
    axes[1].set_xticks(np.arange(len(mixing)), ["source", "sink", *map(str, range(len(mixing) - 2))], fontsize=7)
    for label in axes[1].get_xticklabels()[:2]:
        label.set_rotation(90)
    axes[1].set_xlabel("source, sink, then offset j: j electrodes on from the pair's +", fontsize=8)
    axes[1].set_title("readout mixing weights" + ("" if _fitted(calibration, "mixing") else " (not fitted)"))
    axes[1].axhline(0.0, color="0.5", linewidth=0.5)

    for name, offset, colour in (("drive_gains", -0.2, "C1"), ("channel_gains", 0.2, "C2")):
        log_gains = np.asarray(values[name])
        gains = np.exp(log_gains)
        spread = gains * np.asarray(errors[name])  # d exp(x) = exp(x) dx
        axes[2].bar(
            np.arange(len(gains)) + offset,
            gains,
            width=0.4,
            yerr=spread,
            capsize=1,
            color=colour,
            label=name.replace("_", " "),
        )
    axes[2].axhline(1.0, color="0.5", linewidth=0.5)
    axes[2].set_xlabel("electrode")
    gains_fitted = any(_fitted(calibration, name) for name in ("drive_gains", "channel_gains"))
    axes[2].set_title("drive and channel gains" + ("" if gains_fitted else " (not fitted: 1)"))
    axes[2].legend(fontsize=8)

    if presses is not None:
        labelled = presses.centres[:, :2]
        ax = axes[3]
        ax.plot(*labelled.T, "o", color="C0", markersize=4, label="labelled")
        found = calibration.press_positions[:, :2]
        for start, end in zip(labelled, found, strict=True):
            if np.all(np.isfinite(end)):
                ax.annotate("", end, start, arrowprops={"arrowstyle": "->", "color": "C3", "linewidth": 0.8})
        ax.plot([], [], color="C3", label="to the read position")
        median = (
            ""
            if calibration.press_errors is None
            else (f": median error {1e3 * np.nanmedian(calibration.press_errors):.1f} mm (left out)")
        )
        ax.set_title(f"{presses.n_presses} presses{median}", fontsize=9)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        ax.legend(fontsize=8)
    figure.suptitle(f"calibration: misfit {calibration.misfit:.3g}, correlation {calibration.correlation:.4f}")
    return figure
