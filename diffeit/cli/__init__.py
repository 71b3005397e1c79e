"""The `diffeit` command line."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from ._errors import reporting_user_errors
from ._model import ModelSettings, add_model_options

if TYPE_CHECKING:
    from ..io import Recording
    from ..mesh import Mesh

# Frames reconstructed per batch: one matrix product each, and one step of the progress bar.
_BATCH = 256
# The hyperparameter selection methods `reconstruct` offers: those that need only the frames.
_SELECTION_METHODS = ("gcv", "lcurve")


def _demo(arguments: argparse.Namespace) -> int:
    from ..demo import run_demo

    result = run_demo(arguments.output, seed=arguments.seed)
    print(
        f"data mesh {result.n_data_elements} triangles, reconstruction mesh "
        f"{result.n_reconstruction_elements} triangles\n"
        f"position error: {result.position_error:.4f} m (unit disc)\n"
        f"correlation with the truth: {result.correlation:.3f}\n"
        f"peak dsigma: {result.peak:.3e} S/sq\n"
        f"wrote {result.figure}"
    )
    return 0


def _reconstruct_file(arguments: argparse.Namespace) -> int:
    from .. import io
    from ..plotting import plot_image_strip

    source = Path(arguments.frames)
    outputs = _output_paths(arguments.output, (".png", ".h5"), arguments.overwrite)
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
    if arguments.reference_frame is None and recording.reference is None:
        raise ValueError(f"{source} has no reference frame; choose one with --reference-frame K")

    settings = ModelSettings.from_arguments(arguments, methods=_SELECTION_METHODS, **_scene_settings(recording))
    mesh = _mesh_of(recording, settings)
    images, hyperparameter = reconstruct_recording(
        recording, mesh, settings, reference_frame=arguments.reference_frame, difference=arguments.difference
    )
    reconstructed = _with_images(
        recording,
        source,
        "diffeit reconstruct",
        reference=recording.reference_values(arguments.reference_frame),
        mesh=mesh,
        images=images,
        image_quantity="conductivity change",
        metadata={
            "variable": arguments.variable,
            "reference_frame": arguments.reference_frame,
            "reference_variable": arguments.reference_variable,
            "prior": settings.prior,
            "hyperparameter": hyperparameter,
            "hyperparameter_choice": settings.hyperparameter,
            "background": settings.background,
            "contact_impedance": settings.contact_impedance,
            "difference": arguments.difference,
        },
    )
    shown = plot_image_strip(
        outputs[0],
        mesh,
        images,
        times=recording.times,
        max_panels=arguments.panels,
        title=f"{source.name}: one-step {settings.prior}, hyperparameter {hyperparameter:.3g}",
    )
    io.write_frames(outputs[1], reconstructed, overwrite=arguments.overwrite)
    peak = images.flat[np.argmax(np.abs(images))]
    print(
        f"{recording.n_frames} frames, {mesh.n_elements} triangles; hyperparameter {hyperparameter:.3g}; "
        f"peak dsigma {peak:.3e} S/sq\n"
        f"wrote {outputs[0]} ({len(shown)} panels) and {outputs[1]} (images {images.shape})"
    )
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


def reconstruct_recording(
    recording: Recording,
    mesh: Mesh,
    settings: ModelSettings | None = None,
    *,
    reference_frame: int | None = None,
    difference: str = "plain",
) -> tuple[np.ndarray, float]:
    """(T, E) conductivity changes (S/sq) of every frame of `recording` on `mesh`, one-step, and
    the hyperparameter used.

    The reference is the recording's, or its frame `reference_frame`. `difference`:

    - "plain": dV = V - V_ref. Frames not in volts (`voltage_unit` other than "V", such as
      EIDORS files in device units) are scaled by RMS(V_model) / RMS(V_ref), V_model the
      model's voltages at the background conductivity: one gain that puts them on the model's scale.
    - "relative": normalised differences (V - V_ref) / V_ref, reading by reading
      (`OneStep(..., normalised=True)`): they cancel per-channel gains and restore the sign
      lost by devices that report magnitudes (the Montreal data).

    `settings` (default `ModelSettings()`) name the model and the solver; a hyperparameter that
    names a selection method of `diffeit.inverse.select_hyperparameter` ("gcv", "lcurve") is
    chosen from all the frames at once.
    """
    from tqdm import tqdm

    from ..inverse import select_hyperparameter

    settings = ModelSettings() if settings is None else settings
    if difference not in ("plain", "relative"):
        raise ValueError(f'difference must be "plain" or "relative"; got {difference!r}')
    model = settings.model(mesh, recording.protocol)
    reference = recording.reference_values(reference_frame)
    dv = recording.difference(reference_frame=reference_frame)
    relative = difference == "relative"
    if not relative and recording.voltage_unit != "V":
        model_reference = np.asarray(model.measure(np.full(mesh.n_elements, settings.background)))
        dv = dv * _rms(model_reference) / _rms(reference)
    options = {"reference": reference} if relative else {}
    hyperparameter = settings.hyperparameter
    if isinstance(hyperparameter, str):
        hyperparameter = select_hyperparameter(
            model,
            dv,
            hyperparameter,
            prior=settings.prior,
            background=settings.background,
            normalised=relative,
            throw=False,  # a choice at an end of the candidates is still used, as before
            **options,
        ).value
    solver = settings.solver(model, hyperparameter=hyperparameter, normalised=relative)
    batches = range(0, len(dv), _BATCH)
    # tqdm's disable=None: a bar on a terminal only, and only when there are several batches.
    progress = tqdm(batches, desc="reconstructing", unit="batch", disable=True if len(batches) < 2 else None)
    images = np.concatenate(
        [np.asarray(solver.reconstruct(dv[start : start + _BATCH], **options)) for start in progress]
    )
    return images, float(hyperparameter)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `diffeit` command with `argv` (default: the process's arguments); returns the
    exit status."""
    jax.config.update("jax_enable_x64", True)  # the command is a program of its own: float64, said once here
    parser = argparse.ArgumentParser(prog="diffeit", description="Differentiable EIT for tactile skins.")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="simulate a touch on a 16-electrode skin and image it")
    demo.add_argument("-o", "--output", default="demo.png", help="PNG to write (default demo.png)")
    demo.add_argument("--seed", type=int, default=0, help="noise seed")
    demo.set_defaults(run=_demo)

    reconstruct = commands.add_parser(
        "reconstruct",
        help="image every frame of a frames file (or an EIDORS .mat file) against its reference",
        description="One-step difference reconstruction of every frame; writes OUT.png (an image strip) and "
        "OUT.h5 (the images (T, E) with their mesh, a diffeit frames file). A simulated file's scene sets the "
        "defaults of --background and --contact-impedance.",
    )
    reconstruct.add_argument("frames", help="a diffeit frames file (.h5) or an EIDORS .mat file")
    reconstruct.add_argument("-o", "--output", required=True, help="output name: writes OUT.png and OUT.h5")
    reconstruct.add_argument("--reference-frame", type=int, help="use frame K as the reference (default: the file's)")
    add_model_options(reconstruct, methods=_SELECTION_METHODS)
    reconstruct.add_argument(
        "--difference",
        choices=("plain", "relative"),
        default="plain",
        help="plain V - V_ref, or relative (normalised) (V - V_ref) / V_ref times the model's reference",
    )
    reconstruct.add_argument("--panels", type=int, default=12, help="most panels in the image strip (default 12)")
    reconstruct.add_argument("--variable", help=".mat files: the variable holding the frames")
    reconstruct.add_argument("--reference-variable", help=".mat files: the variable holding the reference frame")
    reconstruct.add_argument("--frame-rate", type=float, default=1.0, help=".mat files: frames per second")
    reconstruct.add_argument("--overwrite", action="store_true", help="replace existing output files")
    reconstruct.set_defaults(run=reporting_user_errors("reconstruct", _reconstruct_file))
    from ._simulate import add_command as add_simulate

    add_simulate(commands)
    from ._fit import add_command as add_fit

    add_fit(commands)
    from ._hardware import add_commands

    add_commands(commands)
    arguments = parser.parse_args(argv)
    return arguments.run(arguments)


if __name__ == "__main__":
    sys.exit(main())
