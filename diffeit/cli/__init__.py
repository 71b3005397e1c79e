"""The `diffeit` command line."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from ._errors import reporting_user_errors
from ._model import ModelSettings, _hyperparameter

if TYPE_CHECKING:
    from ..io import Recording
    from ..mesh import Mesh
    from ..touch import Touches


def _demo(arguments: argparse.Namespace) -> int:
    from ..demo import run_curved_demo, run_demo

    if arguments.skin == "disc":
        result = run_demo(arguments.output, seed=arguments.seed)
    else:
        result = run_curved_demo(arguments.skin, arguments.output, seed=arguments.seed)
    where = "unit disc" if arguments.skin == "disc" else f"{arguments.skin}, 3D distance"
    print(
        f"data mesh {result.n_data_elements} triangles, reconstruction mesh "
        f"{result.n_reconstruction_elements} triangles\n"
        f"position error: {result.position_error:.4f} m ({where})\n"
        f"correlation with the truth: {result.correlation:.3f}\n"
        f"peak dsigma: {result.peak:.3e} S/sq\n"
        f"wrote {result.figure}"
    )
    return 0


def _reconstruct_file(arguments: argparse.Namespace) -> int:
    """`diffeit reconstruct FILE -o OUT`: `diffeit.reconstruct` on the file's recording, with its
    defaults for every option not given. Every frame's result code goes into OUT.h5; the exit
    status is 1 when a frame or the background map's fit failed (the files written all the
    same), else 0."""
    from .. import io
    from .._messages import name_indices
    from ..calibration import CalibrationWarning
    from ..calibration import load as load_calibration
    from ..plotting import plot_image_strip
    from ..reconstruction import SELECTION_METHODS, reconstruct

    start = time.perf_counter()
    source = Path(arguments.frames)
    suffixes = (".png", ".h5", ".touches.csv") if arguments.touches else (".png", ".h5")
    outputs = _output_paths(arguments.output, suffixes, arguments.overwrite)
    hyperparameter = _hyperparameter(arguments.hyperparameter, SELECTION_METHODS)
    if source.suffix.lower() == ".mat":
        if arguments.variable is None:
            raise ValueError(f"{source} is a .mat file: name the frames with --variable (and --reference-variable)")
        recording = io.read_eidors_mat(
            source, arguments.variable, reference=arguments.reference_variable, frame_rate=arguments.frame_rate
        )
    else:
        if arguments.variable is not None or arguments.reference_variable is not None:
            raise ValueError("--variable and --reference-variable apply to EIDORS .mat files only")
        recording = io.read_frames(source)
    if recording.n_frames == 0:
        raise ValueError(f"{source} holds no frames")

    skin = None if arguments.calibration is None else load_calibration(arguments.calibration, recording=recording)
    # A simulated file's scene names its background and contact impedance; the options win.
    given = {"background": arguments.background, "contact_impedance": arguments.contact_impedance}
    model = {**_scene_settings(recording), **{name: value for name, value in given.items() if value is not None}}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CalibrationWarning)
        reconstructed = reconstruct(
            recording,
            method=arguments.method,
            prior=arguments.prior,
            hyperparameter=hyperparameter,
            calibrate=arguments.calibrate,
            h=arguments.h,
            reference_frame=arguments.reference_frame,
            difference=arguments.difference,
            driven_readings=arguments.driven_readings,
            background_map=arguments.background_map,
            max_iterations=arguments.max_iterations,
            progress=True,
            throw=False,
            calibration=skin,
            **model,
        )
    notes = []
    for warning in caught:
        if issubclass(warning.category, CalibrationWarning):
            notes.append(str(warning.message))
            print(f"warning: {warning.message}")
        else:  # not ours to report: pass it on as it came
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)

    metadata = reconstructed.provenance["metadata"]
    extra = {"input": str(source), "reference_frame": arguments.reference_frame, "warnings": notes}
    if source.suffix.lower() == ".mat":
        extra |= {"variable": arguments.variable, "reference_variable": arguments.reference_variable}
    reconstructed = dataclasses.replace(
        reconstructed, provenance={**reconstructed.provenance, "metadata": {**metadata, **extra}}
    )
    mesh, images, quantity = reconstructed.mesh, reconstructed.images, reconstructed.image_quantity
    relative = quantity == "relative conductivity change"
    value, choice = metadata["hyperparameter"], metadata["hyperparameter_choice"]
    # Without a method in the choice, the calibration's hyperparameter (its presses were imaged at it) was used.
    chosen = "given" if isinstance(hyperparameter, float) else choice.get("method", "the calibration's")
    chosen = f"auto: {chosen}" if hyperparameter == "auto" else chosen
    prior = "" if arguments.method in ("total_variation", "greit") else f" {arguments.prior}"  # they have none
    described = arguments.method.replace("_", " ") + prior
    found = None
    if arguments.touches:
        from ..touch import touches

        found = touches(reconstructed, skin)
    shown = plot_image_strip(
        outputs[0],
        mesh,
        images,
        times=reconstructed.times,
        max_panels=arguments.panels,
        title=f"{source.name}: {described}, hyperparameter {value:.3g}; {quantity}"
        + ("; + the touches read" if found is not None else ""),
        label="dsigma / sigma" if relative else "dsigma (S/sq)",
        points=None if found is None else (found.position if skin is None else skin.in_mesh_frame(found.position)),
    )
    io.write_frames(outputs[1], reconstructed, overwrite=arguments.overwrite)
    if found is not None:
        _report_touches(reconstructed, found, outputs[2])
    calibration = metadata["calibration"]
    peak = images.flat[np.argmax(np.abs(images))]
    print(
        f"{reconstructed.n_frames} frames, {mesh.n_elements} triangles; "
        f"hyperparameter {value:.3g} ({chosen})\n"
        f"calibration: misfit {calibration['misfit']:.3g}, correlation {calibration['correlation']:.3f}, "
        f"orientation {calibration['orientation']}; {metadata['difference']} differences\n"
        f"{quantity}: peak {peak:.3e}{'' if relative else ' S/sq'}\n"
        f"reconstructed in {time.perf_counter() - start:.1f} s; "
        f"wrote {outputs[0]} ({len(shown)} panels) and {outputs[1]} (images {images.shape})"
        + (f" and {outputs[2]}" if arguments.touches else "")
    )
    # Failed solves: on stderr, after the files they concern are written.
    results = np.array(metadata["results"])
    if metadata["frames_failed"]:
        codes = dict.fromkeys(results[results != "successful"])  # in the order of their first frame
        which = "; ".join(f"{name_indices(np.flatnonzero(results == c))} {c} ({_message(c)})" for c in codes)
        print(
            f"diffeit reconstruct: {metadata['frames_failed']} of {len(results)} frames failed: {which}. Their images "
            f"are written all the same, their codes in {outputs[1].name}",
            file=sys.stderr,
        )
    # A selection at an end of its candidates is used all the same: said, not failed.
    selection = choice.get(choice.get("method"), {})
    if selection.get("result", "successful") != "successful":
        print(
            f"diffeit reconstruct: note: the hyperparameter {value:.3g} that {choice['method']} chose is at an end "
            "of its candidates",
            file=sys.stderr,
        )
    map_result = (metadata["background_map"] or {}).get("result", "successful")
    map_failed = map_result not in ("successful", "selection_at_boundary")
    if map_failed:
        print(
            f"diffeit reconstruct: the background map's fit failed: {map_result} ({_message(map_result)}); the "
            "frames are imaged at it all the same",
            file=sys.stderr,
        )
    elif map_result != "successful":
        print(
            "diffeit reconstruct: note: the background map's misfit levelled off above the noise "
            "(selection_at_boundary): the model's own error dominates it",
            file=sys.stderr,
        )
    return 1 if metadata["frames_failed"] or map_failed else 0


def _report_touches(reconstructed: Recording, found: Touches, path: Path) -> None:
    """Print every frame's touches (`found`: `diffeit.touches` of the images, through the
    calibration's position map when it has one) and write them to the CSV file `path`: a header,
    then one row per touch (frame, time_s, count, touch, x_m, y_m (and z_m on a curved skin),
    radius_m, depth); a frame without touches has no row."""
    axes = "xyz"[: found.position.shape[-1]]  # a curved skin's touches are points in 3D
    rows = ["frame,time_s,count,touch," + ",".join(f"{axis}_m" for axis in axes) + ",radius_m,depth"]
    for frame in range(reconstructed.n_frames):
        lines = found.lines(frame)
        print(f"frame {frame} (t = {reconstructed.times[frame]:.3f} s): " + ("; ".join(lines) or "no touch"))
        for k in range(int(found.count[frame])):
            measured = (*found.position[frame, k], found.radius[frame, k], found.depth[frame, k])
            rows.append(
                f"{frame},{float(reconstructed.times[frame])!r},{int(found.count[frame])},{k},"
                + ",".join(repr(float(value)) for value in measured)
            )
    path.write_text("\n".join(rows) + "\n")


def _message(code: str) -> str:
    """The message of the `diffeit.results.RESULTS` code named `code`."""
    from ..results import RESULTS, messages

    return messages(getattr(RESULTS, code))[0]


def _experiment(arguments: argparse.Namespace) -> int:
    """`diffeit experiment NAME [--small] [-o DIR]` and `diffeit experiment --list`."""
    import experiments

    if arguments.list or arguments.name is None:
        for study in experiments.STUDIES.values():
            print(f"{study.name:16s} Fig. {study.figure}: {study.title}")
        return 0 if arguments.list else 2
    output = Path(arguments.output or Path("experiments-output") / arguments.name)
    start = time.perf_counter()
    findings = experiments.run(arguments.name, output, small=arguments.small)
    for statement in findings.statements:
        print(statement)
    print(f"{arguments.name}{' (small)' if arguments.small else ''} in {time.perf_counter() - start:.0f} s; wrote:")
    for path in findings.files:
        print(f"  {path}")
    return 0


def _output_paths(output: str, suffixes: tuple[str, ...], overwrite: bool) -> list[Path]:
    """The files of -o OUT: OUT with each of `suffixes` (a .png or .h5 ending of OUT is dropped
    first). Raises FileExistsError for one that exists, unless `overwrite`."""
    base = Path(output)
    base = base.with_suffix("") if base.suffix in (".png", ".h5") else base
    paths = [base.with_name(base.name + suffix) for suffix in suffixes]
    for path in paths:
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
    return paths


def _with_images(
    recording: Recording,
    source: Path,
    command: str,
    *,
    reference: np.ndarray | None,
    mesh: Mesh,
    images: np.ndarray,
    image_quantity: str,
    metadata: dict[str, Any],
) -> Recording:
    """`recording` (read from `source`) with the `images` on `mesh` that `command` made, and
    provenance naming the input and the command's choices (`metadata`); frames, times, protocol,
    geometry and voltage unit kept."""
    provenance = {
        "source": f"{command} {source.name}",
        "metadata": {"input": str(source), "input_source": recording.provenance.get("source", ""), **metadata},
    }
    return dataclasses.replace(
        recording,
        reference=reference,
        mesh=mesh,
        provenance=provenance,
        images=images,
        image_quantity=image_quantity,
    )


def _scene_settings(recording: Recording) -> dict[str, float]:
    """The model of a simulated file: its scene's uniform background (S/sq) and its skin's mean
    contact impedance (ohm m), those the scene names."""
    scene = recording.provenance.get("metadata", {}).get("scene", {})
    settings = {}
    if "conductivity" in scene.get("background", {}):
        settings["background"] = float(scene["background"]["conductivity"])
    if "contact_impedance" in scene.get("skin", {}):
        settings["contact_impedance"] = float(np.mean(scene["skin"]["contact_impedance"]))
    return settings


def _mesh_of(recording: Recording, settings: ModelSettings) -> Mesh:
    """The file's geometry (for a simulation: the reconstruction mesh, coarser than the mesh the
    data were simulated on), else its mesh; without either, a unit disc with the protocol's
    electrodes."""
    from .. import io

    if recording.geometry is not None:
        return io.mesh_from_geometry(recording.geometry)
    if recording.mesh is not None:
        return recording.mesh
    return settings.unit_disc(recording.protocol.n_electrodes)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `diffeit` command line: parse the arguments and run the command they name.

    The commands (demo, reconstruct, experiment, simulate, fit, calibrate and the hardware
    ones) are described by `diffeit COMMAND --help`. Turns on JAX's float64 for the process.

    Arguments:
        argv: The arguments after the program's name, e.g. `["demo", "-o", "demo.png"]`;
            None for the process's (`sys.argv[1:]`).

    Returns:
        The exit status: 0 on success; 1 when a command ran but its computation failed or fell
        short (each command's help says when); 2 for bad input or options, reported in one
        line on stderr; 128 + N for a fit stopped by signal N.

    Raises:
        SystemExit: From argument parsing: status 2 for an unknown command or option, 0 after
            `--help`.
    """
    jax.config.update("jax_enable_x64", True)  # the command is a program of its own: float64, said once here
    parser = argparse.ArgumentParser(prog="diffeit", description="Differentiable EIT for tactile skins.")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="simulate a touch on a 16-electrode skin and image it")
    demo.add_argument("-o", "--output", default="demo.png", help="PNG to write (default demo.png)")
    demo.add_argument("--seed", type=int, default=0, help="noise seed")
    demo.add_argument(
        "--skin",
        choices=("disc", "forearm", "fingertip"),
        default="disc",
        help="the skin: the flat unit disc (default), a forearm (a cylinder patch, radius 4 cm) or a fingertip "
        "(a sphere cap, radius 1 cm), drawn in 3D",
    )
    demo.set_defaults(run=_demo)

    reconstruct = commands.add_parser(
        "reconstruct",
        help="image every frame of a frames file (or an EIDORS .mat file) against its reference",
        description="diffeit.reconstruct on a file's recording, with its defaults for every option not given: "
        "the model is calibrated to the reference (the file's, frame K with --reference-frame, else the mean of "
        "the first frames; level, orientation, signs of magnitudes, broken readings) and refined (a contact "
        "impedance per electrode, the readout's mixing), then every frame is imaged. "
        "Writes OUT.png (an image strip) and OUT.h5 (a diffeit frames file with the images (T, E), their mesh and "
        "the calibration in its provenance). Images are conductivity changes (S/sq) for frames in volts, else "
        "relative conductivity changes. The sheet: the file's geometry, else its mesh, else a unit disc. A "
        "simulated file's scene sets the defaults of --background and --contact-impedance. Every frame's result "
        "code (successful, max_iterations_reached, ...) goes into OUT.h5's provenance. Exit status: 0 when every "
        "frame's solve succeeded; 1 when some frame's (or the background map's fit) failed, named on stderr, "
        "the files written all the same; 2 for bad input or options.",
    )
    reconstruct.add_argument("frames", help="a diffeit frames file (.h5) or an EIDORS .mat file")
    reconstruct.add_argument("-o", "--output", required=True, help="output name: writes OUT.png and OUT.h5")
    reconstruct.add_argument(
        "--method",
        choices=("one_step", "gauss_newton", "total_variation", "greit"),
        default="one_step",
        help="the reconstruction (default one_step)",
    )
    reconstruct.add_argument("--prior", default="noser", help="prior of one_step and gauss_newton (default noser)")
    reconstruct.add_argument(
        "--hyperparameter",
        default="auto",
        help="unit-free regularisation weight, or a rule choosing it from all the frames: auto (the L-curve's "
        "corner, else the noise figure), gcv, lcurve, noise_figure (default auto)",
    )
    reconstruct.add_argument(
        "--no-calibrate",
        dest="calibrate",
        action="store_false",
        help="image with the nominal model as it is: no fit of level, orientation, readings, contacts or mixing",
    )
    reconstruct.add_argument(
        "--background-map",
        action="store_true",
        help="fit a smooth background map to the reference (diffeit.fit.background) and image at it",
    )
    reconstruct.add_argument(
        "--difference",
        choices=("auto", "calibrated", "normalised"),
        default="auto",
        help="calibrated V - V_ref, or normalised (V - V_ref) / V_ref times the model's voltages (gains per "
        "reading); auto: calibrated when the calibrated model reproduces the reference (default auto)",
    )
    reconstruct.add_argument(
        "--driven-readings",
        choices=("auto", "keep", "drop"),
        default="auto",
        help="readings on driven electrodes: kept when the model reproduces them (auto, default), or forced",
    )
    reconstruct.add_argument(
        "--max-iterations",
        type=int,
        help="iteration limit of gauss_newton and total_variation (default: theirs, 20 and 100)",
    )
    reconstruct.add_argument(
        "--reference-frame",
        type=int,
        help="use frame K as the reference (default: the file's, else the mean of its first frames)",
    )
    reconstruct.add_argument(
        "--h", type=float, help="element size (m) of the mesh built from the file's geometry or the default disc"
    )
    reconstruct.add_argument("--background", type=float, help="nominal background conductivity, S/sq (default 1)")
    reconstruct.add_argument("--contact-impedance", type=float, help="nominal contact impedance, ohm m (default 0.01)")
    reconstruct.add_argument("--panels", type=int, default=12, help="most panels in the image strip (default 12)")
    reconstruct.add_argument("--variable", help=".mat files: the variable holding the frames")
    reconstruct.add_argument("--reference-variable", help=".mat files: the variable holding the reference frame")
    reconstruct.add_argument("--frame-rate", type=float, default=1.0, help=".mat files: frames per second")
    reconstruct.add_argument(
        "--calibration",
        help="a calibration file of this skin and board (from `diffeit calibrate`): images at its model, and "
        "touches read through its position map",
    )
    reconstruct.add_argument(
        "--touches",
        action="store_true",
        help="read the touches of every frame (diffeit.touches), print them frame by frame and write "
        "OUT.touches.csv: a header, then one row per touch: frame,time_s,count,touch,x_m,y_m,radius_m,depth "
        "(metres; depth the peak relative change; a frame without touches has no row), and mark them with a + "
        "on OUT.png",
    )
    reconstruct.add_argument("--overwrite", action="store_true", help="replace existing output files")
    reconstruct.set_defaults(run=reporting_user_errors("reconstruct", _reconstruct_file))
    experiment = commands.add_parser(
        "experiment",
        help="run a study of experiments/ (the dissertation's Chapter 5), writing its figures and tables",
        description="Run the study NAME, writing its PNG figures and CSV tables into DIR and printing its "
        "findings; --small runs the quick mode CI runs. --list names the studies.",
    )
    experiment.add_argument("name", nargs="?", help="the study to run (see --list)")
    experiment.add_argument("--list", action="store_true", help="name the studies and stop")
    experiment.add_argument("--small", action="store_true", help="the quick mode: fewer settings, coarser meshes")
    experiment.add_argument("-o", "--output", help="folder to write into (default experiments-output/NAME)")
    experiment.set_defaults(run=reporting_user_errors("experiment", _experiment))
    from ._simulate import add_command as add_simulate

    add_simulate(commands)
    from ._fit import add_command as add_fit

    add_fit(commands)
    from ._calibrate import add_command as add_calibrate

    add_calibrate(commands)
    from ._hardware import add_commands

    add_commands(commands)
    arguments = parser.parse_args(argv)
    return arguments.run(arguments)


if __name__ == "__main__":
    sys.exit(main())
