"""`diffeit acquire`, `diffeit live` and `diffeit emulate`: the command line of the hardware
module `hw`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._errors import reporting_user_errors
from ._model import ModelSettings, add_model_options

if TYPE_CHECKING:
    import hw

    from ..calibration import SkinCalibration
    from ..fit import JointFit
    from ..protocol import Protocol

_PROTOCOLS = ("adjacent", "opposite", "full")
# The dead band of the live memory correction, in standard deviations of the image noise: under it
# a held press stays held (noise read as a chattering load would pump the skin's hysteretic modes
# and make a long press fade), above it a real change passes.
DEAD_BAND = 3.0
# The live image's colour scale, dsigma/sigma from -L to L: fixed, so that frames compare and an
# untouched skin shows pale noise instead of noise stretched to full scale.
COLOUR_LIMIT = 0.5
# `live --hyperparameter auto`: a rule that needs no frames to come (the noise figure of
# diffeit.reconstruct's "auto" fallback); the L-curve would need the frames themselves.
_LIVE_METHODS = ("auto",)


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Add `acquire`, `live` and `emulate` to the subcommands of `diffeit`."""
    acquire = commands.add_parser(
        "acquire",
        help="record frames from a serial device into a frames file",
        description="Read frames from a serial port (binary diffeit frames, or text lines with --text) and append "
        "each to OUT (a diffeit frames file, readable at any time, also after a crash). Ctrl-C ends the run.",
    )
    _source_arguments(acquire)
    acquire.add_argument("-o", "--output", required=True, help="frames file to write (.h5)")
    acquire.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    acquire.set_defaults(run=_acquire)

    live = commands.add_parser(
        "live",
        help="reconstruct frames from a serial device as they arrive",
        description="One-step difference images of frames as they arrive, in batches, against the first frame "
        "(or the mean of the first --reference-frames), with the model calibrated to that reference as "
        "diffeit reconstruct does (level, orientation, broken readings). Shows the relative change dsigma/sigma "
        "on a fixed colour scale (--colour-limit) in a window, or without a display saves the latest image to --png. "
        "Exit status: 0 when frames were imaged, all finite; 1 when none was, or some image was not finite (counted "
        "on stderr and in the image's title); 2 for bad options or a device that cannot be opened.",
    )
    _source_arguments(live)
    live.add_argument(
        "--reference-frames",
        type=int,
        default=1,
        help="frames averaged into the reference (1), but those of 3 or more that look damaged; with 6 or more "
        "the skin's drift is followed and taken out",
    )
    live.add_argument("--batch", type=int, default=8, help="frames reconstructed together (8)")
    add_model_options(live, methods=_LIVE_METHODS, hyperparameter_default="auto")
    live.add_argument(
        "--colour-limit",
        type=float,
        default=COLOUR_LIMIT,
        help=f"the colour scale's end: dsigma/sigma from -L to +L, the same for every frame ({COLOUR_LIMIT:g})",
    )
    live.add_argument(
        "--memory",
        metavar="FIT",
        help="a saved joint fit (OUT.fit.h5 of diffeit fit): image on its background and contact impedances and "
        "show the memoryless stimulus dsigma/sigma, the skin's memory corrected frame by frame (causally)",
    )
    live.add_argument(
        "--dead-band",
        type=float,
        default=DEAD_BAND,
        help="--memory: image changes below this many noise standard deviations (at the fit's noise level) "
        f"keep the stimulus ({DEAD_BAND:g}; 0: the exact inverse, whose long presses fade in noise)",
    )
    live.add_argument(
        "--calibration",
        metavar="SKIN.cal.h5",
        help="a calibration file of this skin and board (from `diffeit calibrate`): image at its model (its mesh, "
        "level, contact impedances, gains) and, with --hyperparameter auto, its hyperparameter, instead of "
        "calibrating to the reference; touches are read through its position map. Not with --memory, --h, "
        "--background or --contact-impedance (it brings its model)",
    )
    live.add_argument(
        "--touches",
        action="store_true",
        help="print each frame's touches (diffeit.touch.LiveTouches): position in mm, radius in mm, depth "
        "(the peak dsigma/sigma); with --calibration, through its position map and polarity (without labelled "
        "presses, the polarity the first touched frames show), and, when it knows its readings' noise, a frame "
        "counts as touched by the voltage test and each touch is read against the rest before it",
    )
    live.add_argument("--png", default="live.png", help="image written when there is no display (live.png)")
    live.set_defaults(run=_live)

    emulate = commands.add_parser(
        "emulate",
        help="stream a simulated scene over a pseudo-terminal, as a device would",
        description="Simulate SCENE.toml (diffeit.simulate) and stream its frames, the reference first, over a "
        "pseudo-terminal in raw mode at the scene's frame rate; a client opens --port as a serial port.",
    )
    emulate.add_argument("scene", help="a scene file (.toml)")
    emulate.add_argument("--port", default="./ttyEIT", help="path of the emulated port, a link (./ttyEIT)")
    emulate.add_argument("--frame-rate", type=float, help="frames per second (default: the scene's)")
    emulate.add_argument("--text", action="store_true", help="send text lines instead of binary frames")
    emulate.add_argument(
        "--faults",
        default="",
        help="fault rates per frame, e.g. bit_flip=0.01,truncated=0.01,disconnect=0.002 (kinds: bit_flip, "
        "dropped_bytes, truncated, stall, disconnect)",
    )
    emulate.add_argument("--seed", type=int, default=0, help="seed of the faults (0)")
    emulate.add_argument("--wait", type=float, default=60.0, help="seconds to wait for a client (60)")
    emulate.add_argument("--log", help="write the ground-truth fault log here (JSON)")
    emulate.set_defaults(run=reporting_user_errors("emulate", _emulate_scene, (ValueError, FileNotFoundError)))


def _source_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--port", required=True, help="serial port name or pyserial URL (socket://host:port)")
    parser.add_argument("--baudrate", type=int, default=115200, help="bits per second (115200)")
    parser.add_argument(
        "--protocol",
        choices=_PROTOCOLS,
        help="the frames' protocol: adjacent (n(n-3) values), opposite, full (the n x n adjacent layout); "
        "binary frames declare theirs, text lines need it (default adjacent)",
    )
    parser.add_argument("--electrodes", type=int, default=16, help="number of electrodes (16)")
    parser.add_argument("--text", action="store_true", help="the device prints text lines, not binary frames")
    parser.add_argument("--frames", type=int, help="stop after this many frames")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument(
        "--reconnect-timeout", type=float, default=5.0, help="seconds to wait for a vanished device (5)"
    )


def _protocol(name: str | None, n_electrodes: int) -> Protocol | None:
    from ..protocol import adjacent, opposite

    if name is None:
        return None
    if name == "opposite":
        return opposite(n_electrodes)
    return adjacent(n_electrodes, measure_driven=name == "full")


def _open_source(arguments: argparse.Namespace) -> hw.SerialSource:
    import hw

    protocol = _protocol(arguments.protocol, arguments.electrodes)
    if arguments.text:
        parser = hw.TextParser(protocol if protocol is not None else _protocol("adjacent", arguments.electrodes))
    else:
        parser = hw.BinaryParser(protocol)
    return hw.SerialSource(
        arguments.port, parser, baudrate=arguments.baudrate, reconnect_timeout=arguments.reconnect_timeout
    )


def _undamaged(reference: np.ndarray) -> np.ndarray:
    """The reference frames (T, M) but those that look damaged (a board's glitch, often its
    first frame after it connects: `diffeit.calibration`'s test, of 3 frames or more), which
    are said."""
    from .._messages import name_indices
    from ..calibration import damaged_frames

    damaged = damaged_frames(reference)
    if damaged.any():
        print(
            f"reference frame(s) {name_indices(np.flatnonzero(damaged))} left out: they differ from the others by "
            "more than half their size (damaged)",
            flush=True,
        )
    return reference[~damaged]


def _touched_reference_said(reference: np.ndarray, skin: SkinCalibration | None) -> None:
    """Say on stderr which of the reference frames (T, M) look touched against the calibration's
    reference (`diffeit.touch.touched`, in its noise): a finger on the skin as the stream began,
    or a skin that changed since its calibration. Every frame is imaged against them all the
    same: a single frame cannot tell the two apart (`diffeit.reconstruct` of a recording can,
    `diffeit.calibration.calibrated_reference_frames`)."""
    if skin is None or skin.reference is None or skin.noise is None:
        return
    from .._messages import name_indices
    from ..touch import touched

    pressed = touched(reference, skin.reference, skin)
    if pressed is not None and pressed.any():
        print(
            f"diffeit live: reference frame(s) {name_indices(np.flatnonzero(pressed))} look touched against the "
            "calibration's reference (a finger on the skin, or a skin changed since its calibration): touches are "
            "read against them; start again untouched if they were",
            file=sys.stderr,
            flush=True,
        )


def _frame_protocol(source: hw.SerialSource, frame: hw.Frame) -> Protocol:
    """The protocol of the frames: the declared one, else the layout the first frame names."""
    import hw

    if source.parser.protocol is not None:
        return source.parser.protocol
    protocol = hw.layout_protocol(frame.layout, frame.n_electrodes)
    if protocol is None:
        raise ValueError(f"the device sends frames of {frame.n_values} values without a layout: pass --protocol")
    return protocol


def _acquire(arguments: argparse.Namespace) -> int:
    from tqdm import tqdm

    import hw

    output = Path(arguments.output)
    if output.exists() and not arguments.overwrite:
        print(f"diffeit acquire: error: {output} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    if not output.parent.is_dir():  # before the device streams: no frame is read to be lost
        print(f"diffeit acquire: error: the folder {output.parent} does not exist", file=sys.stderr)
        return 2
    try:
        source = _open_source(arguments)
    except (ValueError, ConnectionError) as error:
        print(f"diffeit acquire: error: {error}", file=sys.stderr)
        return 2
    recorder, ending = None, "done"
    progress = tqdm(total=arguments.frames, unit="frame", desc=f"recording {output.name}", disable=None)
    try:
        for frame in source.frames(max_frames=arguments.frames, duration=arguments.duration):
            if recorder is None:
                recorder = hw.Recorder(
                    output, _frame_protocol(source, frame), metadata=source.description, overwrite=arguments.overwrite
                )
            statistics = source.statistics
            recorder.append(frame, statistics)
            progress.update()
            progress.set_postfix(dropped=statistics.rejected, missing=statistics.missing_frames, refresh=False)
    except hw.DeviceLost as error:
        ending = str(error)
    except KeyboardInterrupt:
        ending = "interrupted"
    except (ValueError, OSError) as error:  # a frame the recording cannot take, a file it cannot write
        print(f"diffeit acquire: error: {error}", file=sys.stderr)
        return 2
    finally:
        progress.close()
        if recorder is not None:
            recorder.append([], source.statistics)
            recorder.close()
        source.close()
    statistics = source.statistics
    print(
        f"{ending}: {statistics.frames} frames recorded in {output if recorder else 'nothing (no frame arrived)'}; "
        f"rejected {statistics.rejected} ({_kinds(statistics)}), missing {statistics.missing_frames} by the "
        f"counter, {statistics.discarded_bytes} bytes discarded, {statistics.reconnects} reconnections"
    )
    return 0 if recorder is not None else 1


def _kinds(statistics: hw.DropStatistics) -> str:
    counts = [f"{kind} {getattr(statistics, kind)}" for kind in statistics.REJECTION_KINDS if getattr(statistics, kind)]
    return ", ".join(counts) or "none"


def _live(arguments: argparse.Namespace) -> int:
    import hw

    if arguments.batch < 1 or arguments.reference_frames < 1:
        print("diffeit live: error: --batch and --reference-frames must be at least 1", file=sys.stderr)
        return 2
    if not arguments.colour_limit > 0:
        print(f"diffeit live: error: --colour-limit must be positive; got {arguments.colour_limit}", file=sys.stderr)
        return 2
    if not arguments.dead_band >= 0:
        print(f"diffeit live: error: --dead-band must be >= 0; got {arguments.dead_band}", file=sys.stderr)
        return 2
    try:
        settings = ModelSettings.from_arguments(arguments, methods=_LIVE_METHODS, hyperparameter="auto")
        skin = _skin_calibration(arguments)  # first: it refuses --memory with it before the fit is read
        fit = _memory_fit(arguments.memory)
        source = _open_source(arguments)
    except (ValueError, ConnectionError, FileNotFoundError) as error:
        print(f"diffeit live: error: {error}", file=sys.stderr)
        return 2
    viewer, shown, ending = None, 0, "done"
    reference_frames: list[np.ndarray] = []
    batch: list[hw.Frame] = []
    try:
        for frame in source.frames(max_frames=arguments.frames, duration=arguments.duration):
            if len(reference_frames) < arguments.reference_frames:
                protocol = _frame_protocol(source, frame)
                if skin is not None and not reference_frames:
                    _check_calibration(skin, protocol)
                reference_frames.append(frame.values)
                continue
            if viewer is None:
                reference = _undamaged(np.array(reference_frames))
                _touched_reference_said(reference, skin)
                viewer = _LiveViewer(
                    protocol,
                    settings,
                    arguments.png,
                    reference,
                    fit,
                    dead_band=arguments.dead_band,
                    colour_limit=arguments.colour_limit,
                    calibration=skin,
                    touches=arguments.touches,
                )
            batch.append(frame)
            if len(batch) == arguments.batch:
                shown += viewer.show(batch)
                batch = []
    except hw.DeviceLost as error:
        ending = str(error)
    except KeyboardInterrupt:
        ending = "interrupted"
    except ValueError as error:
        print(f"diffeit live: error: {error}", file=sys.stderr)
        return 2
    finally:
        source.close()
    if batch:  # the last, partial batch: also when the device went away
        shown += viewer.show(batch)
    where = f"; the latest image is in {arguments.png}" if viewer is not None and viewer.headless and shown else ""
    corrected = " and corrected for memory" if fit is not None else ""
    noted = "" if viewer is None else viewer.stream_note()
    print(f"{ending}: {shown} frames reconstructed{corrected}, {source.statistics.rejected} rejected{where}{noted}")
    nonfinite = viewer.nonfinite if viewer is not None else []
    if nonfinite:
        from .._messages import name_indices

        print(
            f"diffeit live: {len(nonfinite)} of {shown} images not finite, imaged frames {name_indices(nonfinite)} "
            "(counted from 0 after the reference frames): not drawn",
            file=sys.stderr,
        )
    return 0 if shown and not nonfinite else 1


# What a stream's values are: readings in the protocol's order and sign (hw.frame), as
# `diffeit.io.Recording.readings` names them.
_STREAM_READINGS = "signed"


def _skin_calibration(arguments: argparse.Namespace) -> SkinCalibration | None:
    """The calibration `--calibration` names, or None; ValueError for options it excludes, a
    file that is not one, or one for another protocol (when --protocol declares the stream's)
    or kind of readings than the stream's."""
    if arguments.calibration is None:
        return None
    if arguments.memory is not None:
        raise ValueError("--calibration and --memory each bring a model to image at: give one")
    options = {"h": "--h", "background": "--background", "contact_impedance": "--contact-impedance"}
    given = [option for name, option in options.items() if getattr(arguments, name) is not None]
    if given:
        names = ", ".join(given)
        raise ValueError(f"a calibration brings its model (mesh, level, contact impedances): give no {names}")
    from ..calibration import load

    calibration = load(arguments.calibration)
    declared = _protocol(arguments.protocol, arguments.electrodes)
    if declared is None and arguments.text:  # text lines without --protocol are adjacent ones
        declared = _protocol("adjacent", arguments.electrodes)
    _check_calibration(calibration, declared)  # before the device streams; the frames' protocol at the first
    return calibration


def _check_calibration(calibration: SkinCalibration, protocol: Protocol | None) -> None:
    """ValueError for a calibration of another kind of readings than a stream's (signed) or,
    when `protocol` is known, of another protocol."""
    if calibration.readings != _STREAM_READINGS:
        raise ValueError(
            f"the calibration is for {calibration.readings} readings; the device's frames are {_STREAM_READINGS} "
            "readings (in the protocol's order and sign)"
        )
    if protocol is not None and calibration.protocol != protocol:
        mine, theirs = calibration.protocol, protocol
        if (mine.n_electrodes, mine.n_measurements) == (theirs.n_electrodes, theirs.n_measurements):
            which = f"other drives and measurements on the same {mine.n_electrodes} electrodes"
        else:
            which = (
                f"{mine.n_electrodes} electrodes and {mine.n_measurements} readings; the frames' has "
                f"{theirs.n_electrodes} and {theirs.n_measurements}"
            )
        raise ValueError(f"the calibration is for another protocol than the frames' ({which})")


def _memory_fit(path: str | None) -> JointFit | None:
    """The joint fit `--memory` names, or None."""
    if path is None:
        return None
    from ..fit import load

    return load(path)


class _LiveViewer:
    """One-step reconstruction of batches of frames against the mean of the `reference` frames
    (R, M), shown in a window or saved as a PNG, on a fixed colour scale (+-`colour_limit`).

    Without a joint fit: the model is calibrated to the reference
    (`diffeit.calibration.calibrate_to_reference`: the level and unit, the orientation and drive
    sign, broken readings masked; its summary is printed), the hyperparameter "auto" is the noise
    figure's (the frames to come are unknown), and the viewer shows dsigma/sigma at the calibrated
    level. With a joint fit (`--memory`): the images are linearised at the fit's background and
    contact impedances, taken relative to the background, and corrected for the skin's memory
    frame by frame (`diffeit.fit.correct_memory_step`, from a rested skin at the first imaged
    frame, the state kept between batches, a dead band of `dead_band` standard deviations of the
    image noise, `diffeit.touch.image_noise`); the viewer shows the memoryless stimulus dsigma/sigma.

    With a skin calibration (`calibration`, `diffeit calibrate`'s): no calibration to the
    reference; the images are made at the calibration's model and level, the reference mapped
    by its `signed`, at its hyperparameter when "auto" asks and it has one.

    With `touches`: each frame's touches are read from its image and printed, a line a frame
    beside its image's peak (`diffeit.touch.LiveTouches`: `diffeit.touches`'s rule, the
    calibration's position map, polarity and ringing; where the calibration knows its readings'
    noise, its voltage test, and each frame read against the rest anchor in force, carried
    from batch to batch; a frame the rule takes for what the last touch left says so; a frame
    whose differences exceed half the reference is said damaged and not read).

    With 6 or more reference frames, the skin's drift (every reading moving with a common gain:
    a hydrogel drying, a board warming) is followed and each frame divided by its gain before
    it is imaged (`diffeit.calibration.LiveDrift`); `stream_note` gives the gains' range.

    An electrode off the skin (half its readings changed by more than half, the others not)
    has the readings on it held in that frame, and in every frame once it has been off in 3
    (`diffeit.calibration.LiveLost`): neither the drift nor the touches' tests read the loss.
    Once it is lost, the images are made from the other readings alone (the reconstruction
    matrix made again on them, as `diffeit.reconstruct` masks them; with `--memory`, at the
    held readings). A warning says when it is lost, a frame's touch line that readings were
    held, and `stream_note` in how many frames.

    The solves are direct (a matrix product, a closed-form memory step): what fails is a
    non-finite image (overflowing readings, a degenerate memory). `nonfinite` lists those
    frames (their index among the frames imaged, from 0); they are not drawn, their count is in
    the title, no touches are read from them, and they do not enter the memory state."""

    def __init__(
        self,
        protocol: Protocol,
        settings: ModelSettings,
        png: str,
        reference: np.ndarray,
        fit: JointFit | None = None,
        *,
        dead_band: float = DEAD_BAND,
        colour_limit: float = COLOUR_LIMIT,
        calibration: SkinCalibration | None = None,
        touches: bool = False,
    ) -> None:
        import matplotlib.pyplot as plt

        if calibration is not None and fit is not None:
            raise ValueError("a skin calibration and a joint fit each bring a model to image at: give one")
        self.mesh = settings.unit_disc(protocol.n_electrodes) if calibration is None else calibration.model.mesh
        self.fit = fit
        self.colour_limit = colour_limit
        self.imaged = 0
        self.nonfinite: list[int] = []
        self.touches = touches
        self.skin = calibration
        self.start_time: float | None = None  # the host time of the first frame imaged
        from ..calibration import LiveDrift, LiveLost

        self.drift = LiveDrift.of(reference)  # None for fewer than 6 reference frames
        self.recorded_reference = reference.mean(axis=0)  # as recorded: a board's stream moves its readings
        self.lost = LiveLost.of(self.recorded_reference, protocol)
        self.held_frames = 0  # frames with an electrode off, the readings on it held
        self.gains: list[float] = []  # every imaged frame's common gain, taken out
        from ..touch import _one_step_noise, image_noise

        # Where the readings' noise is known (the calibration's, or 6 or more reference frames'),
        # the touches are found on the image divided by its own noise, as `diffeit.touches` does.
        self.image_noise = None
        if fit is None:
            from ..reconstruction import _reading_noise

            self._calibrate(protocol, settings, reference, calibration)
            self.every_reading = self.solver  # made again on the readings kept when an electrode is lost
            self.kept = np.ones(len(self.reference), bool)  # of the calibration's readings (`signed`)
            self.reading_noise = _reading_noise(self.calibration, reference) if touches else None
            self.image_noise = _one_step_noise(self.solver, self.reading_noise, self.calibration.background)
        else:
            import equinox as eqx

            from ..fit import correct_memory_step
            from ._fit import fitted_one_step

            self.reference = reference.mean(axis=0)
            self.solver = fitted_one_step(fit, self.mesh, protocol, settings)
            matrix = np.asarray(self.solver.matrix)  # white reading noise at the fit's data scale (volts)
            scale = np.full(matrix.shape[1], fit.settings.data_scale)
            self.tolerance = dead_band * image_noise(matrix, scale, fit.background)
            self.step = eqx.filter_jit(correct_memory_step)
            self.state = None
        self.live_touches = None  # the touches' state, carried from batch to batch
        if touches:
            from ..touch import LiveTouches

            mean = reference.mean(axis=0)
            self.live_touches = LiveTouches.of(self.mesh, calibration, mean, len(reference), self.image_noise)
        # Agg is what matplotlib falls back to without a display: then write PNGs instead.
        self.headless = plt.get_backend().lower() == "agg"
        self.png = png
        self.figure, self.axes = plt.subplots(figsize=(5, 5))
        self.axes.set_aspect("equal")
        self.axes.set_axis_off()
        if not self.headless:
            plt.ion()
            plt.show()

    def _calibrate(
        self, protocol: Protocol, settings: ModelSettings, reference: np.ndarray, skin: SkinCalibration | None
    ) -> None:
        """The calibrated model and its solver (class docstring); prints what the calibration found."""
        from ..calibration import calibrate_to_reference
        from ..inverse import CONTACT_IMPEDANCE_SPREAD, OneStep

        if skin is None:
            calibration = calibrate_to_reference(
                settings.model(self.mesh, protocol), reference, background=settings.background
            )
        else:
            _check_calibration(skin, protocol)
            calibration = skin
        self.calibration = calibration
        self.reference = calibration.signed(reference.mean(axis=0))
        model, level = calibration.model, calibration.background
        if skin is not None and settings.hyperparameter == "auto" and skin.hyperparameter is not None:
            # The position map was fitted on images made at it (as diffeit reconstruct does).
            hyperparameter, chosen = float(skin.hyperparameter), "the calibration's"
        else:
            hyperparameter = settings.hyperparameter_at(model, level)
            chosen = "noise figure" if settings.hyperparameter == "auto" else "given"
        # Each contact free to drift, as `diffeit reconstruct` images (at the spread a position map was fitted at).
        self.solver = OneStep(
            model,
            prior=settings.prior,
            hyperparameter=hyperparameter,
            background=level,
            contact_impedance_spread=CONTACT_IMPEDANCE_SPREAD if skin is None else skin.imaging_spread,
        )
        used = f"{int(calibration.used.sum())} of {len(calibration.used)} readings"
        if skin is None:
            print(
                f"calibrated to the reference: misfit {calibration.misfit:.3f}, correlation "
                f"{calibration.correlation:.3f}, orientation {calibration.orientation}, {used}; "
                f"hyperparameter {hyperparameter:.3g}"
            )
        else:
            mapped = "" if skin.position_map is None else f", position map of degree {skin.position_map.degree}"
            print(
                f"imaging at the calibration's model: level {calibration.conductivity:.4g} S/sq, {used}{mapped}; "
                f"hyperparameter {hyperparameter:.3g} ({chosen})"
            )
        for note in calibration.warnings:
            print(f"warning: {note}")

    def show(self, batch: list[hw.Frame]) -> int:
        """Reconstruct the batch (one call), draw its last image; the frames reconstructed."""
        import matplotlib.pyplot as plt

        values = np.array([frame.values for frame in batch])
        lost_before = self.lost.lost
        values, held, self.lost = self.lost.step(values)
        self.held_frames += int(held.any(axis=1).sum())
        if self.lost.lost != lost_before:
            self._say_lost(lost_before)
            if self.fit is None:
                self._image_without_lost()
        if self.drift is not None:
            values, gains, self.drift = self.drift.step(values, [_drift_time(frame) for frame in batch])
            self.gains += gains.tolist()
        if self.fit is None:
            differences = self.calibration.signed(values) - self.reference
            images = self.solver.solve(differences[:, self.kept], throw=False).value
            images = np.asarray(images) / self.calibration.background
        else:
            differences = values - self.reference
            images = np.asarray(self.solver.solve(differences, throw=False).value)
            images = self._corrected(images / np.asarray(self.fit.background), batch)
        finite = np.all(np.isfinite(images), axis=1)
        if self.touches:
            from ..calibration import glitched_frames

            # As `diffeit.reconstruct` and `diffeit.touches`: a board's glitch is not read (and
            # is passed over by the anchors).
            damaged = glitched_frames(differences, self.reference, values, self.recorded_reference)
            self._print_touches(batch, values, images, finite, damaged, held)
        self.nonfinite += (self.imaged + np.flatnonzero(~finite)).tolist()
        self.imaged += len(batch)
        image = images[-1]
        self.axes.clear()
        self.axes.set_axis_off()
        if finite[-1]:
            self.axes.tripcolor(
                *self.mesh.nodes.T,
                self.mesh.triangles,
                facecolors=image,
                cmap="RdBu_r",
                vmin=-self.colour_limit,
                vmax=self.colour_limit,
            )
            detail = f"peak {image.flat[np.argmax(np.abs(image))]:+.2f}"
        else:
            detail = "not finite: not drawn"
        counter = batch[-1].counter
        quantity = "dsigma/sigma" if self.fit is None else "memoryless stimulus dsigma/sigma"
        failures = f"\n{len(self.nonfinite)} of {self.imaged} images not finite" if self.nonfinite else ""
        self.axes.set_title(
            f"frame {counter if counter is not None else ''}: {quantity}\n"
            f"colour -{self.colour_limit:g} to +{self.colour_limit:g}, {detail}{failures}",
            fontsize=10,
        )
        if self.headless:
            self.figure.savefig(self.png, dpi=100)
        else:
            plt.pause(0.001)
        return len(batch)

    def stream_note(self) -> str:
        """What the drift's correction took out, and the readings held on electrodes off, in
        words ("" when neither)."""
        gains = np.array(self.gains)
        note = ""
        if np.any(gains != 1.0):
            note = f"; the common gain drifted, taken out: {gains.min():.4f} to {gains.max():.4f}"
        if self.held_frames:
            from .._messages import name_indices

            lost = np.array(self.lost.lost, int)
            note += f"; readings held on electrodes off in {self.held_frames} frames"
            if len(lost):
                first = name_indices(self.lost.first_off[lost])
                note += f" (electrode(s) {name_indices(lost)} lost, off from frame(s) {first})"
        return note

    def _image_without_lost(self) -> None:
        """Image from the readings on no lost electrode alone from now on, as `diffeit.reconstruct`
        masks them: the reconstruction matrix made again on them, and the images' noise with it."""
        import equinox as eqx

        from ..touch import _one_step_noise

        self.kept = ~self.lost.on_lost[self.calibration.used]
        model = self.calibration.model
        self.solver = self.every_reading.bound(model.replace(protocol=model.protocol.select(self.kept)))
        if self.reading_noise is not None:
            noise = self.reading_noise[self.kept]
            self.image_noise = _one_step_noise(self.solver, noise, self.calibration.background)
            if self.live_touches is not None:
                self.live_touches = eqx.tree_at(
                    lambda live: live.image_noise, self.live_touches, self.image_noise, is_leaf=lambda x: x is None
                )

    def _say_lost(self, before: tuple[int, ...]) -> None:
        """Warn of the electrodes lost since `before` (`diffeit.calibration.LiveLost`)."""
        from .._messages import name_indices

        new = np.array(sorted(set(self.lost.lost) - set(before)), int)
        first = name_indices(self.lost.first_off[new])
        print(
            f"warning: electrode(s) {name_indices(new)} lost, off from frame(s) {first} "
            "(half their readings changed by more than half, in 3 frames): the readings on them hold the reference's "
            "values times the frame's common gain, and images are made from the other readings alone",
            flush=True,
        )

    def _print_touches(
        self,
        batch: list[hw.Frame],
        values: np.ndarray,
        images: np.ndarray,
        finite: np.ndarray,
        damaged: np.ndarray,
        held: np.ndarray,
    ) -> None:
        """Print a line per frame of the batch: its index among the frames imaged, its time, its
        image's peak and its touches (`diffeit.touch.LiveTouches`, the state carried); frames
        whose image is not `finite`, or that are `damaged`, are not read; those with electrodes
        `held` (B, E) say so."""
        from .._messages import name_indices
        from ..touch import DAMAGED_LINE, REMAINS_NOTE

        read = finite & ~damaged
        found, left_behind, self.live_touches = self.live_touches.step(values, images, read)
        row = np.cumsum(read) - 1  # each read image's row in `found`
        for k, (frame, image) in enumerate(zip(batch, images, strict=True)):
            if self.start_time is None:
                self.start_time = frame.host_time
            when = "" if frame.host_time is None else f" (t = {frame.host_time - self.start_time:.3f} s)"
            if not finite[k]:
                text = "not finite: no touches read"
            elif damaged[k]:
                text = DAMAGED_LINE
            else:
                peak = image.flat[np.argmax(np.abs(image))]
                # A touch's line says it is what the last touch left (`Touches.lines`); so does "no touch".
                text = f"peak {peak:+.3f}; " + ("; ".join(found.lines(int(row[k]))) or "no touch")
                if left_behind[k] and not found.count[int(row[k])]:
                    text += f" {REMAINS_NOTE}"
                if held[k].any():
                    text += f" (electrode(s) {name_indices(np.flatnonzero(held[k]))} off: the readings on them held)"
            print(f"frame {self.imaged + k}{when}: {text}", flush=True)

    def _corrected(self, images: np.ndarray, batch: list[hw.Frame]) -> np.ndarray:
        """The memoryless stimulus of the relative images (B, E) of `batch`, frame by frame."""
        from ..scene import initial_state

        stimuli = []
        for image, frame in zip(images, batch, strict=True):
            now = _frame_time(frame)
            if self.state is None:
                self.state = initial_state(self.mesh.n_elements, time=now)
            # A clock that steps back (a device reset) holds the memory still rather than rewinding it.
            now = max(now, float(self.state.time))
            if not np.all(np.isfinite(image)):  # reported by `show`; it would poison the state for good
                stimuli.append(image)
                continue
            # An array, not a Python float: filter_jit would compile anew for every static time.
            time = np.float64(now)
            stimulus, self.state = self.step(self.state, image, time, self.fit.memory, self.tolerance)
            stimuli.append(np.asarray(stimulus))
        return np.array(stimuli)


def _frame_time(frame: hw.Frame) -> float:
    """A frame's time in seconds: the host's clock (every frame from a SerialSource has it), else
    the device's."""
    if frame.host_time is not None:
        return frame.host_time
    if frame.device_time is not None:
        return frame.device_time
    raise ValueError("the memory correction needs frame times; the frames carry neither a host nor a device time")


def _drift_time(frame: hw.Frame) -> float:
    """A frame's time in seconds for the drift's trend: the device's clock, whose frames are
    evenly spaced (the host's time stamps frames as they arrive, several at once), else the
    host's."""
    return frame.device_time if frame.device_time is not None else _frame_time(frame)


def _emulate_scene(arguments: argparse.Namespace) -> int:
    import hw

    from .. import Scene, simulate

    faults = _fault_rates(arguments.faults, arguments.seed)
    simulation = simulate(Scene.from_toml(arguments.scene))
    frames = np.concatenate([np.asarray(simulation.reference)[None], np.asarray(simulation.frames)])
    times = np.asarray(simulation.times)
    frame_rate = arguments.frame_rate or (1 / np.median(np.diff(times)) if len(times) > 1 else 1.0)
    protocol = simulation.protocol
    layout = hw.layout_of(protocol)
    emulator = hw.Emulator(
        frames,
        frame_rate=frame_rate,
        text=arguments.text,
        faults=faults,
        port=arguments.port,
        layout=layout,
        n_electrodes=protocol.n_electrodes if layout != hw.LAYOUT_DECLARED else 0,
        host_timeout=arguments.wait,
    )
    print(
        f"streaming {len(frames)} frames ({protocol.n_measurements} values; frame 0 the reference) at "
        f"{frame_rate:g} frames/s on {emulator.port}",
        flush=True,
    )
    emulator.start()
    try:
        emulator.wait()
    except KeyboardInterrupt:
        emulator.stop()
    log = emulator.log
    if arguments.log:
        Path(arguments.log).write_text(json.dumps([fault.__dict__ for fault in log], indent=1))
    kinds = sorted({fault.kind for fault in log})
    summary = ", ".join(f"{kind} {sum(f.kind == kind for f in log)}" for kind in kinds) or "no faults"
    print(f"done: {len(frames) - len(emulator.lost_frames)} frames sent intact; {summary}")
    return 0


def _fault_rates(text: str, seed: int) -> hw.FaultRates | None:
    """--faults "bit_flip=0.01,truncated=0.02" as FaultRates (None when empty)."""
    import hw

    if not text.strip():
        return None
    rates = {}
    for item in text.split(","):
        name, equals, value = item.partition("=")
        if not equals or name.strip() not in hw.FAULT_KINDS:
            raise ValueError(f"--faults takes kind=rate items, kinds {hw.FAULT_KINDS}; got {item!r}")
        try:
            rates[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f"--faults: {name.strip()} rate {value!r} is not a number") from None
    return hw.FaultRates(**rates, seed=seed)
