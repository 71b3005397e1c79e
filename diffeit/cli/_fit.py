"""`diffeit fit FRAMES.h5 -o OUT`: the joint fit of a frames file (background map, contact
impedances, memory parameters and the memoryless stimulus), its corrected images and a figure."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import signal
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import _mesh_of, _output_paths, _with_images
from ._errors import reporting_user_errors
from ._model import ModelSettings, add_model_options

if TYPE_CHECKING:
    from ..fit import JointFit, JointProgress, MemoryUncertainty
    from ..inverse import OneStep
    from ..mesh import Mesh
    from ..protocol import Protocol

# What the images of OUT.h5 hold: the io schema's "conductivity change" is in S/sq, these are
# relative and free of the skin's memory.
IMAGE_QUANTITY = "relative conductivity change dsigma/sigma, memoryless stimulus (diffeit fit)"
# Exit statuses: 0 converged; 1 the fit ran but did not converge, or a computation after it
# failed (its files are written); 2 bad input; 128 + the signal when one of `STOPPING_SIGNALS`
# stopped it (Ctrl-C 130, SIGTERM 143: the fit so far is saved), as a shell reports a process
# the signal ended.
FELL_SHORT = 1
STOPPING_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# The default --checkpoint-every, accepted steps: a checkpoint costs about one objective evaluation
# and a file write, a step at least one evaluation and its gradient.
CHECKPOINT_EVERY = 25
CHECKPOINT_SUFFIX = ".checkpoint.fit.h5"


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `fit` to the subcommands `commands` of the `diffeit` parser."""
    fit = commands.add_parser(
        "fit",
        help="fit background, contact impedances, memory and the memoryless stimulus to a frames file",
        description="The joint fit (diffeit.fit.joint) of every frame of a frames file: the background "
        "conductivity map, the contact impedances, the skin's memory parameters and the memoryless stimulus "
        "(dsigma/sigma) of every frame, through the forward model with the memory model in the loop. The first "
        "--reference-frames frames must be untouched (the file's separate reference frame is not used). Writes "
        "OUT.h5 (a frames file whose images are the stimulus), OUT.fit.h5 (the fit: diffeit.fit.load reads it, "
        "diffeit live --memory applies it) and OUT.png (the background map, the parameters, and the images "
        "before and after the memory correction). While it runs, the fit so far goes to OUT.checkpoint.fit.h5 "
        "every --checkpoint-every accepted steps, each time written whole to a temporary file and renamed over "
        "the last (a kill, even SIGKILL, leaves the last checkpoint intact): --resume OUT.checkpoint.fit.h5 "
        "continues from it; it is removed once OUT.fit.h5 holds the result. Ctrl-C or SIGTERM stops the fit at "
        "its next step with the checkpoint written there (a second one stops at once). Exit status 0 when the "
        "fit converged; 1 when it did not, or when the memory uncertainty or the images before correction "
        "failed (stderr says which; the files hold the last iterate: raise --max-steps or --resume from "
        "OUT.fit.h5); 2 for bad input; 130 when stopped by Ctrl-C and 143 by SIGTERM. "
        "--background and --contact-impedance, when given, are the fit's starting values (fixed when their "
        "group is not --free; a simulated file's scene does not set them: the fit finds its own); --prior and "
        "--hyperparameter set the one-step images shown before correction.",
    )
    fit.add_argument("frames", help="a diffeit frames file (.h5), frames in volts")
    fit.add_argument("-o", "--output", required=True, help="output name: writes OUT.h5, OUT.fit.h5 and OUT.png")
    fit.add_argument(
        "--reference-frames", type=int, default=1, help="the first K frames are untouched: the reference (default 1)"
    )
    fit.add_argument("--max-steps", type=int, help="L-BFGS steps at most (default: diffeit.fit.joint's)")
    fit.add_argument(
        "--noise",
        type=float,
        help="the readings' noise, percent of the reference's RMS: balances misfit and priors (default 0.5)",
    )
    fit.add_argument(
        "--free",
        nargs="+",
        metavar="GROUP",
        help="the groups fitted, of background, contact_impedance, memory, stimulus (default all); the others "
        "keep their starting values",
    )
    fit.add_argument(
        "--resume",
        metavar="FIT",
        help="continue from a saved fit: OUT.fit.h5 of an earlier run, or the OUT.checkpoint.fit.h5 an "
        "interrupted or killed run left",
    )
    fit.add_argument(
        "--checkpoint-every",
        type=int,
        default=CHECKPOINT_EVERY,
        metavar="N",
        help=f"write the fit so far to OUT{CHECKPOINT_SUFFIX} every N accepted steps, and when stopped by "
        f"Ctrl-C or SIGTERM (default {CHECKPOINT_EVERY}; 0: only when stopped)",
    )
    add_model_options(fit)
    fit.add_argument("--panels", type=int, default=8, help="most frames shown before and after (default 8)")
    fit.add_argument("--overwrite", action="store_true", help="replace existing output files")
    fit.set_defaults(run=reporting_user_errors("fit", _fit_file))


def _fit_file(arguments: argparse.Namespace) -> int:
    from .. import io
    from .._messages import name_indices
    from ..fit import joint, load, memory_uncertainty
    from ..results import RESULTS, messages, names

    source = Path(arguments.frames)
    png, images_file, fit_file = _output_paths(arguments.output, (".png", ".h5", ".fit.h5"), arguments.overwrite)
    # Its own rule: an earlier run's checkpoint is the run to continue, not an output to refuse.
    (checkpoint_file,) = _output_paths(arguments.output, (CHECKPOINT_SUFFIX,), overwrite=True)
    continued = arguments.resume is not None and Path(arguments.resume).resolve() == checkpoint_file.resolve()
    if checkpoint_file.exists() and not (continued or arguments.overwrite):
        raise FileExistsError(
            f"{checkpoint_file} exists, the state of an interrupted fit: continue it with --resume {checkpoint_file}, "
            "or pass --overwrite to start afresh"
        )
    if arguments.panels < 1:
        raise ValueError(f"--panels must be at least 1; got {arguments.panels}")
    if arguments.checkpoint_every < 0:
        raise ValueError(f"--checkpoint-every must be 0 or more (accepted steps); got {arguments.checkpoint_every}")
    recording = io.read_frames(source)
    if recording.n_frames < 3:
        raise ValueError(f"{source} holds {recording.n_frames} frames; the joint fit needs at least 3")
    if recording.voltage_unit != "V":
        raise ValueError(
            f"{source} holds frames in {recording.voltage_unit!r} units: the fit is absolute and needs volts"
        )
    # No fallbacks from a simulated file's scene: its true values would give the fit a head start.
    settings = ModelSettings.from_arguments(arguments)
    mesh = _mesh_of(recording, settings)
    model = settings.model(mesh, recording.protocol)
    initial: dict | JointFit = {}
    if arguments.resume:
        initial = load(arguments.resume)
    else:
        if arguments.background is not None:
            initial["background"] = settings.background
        if arguments.contact_impedance is not None:
            initial["contact_impedance"] = settings.contact_impedance
    options = {
        name: value
        for name, value in (("max_steps", arguments.max_steps), ("noise", arguments.noise))
        if value is not None
    }
    if arguments.free is not None:
        options["free"] = [name.replace("-", "_") for item in arguments.free for name in item.split(",") if name]

    signals = _DeferredSignals()
    checkpoints = _Checkpoints(checkpoint_file, arguments.checkpoint_every, signals)
    start = time.perf_counter()
    try:
        with signals:
            fit = joint(
                model,
                recording.frames,
                recording.times,
                reference_frames=arguments.reference_frames,
                initial=initial or None,
                progress=sys.stderr.isatty(),
                throw=False,
                on_step=checkpoints,
                **options,
            )
            fit.save(fit_file, overwrite=arguments.overwrite)
    except _Stopped as stopped:
        print(
            f"diffeit fit: stopped by {signal.Signals(stopped.number).name}; the fit at step {stopped.steps} is in "
            f"{checkpoint_file}: continue with diffeit fit {source} -o {arguments.output} --resume {checkpoint_file}",
            file=sys.stderr,
        )
        return 128 + stopped.number
    if signals.received is not None:  # as the fit ended, after its last step
        checkpoint_file.unlink(missing_ok=True)
        print(
            f"diffeit fit: stopped by {signal.Signals(signals.received).name} as the fit ended; it is in {fit_file} "
            f"({images_file} and {png} not written)",
            file=sys.stderr,
        )
        return 128 + signals.received
    seconds = time.perf_counter() - start
    converged = bool(fit.result == RESULTS.successful)
    steps = len(fit.history.objective) - 1
    # What fell short after the fit, by computation: said on stderr and kept in OUT.h5.
    failures = {}
    uncertainty = None
    if _shared_memory_fitted(fit):
        try:
            uncertainty = memory_uncertainty(model, recording.frames, fit)
        except (ValueError, np.linalg.LinAlgError) as error:
            failures["memory_uncertainty"] = str(error)
        else:
            if np.isnan(uncertainty.relative_error).any():
                failures["memory_uncertainty"] = "NaN standard errors (an information matrix not finite)"
                uncertainty = None

    reference = np.mean(recording.frames[: arguments.reference_frames], axis=0)
    solver = fitted_one_step(fit, mesh, recording.protocol, settings)
    before = np.asarray(solver.solve(recording.frames - reference, throw=False).value) / np.asarray(fit.background)
    nonfinite = np.flatnonzero(~np.all(np.isfinite(before), axis=1))
    if nonfinite.size:
        failures["images_before"] = f"the one-step images of frames {name_indices(nonfinite)} are not finite"
    stimulus = np.asarray(fit.stimulus)

    corrected = _with_images(
        recording,
        source,
        "diffeit fit",
        reference=recording.reference,
        mesh=mesh,
        images=stimulus,
        image_quantity=IMAGE_QUANTITY,
        metadata={
            "fit": str(fit_file),
            "reference_frames": arguments.reference_frames,
            "free": list(fit.settings.free),
            "result": names(fit.result)[0],
            "result_message": messages(fit.result)[0],
            "failures": failures,
            "steps": steps,
            "misfit": fit.misfit,
            "seconds": seconds,
            "memory": _memory_values(fit),
            "memory_relative_error": {}
            if uncertainty is None
            else dict(zip(uncertainty.names, uncertainty.relative_error.tolist(), strict=True)),
        },
    )
    io.write_frames(images_file, corrected, overwrite=arguments.overwrite)
    shown = plot_fit(
        png,
        mesh,
        fit,
        before,
        times=recording.times,
        max_panels=arguments.panels,
        title=f"{source.name}: joint fit, {steps} steps, {'converged' if converged else 'NOT converged'}",
        seconds=seconds,
        uncertainty=uncertainty,
    )
    peak = stimulus.flat[np.argmax(np.abs(stimulus))]
    print(
        f"{recording.n_frames} frames, {mesh.n_elements} triangles; joint fit: {steps} steps in {seconds:.1f} s, "
        f"{'converged' if converged else 'did not converge'}\n"
        f"misfit {fit.misfit:.3g} (relative); background {float(np.median(fit.background)):.3g} S/sq (median); "
        f"peak stimulus {peak:.3g} dsigma/sigma\n"
        f"memory: {_memory_line(fit, uncertainty)}\n"
        f"wrote {png} ({len(shown)} frames before and after), {images_file} (stimulus {stimulus.shape}) and {fit_file}"
    )
    # Superseded by OUT.fit.h5, written above.
    checkpoint_file.unlink(missing_ok=True)
    if not converged:
        print(
            f"diffeit fit: the joint fit did not converge ({messages(fit.result)[0]}); the files hold its last "
            f"iterate: raise --max-steps, or continue with --resume {fit_file}",
            file=sys.stderr,
        )
    for name, failure in failures.items():
        print(f"diffeit fit: {name.replace('_', ' ')} failed: {failure}", file=sys.stderr)
    return 0 if converged and not failures else FELL_SHORT


class _Stopped(Exception):
    """The stopping signal `number` stopped the fit at a step; the fit at `steps` accepted steps
    is saved."""

    def __init__(self, number: int, steps: int) -> None:
        super().__init__(number, steps)
        self.number, self.steps = number, steps


class _DeferredSignals:
    """While the block runs, the first of `STOPPING_SIGNALS` is kept in `received` (its number)
    for the fit's next step to act on, not raised where it lands: a KeyboardInterrupt raised
    inside the forward model's host solve reaches Python as an XLA runtime error, and the fit
    could not save its state. After it the handlers are the previous ones again: a second
    signal stops at once. Only the main thread may set handlers; elsewhere they stay."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, object] = {}

    def __enter__(self) -> _DeferredSignals:
        if threading.current_thread() is threading.main_thread():
            self._previous = {number: signal.signal(number, self._receive) for number in STOPPING_SIGNALS}
        return self

    def __exit__(self, *exception: object) -> None:
        self._restore()

    def _receive(self, number: int, frame: object) -> None:
        self.received = number
        self._restore()
        # os.write, not print: a handler may run while another write to stderr is under way.
        os.write(2, b"diffeit fit: stopping at the fit's next step, saving it there (again to stop at once)\n")

    def _restore(self) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)
        self._previous = {}


class _Checkpoints:
    """The joint fit's `on_step`: writes the fit so far over `path` every `every` accepted steps
    of this run (0: never on a count) and, once `signals` received one, at the next step, then
    stops the fit there (`_Stopped`). `JointFit.save` writes a temporary file and renames it into
    place: a kill mid-write leaves the last checkpoint whole."""

    def __init__(self, path: Path, every: int, signals: _DeferredSignals) -> None:
        self.path, self.every, self.signals = path, every, signals
        self.first: int | None = None

    def __call__(self, progress: JointProgress) -> None:
        if self.first is None:
            self.first = progress.steps
        done = progress.steps - self.first
        if self.signals.received is not None or (self.every and done and done % self.every == 0):
            progress.fit().save(self.path, overwrite=True)
        if self.signals.received is not None:
            raise _Stopped(self.signals.received, progress.steps)


def fitted_one_step(fit: JointFit, mesh: Mesh, protocol: Protocol, settings: ModelSettings) -> OneStep:
    """The one-step solver linearised at the fit's background and contact impedances (prior and
    hyperparameter from `settings`): its images over `fit.background` are relative changes
    dsigma/sigma, what the memory correction takes. ValueError when the fit was made on
    another mesh."""
    from ..forward import ForwardModel
    from ..inverse import OneStep

    background = np.asarray(fit.background)
    z = np.asarray(fit.contact_impedance)
    if background.shape != (mesh.n_elements,) or z.shape != (mesh.n_electrodes,):
        raise ValueError(
            f"the fit was made on a mesh of {background.size} elements and {z.size} electrodes; this mesh has "
            f"{mesh.n_elements} and {mesh.n_electrodes} (give the --h of the fit's mesh)"
        )
    model = ForwardModel(mesh, protocol, contact_impedance=z)
    hyperparameter = settings.hyperparameter_at(model, background)
    return OneStep(model, prior=settings.prior, hyperparameter=hyperparameter, background=background)


def plot_fit(
    path: str | Path,
    mesh: Mesh,
    fit: JointFit,
    before: np.ndarray,
    *,
    times: np.ndarray,
    max_panels: int = 8,
    title: str = "",
    seconds: float | None = None,
    uncertainty: MemoryUncertainty | None = None,
) -> np.ndarray:
    """Save the fit's figure as a PNG: the background map and a table of the parameters (with the
    memory parameters' relative standard errors when `uncertainty` gives them) above,
    the plain one-step images `before` (T, E) dsigma/sigma and the fitted stimulus below, the
    same frames (every k-th, at most `max_panels`) on one colour scale; returns the frames shown."""
    from matplotlib.figure import Figure

    from ..plotting import mesh_projection, plot_elements
    from ..results import RESULTS, messages

    stimulus = np.asarray(fit.stimulus)
    shown = np.arange(0, len(stimulus), math.ceil(len(stimulus) / max_panels))
    limit = float(max(np.max(np.abs(before[shown])), np.max(np.abs(stimulus[shown])))) or 1.0
    columns = max(len(shown), 4)
    figure = Figure(figsize=(1.6 * columns + 1.0, 9.0), layout="constrained")
    top, *strips = figure.subfigures(3, 1, height_ratios=[1.7, 1.0, 1.0])
    map_axes, table_axes = top.subplots(1, 2, width_ratios=[1.0, 1.6])
    if mesh_projection(mesh) is not None:  # a skin on a curved surface: its map in 3D axes in the same place
        map_axes.remove()
        map_axes = top.add_subplot(map_axes.get_subplotspec(), projection=mesh_projection(mesh))
    plot_elements(map_axes, mesh, np.asarray(fit.background), cmap="viridis", symmetric=False, label="S/sq")
    map_axes.set_title("background conductivity", fontsize=9)
    table_axes.set_axis_off()
    table = table_axes.table(
        cellText=_parameter_rows(fit, seconds, uncertainty), colWidths=[0.42, 0.58], cellLoc="left", loc="center"
    )
    table.auto_set_font_size(False)
    table.set_fontsize(7.5)
    table.scale(1.0, 1.15)
    if not bool(fit.result == RESULTS.successful):
        message = textwrap.fill(messages(fit.result)[0], 70)
        table_axes.text(
            0.5, -0.02, message, ha="center", va="top", fontsize=7.5, color="C3", transform=table_axes.transAxes
        )
    if title:
        top.suptitle(title, fontsize=10)
    names = ("before: plain one-step images against the reference", "after: the fitted stimulus")
    for strip, images, name in zip(strips, (before, stimulus), names, strict=True):
        kw = {"projection": mesh_projection(mesh)}  # 3D axes for a skin on a curved surface
        axes = np.atleast_1d(strip.subplots(1, columns, squeeze=False, subplot_kw=kw)).ravel()
        for ax, frame in zip(axes, shown, strict=False):
            artist = plot_elements(ax, mesh, images[frame], label=None)
            artist.set_clim(-limit, limit)
            artist.colorbar.remove()  # one colour bar per strip
            ax.set_title(f"frame {frame}, {times[frame]:.2f} s", fontsize=7)
        for ax in axes[len(shown) :]:
            ax.set_axis_off()
        strip.colorbar(artist, ax=list(axes), shrink=0.8, label="dsigma/sigma")
        strip.suptitle(name, fontsize=9)
    figure.savefig(path, dpi=100)
    return shown


def _parameter_rows(
    fit: JointFit, seconds: float | None, uncertainty: MemoryUncertainty | None = None
) -> list[list[str]]:
    from ..results import RESULTS

    z = np.asarray(fit.contact_impedance)
    b = np.asarray(fit.background)
    objective = fit.history.objective
    free = fit.settings.memory_fitted
    rows = [
        ["result", "converged" if bool(fit.result == RESULTS.successful) else "NOT converged (below)"],
        ["steps; objective", f"{len(objective) - 1}; {objective[0]:.4g} -> {objective[-1]:.4g}"],
        ["misfit (relative)", f"{fit.misfit:.3g}"],
        ["background, S/sq", f"{b.min():.3g} .. {np.median(b):.3g} .. {b.max():.3g}"],
        ["contact impedance, ohm m", f"{z.min():.3g} .. {np.mean(z):.3g} .. {z.max():.3g}"],
    ]
    for name, value in _memory_values(fit).items():
        rows.append([f"memory {name}", _memory_value(name, value, free, uncertainty)])
    if seconds is not None:
        rows.append(["time", f"{seconds:.1f} s"])
    return rows


def _memory_values(fit: JointFit) -> dict[str, float | list]:
    """The fitted memory parameters by field name, as plain numbers (lists when per element)."""
    memory = fit.memory
    return {field.name: np.asarray(getattr(memory, field.name)).tolist() for field in dataclasses.fields(memory)}


def _shared_memory_fitted(fit: JointFit) -> bool:
    """Whether the fit fitted memory parameters shared by all elements (what
    `diffeit.fit.memory_uncertainty` reports on)."""
    names = fit.settings.memory_fitted
    return bool(names) and all(np.size(getattr(fit.memory, name)) == 1 for name in names)


def _memory_value(name: str, value: float | list, free: tuple[str, ...], uncertainty: MemoryUncertainty | None) -> str:
    """A memory parameter's value, "(fixed)" when not fitted, and its relative standard error when known."""
    if name not in free:
        return f"{_number(value)} (fixed)"
    if uncertainty is None:
        return _number(value)
    return f"{_number(value)} {uncertainty.error_text(name)}"


def _memory_line(fit: JointFit, uncertainty: MemoryUncertainty | None) -> str:
    free = fit.settings.memory_fitted
    values = _memory_values(fit)
    fitted = [f"{name} {_memory_value(name, values[name], free, uncertainty)}" for name in values if name in free]
    if not fitted:
        return "fixed (not fitted)"
    return ", ".join(fitted) + (
        "" if uncertainty is None else " (+-: relative standard error, the data's Cramer-Rao bound)"
    )


def _number(value: float | list) -> str:
    if isinstance(value, list):
        array = np.asarray(value)
        return f"{array.min():.3g} .. {array.max():.3g}"
    return f"{value:.3g}"
