"""Calibrating a simulated skin from a calibration session: the median position error of touches
read on presses the calibration did not use, against the number of labelled presses.

    python benchmarks/calibration.py [--seeds 5] [--presses 0 10 25 50 100] [--test 60] [--reach 0.8]

The skin: a disc of radius 80 mm with 16 electrodes, opposition drive, a board that reports
magnitudes only, and the artefacts real boards have (`diffeit.scene` effects): electrode positions
off by up to 5 degrees, a readout that mixes in the source electrode's and the far electrode's
potentials with weights up to 0.3 of the pair's, gains per reading of +-20%, contact impedances
spread 3x, a sheet 30% more conductive on one side than the other, medium noise. A session
holds 20 untouched frames, then presses (radius 10 mm, dsigma/sigma = -0.3) at random places
within 80% of the radius (`--reach`), one frame each. For each seed the calibration uses the first K presses
of the session (K = 0: the reference alone) and the touches are read (`de.reconstruct(...,
calibration=...)`, `de.touches`) on `--test` other presses, against:

- **nominal**: `de.reconstruct` and `de.touches` with their defaults (no calibration; the
  test recording starts with the session's untouched frames, its reference);
- **true model**: the calibration's pipeline with the truth's electrode positions, readout,
  gains, contact impedances and mean level put in its place (no position map), testing the
  frames for touches against its reference frames' spread as a calibration does.

Errors are medians over the test presses (a press without a touch read counts as missed and
is left out of the median; the misses are counted). Times are `de.calibrate`'s, in this process.
Beside them, the fitted model against the truth: the largest and the root-mean-square error of
an electrode centre, degrees (the calibration's shift against the true offset, both about their
mean: a common rotation of the electrodes rotates the sheet; where the positions are not
fitted, the true offsets), the errors' root mean square in units of the standard errors the
calibration reports for them (about 1 when it knows how well the data determine them; "-"
where not fitted), the largest centre error that noise alone would leave (the median over
draws of the largest of errors drawn with those standard errors, about their mean: what a fit
as well determined, free of model error, would reach; "-" where not fitted), and the largest
error of a readout mixing weight (source, sink and every offset weight, relative to the
pair's).
A median over 60 presses moves by about 10% from one session to the next, so a second table
pools the seeds: the ratio of our median error to the true model's over every seed's test
presses, with a bootstrap interval.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import MarkdownTable, skin_benchmark, write_tables

RADIUS = 0.08  # m
PRESS_RADIUS, PRESS_CHANGE = 0.01, -0.3  # m, dsigma / sigma
FRAME_RATE, REFERENCE_FRAMES = 10.0, 20
ELECTRODE_ERROR = np.deg2rad(5.0)  # the largest electrode position error, rad


def session(seed: int, n_presses: int, **options):
    """A simulated calibration session: the recording (magnitudes), the presses (labelled), and
    the truth (the scene and its artefacts); `options` are `session_scene`'s. Each press is held
    `hold` frames, labelled with their holds (start and end) when longer than a frame, else an
    instant."""
    import diffeit as de

    scene, centres, starts, offsets = session_scene(seed, n_presses, **options)
    recording = read_by_the_board(scene)
    step = 1.0 / FRAME_RATE
    held = starts + 0.5 * step
    hold = options.get("hold", 1)
    if hold > 1:  # the holds, from the first held frame's time to the last's
        held = np.stack([held, held + (hold - 1) * step], axis=1)
    return recording, de.io.Presses(centres, PRESS_RADIUS, held), {"scene": scene, "offsets": offsets}


def read_by_the_board(scene):
    """`scene` simulated and read as the benchmark's board reads it: magnitudes, in volts, the
    skin's geometry (with its mesh size) attached."""
    import diffeit as de

    recording = de.simulate(scene).to_recording()
    return de.io.Recording(
        frames=np.abs(np.asarray(recording.frames)),
        times=recording.times,
        protocol=recording.protocol,
        geometry={**dict(scene.skin.geometry), "h": scene.skin.h},
        readings="magnitude",
        voltage_unit="V",
    )


def session_scene(
    seed: int,
    n_presses: int,
    *,
    hold: int = 1,
    period: int = 2,
    memory=None,
    reach: float = 0.8,
    inner: float = 0.0,
    rows: bool = False,
    contact_drift: float = 0.0,
):
    """A calibration session's scene, not simulated (`session` simulates it): the scene, the
    presses' centres (K, 2) m, their start times (K,) s, and the electrodes' offsets along the
    rim (16,) m. Each press is held `hold` frames, one every `period` frames; the presses lie
    between `inner` and `reach` of the skin's radius; with `memory` (a
    `diffeit.memory.MemoryParameters`), the skin has that memory; with `rows`, the presses come
    in rows from the bottom up (a robot's raster: the first of them cover the lower part alone);
    with `contact_drift` d, each electrode's contact impedance drifts exponentially, to a factor
    exp(u d) by the session's end, u uniform in [-1, 1] (`diffeit.scene.ContactDrift`)."""
    import diffeit as de
    from diffeit.scene import (
        Background,
        ContactDrift,
        Disc,
        ElectrodePositionError,
        MeasurementNoise,
        Noise,
        Polygon,
        Press,
        ReadingGains,
        ReadoutMixing,
        Region,
        Scene,
        Skin,
        Touch,
    )

    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n_presses)
    distance = RADIUS * np.sqrt(rng.uniform(inner**2, reach**2, n_presses))
    centres = np.stack([distance * np.cos(angle), distance * np.sin(angle)], axis=1)
    if rows:
        centres = centres[np.argsort(centres[:, 1])]
    step = 1.0 / FRAME_RATE
    starts = (REFERENCE_FRAMES + period * np.arange(n_presses)) * step - 0.5 * step
    geometry = {"kind": "disc", "radius": RADIUS, "n_electrodes": 16, "electrode_width": 0.15 * RADIUS}
    contact = 0.01 * RADIUS * np.exp(rng.uniform(-0.55, 0.55, 16))  # spread 3x
    skin = Skin(geometry=geometry, h=0.1 * RADIUS, protocol="opposite", contact_impedance=contact)
    offsets = rng.uniform(-1, 1, 16) * ELECTRODE_ERROR * RADIUS
    measurements = de.protocol.opposite(16).n_measurements
    effects = (
        ElectrodePositionError(offsets),
        ReadoutMixing.random(16, 0.3, seed=seed),
        ReadingGains.random(measurements, 0.2, seed=seed),
        MeasurementNoise(Noise.level("medium"), seed=seed),
    ) + (() if memory is None else (memory,))
    duration = (REFERENCE_FRAMES + period * n_presses) * step
    if contact_drift:  # drawn last: the sessions without it are as before
        effects += (ContactDrift(rng.uniform(-1, 1, 16) * contact_drift / duration),)
    touches = tuple(
        Touch(Disc(tuple(c), PRESS_RADIUS), PRESS_CHANGE, Press(start=s, hold=hold * step))
        for c, s in zip(centres, starts, strict=True)
    )
    right = Polygon([[0, -2 * RADIUS], [2 * RADIUS, -2 * RADIUS], [2 * RADIUS, 2 * RADIUS], [0, 2 * RADIUS]])
    background = Background(1.0, (Region(right, 1.3, 0.3 * RADIUS),))
    scene = Scene(
        skin=skin,
        background=background,
        touches=touches,
        frame_rate=FRAME_RATE,
        duration=duration,
        effects=effects,
    )
    return scene, centres, starts, offsets


def true_calibration(fitted, truth, reference: np.ndarray):
    """The calibration `fitted` with the truth's model in its place (module docstring), its
    readings' noise the spread of the `reference` frames (N, M) in its units."""
    import equinox as eqx
    import jax.numpy as jnp

    import diffeit as de
    from diffeit.readout import Readout

    scene = truth["scene"]
    protocol = fitted.protocol
    mixing = next(e for e in scene.effects if isinstance(e, de.scene.ReadoutMixing))
    gains = next(e for e in scene.effects if isinstance(e, de.scene.ReadingGains))
    readout = Readout(protocol, mixing.source, mixing.sink, mixing.offsets, gains.gains)
    mesh = scene.skin.mesh(scene.skin.h, tuple(truth["offsets"]))
    contact = np.asarray(scene.skin.contact_impedance)
    model = de.ForwardModel(mesh, readout.folded(protocol), contact)
    level = float(np.mean(np.asarray(scene.background.values_on(mesh))))
    sign = np.where(np.asarray(model.measure(jnp.full(mesh.n_elements, level))) < 0, -1.0, 1.0)
    # Every reading is used, at the mean level (not the fitted calibration's background map, in
    # its units); the noise, in the truth's units, is set once they are in place.
    true = eqx.tree_at(
        lambda c: (
            c.model,
            c.conductivity,
            c.readout,
            c.used,
            c.reading_sign,
            c.background_map,
            c.position_map,
            c.hyperparameter,
            c.noise,
        ),
        fitted,
        (model, level, readout, np.ones(protocol.n_measurements, bool), sign, None, None, None, None),
        is_leaf=lambda node: node is None,
    )
    noise = np.std(true.signed(reference), axis=0, ddof=1)
    return eqx.tree_at(lambda c: c.noise, true, noise, is_leaf=lambda node: node is None)


def touches_read(recording, calibration, solver=None):
    """The touches `de.touches` reads in `recording` at `calibration`; the images
    `de.reconstruct`'s defaults, or `solver`'s at the "auto" hyperparameter."""
    import diffeit as de

    chosen = {} if solver is None else {"solver": solver, "hyperparameter": "auto"}
    images = de.reconstruct(recording, calibration=calibration, progress=False, throw=False, **chosen)
    return de.touches(images, calibration)


def press_errors(recording, presses, found) -> np.ndarray:
    """(K,) the distance, m, between the strongest touch of `found` and each press (NaN: missed)."""
    chosen = np.array([frames[0] for frames in presses.frames(recording.times)])
    return np.linalg.norm(found.position[chosen, 0] - presses.centres, axis=1)


def errors(recording, presses, calibration, solver=None) -> np.ndarray:
    """(K,) the distance, m, between the strongest touch read and each press (NaN: missed)
    (`touches_read`)."""
    return press_errors(recording, presses, touches_read(recording, calibration, solver))


def model_errors(calibration, truth) -> tuple[np.ndarray, float | None, float]:
    """The electrode centre errors of `calibration` against the truth (module docstring), (L,)
    degrees; their root mean square in units of their reported standard errors (None where the
    positions were not fitted); and the largest mixing weight error."""
    import diffeit as de

    # About the electrodes' common rotation, which rotates the sheet (the labels' frame takes it).
    shift = np.asarray(calibration.values["electrode_positions"])
    offsets = np.asarray(truth["offsets"])
    error = (shift - shift.mean()) - (offsets - offsets.mean())
    centre = np.rad2deg(error / RADIUS)
    standard = calibration.standard_errors.get("electrode_positions")
    fitted = standard is not None and np.all(np.asarray(standard) > 0)
    in_errors = float(np.sqrt(np.mean((error / np.asarray(standard)) ** 2))) if fitted else None
    mixing = next(e for e in truth["scene"].effects if isinstance(e, de.scene.ReadoutMixing))
    readout = calibration.readout
    weight = max(
        abs(float(readout.source) - float(mixing.source)),
        abs(float(readout.sink) - float(mixing.sink)),
        float(np.max(np.abs(np.asarray(readout.offsets) - np.asarray(mixing.offsets)))),
    )
    return centre, in_errors, weight


def noise_largest(calibration, draws: int = 4000) -> float | None:
    """The largest electrode centre error, degrees, that noise alone would leave: the median
    over `draws` seeded draws of the largest of the errors drawn with the standard errors the
    calibration reports (about their mean, as `model_errors`); None where not fitted."""
    standard = calibration.standard_errors.get("electrode_positions")
    if standard is None or not np.all(np.asarray(standard) > 0):
        return None
    drawn = np.random.default_rng(0).normal(size=(draws, len(standard))) * np.rad2deg(np.asarray(standard) / RADIUS)
    return float(np.median(np.max(np.abs(drawn - drawn.mean(axis=1, keepdims=True)), axis=1)))


def cell(distance: np.ndarray) -> str:
    """The median error, mm, and the misses in brackets."""
    return f"{1e3 * np.nanmedian(distance):.1f} ({int(np.isnan(distance).sum())})"


def split(recording, presses, calibration_presses: int, test_presses: int):
    """A session's test recording (the untouched frames, then the presses after the first
    `calibration_presses`, which are left out; `de.reconstruct` takes its reference from the
    first frames) and its `test_presses` presses."""
    import diffeit as de

    after = REFERENCE_FRAMES + 2 * calibration_presses
    tested = np.r_[np.arange(REFERENCE_FRAMES), np.arange(after, recording.n_frames)]
    test = de.io.Recording(
        frames=recording.frames[tested],
        times=recording.times[tested],
        protocol=recording.protocol,
        geometry=recording.geometry,
        readings="magnitude",
    )
    return test, presses.select(np.arange(calibration_presses, calibration_presses + test_presses))


def calibration_session(recording, count: int):
    """The session's recording up to its `count`-th press (its untouched frames alone for 0)."""
    import diffeit as de

    kept = slice(0, REFERENCE_FRAMES + 2 * count)
    return de.io.Recording(
        frames=recording.frames[kept],
        times=recording.times[kept],
        protocol=recording.protocol,
        geometry=recording.geometry,
        readings="magnitude",
    )


def pooled_ratio(ours: list[np.ndarray], true: list[np.ndarray], draws: int = 2000) -> tuple[float, float, float]:
    """The ratio of the pooled medians (over every seed's test presses, misses left out) of our
    errors to the true model's, and its 95% bootstrap interval: the test presses resampled
    within each seed, both pipelines' errors at the same presses."""
    rng = np.random.default_rng(0)

    def ratio(index: list[np.ndarray]) -> float:
        mine = np.concatenate([o[i] for o, i in zip(ours, index, strict=True)])
        theirs = np.concatenate([t[i] for t, i in zip(true, index, strict=True)])
        return float(np.nanmedian(mine) / np.nanmedian(theirs))

    resampled = [ratio([rng.integers(0, len(o), len(o)) for o in ours]) for _ in range(draws)]
    low, high = np.percentile(resampled, [2.5, 97.5])
    return ratio([np.arange(len(o)) for o in ours]), float(low), float(high)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presses", type=int, nargs="+", default=[0, 10, 25, 50, 100])
    parser.add_argument("--reach", type=float, default=0.8, help="presses lie within this fraction of the radius")
    started = skin_benchmark(parser, __file__, seeds=5, test=60)
    if started is None:
        return
    options, printed = started
    import diffeit as de

    print(
        f"\nmedian position error (mm) of touches on {options.test} test presses, misses in brackets; "
        f"{options.seeds} simulated sessions (seeds 0..{options.seeds - 1})\n"
    )
    table = MarkdownTable(
        [
            "labelled presses",
            "seed",
            "nominal",
            "calibrated",
            "true model",
            "calibration time",
            "centre error, deg (largest, RMS)",
            "in standard errors (RMS)",
            "largest from noise alone, deg",
            "mixing weight error",
        ]
    )
    most = max(options.presses)
    ours_by_count: dict[int, list[np.ndarray]] = {count: [] for count in options.presses}
    true_by_seed: list[np.ndarray] = []
    for seed in range(options.seeds):
        recording, presses, truth = session(seed, most + options.test, reach=options.reach)
        reference = recording.frames[:REFERENCE_FRAMES]
        test, test_presses = split(recording, presses, most, options.test)
        nominal = errors(test, test_presses, None)
        true = None
        for count in options.presses:
            start = time.perf_counter()
            calibration = de.calibrate(
                calibration_session(recording, count), presses.select(np.arange(count)) if count else None
            )
            seconds = time.perf_counter() - start
            if true is None:
                true = errors(test, test_presses, true_calibration(calibration, truth, reference))
                true_by_seed.append(true)
            ours = errors(test, test_presses, calibration)
            ours_by_count[count].append(ours)
            centre, in_errors, weight = model_errors(calibration, truth)
            from_noise = noise_largest(calibration)
            table.row(
                [
                    str(count),
                    str(seed),
                    cell(nominal),
                    cell(ours),
                    cell(true),
                    f"{seconds:.1f} s",
                    f"{np.max(np.abs(centre)):.2f}, {np.sqrt(np.mean(centre**2)):.2f}",
                    "-" if in_errors is None else f"{in_errors:.2f}",
                    "-" if from_noise is None else f"{from_noise:.2f}",
                    f"{weight:.3f}",
                ]
            )
    print(
        "\nthe seeds pooled: the ratio of our median error to the true model's over every seed's test presses, "
        "with its 95% bootstrap interval (test presses resampled within each seed)\n"
    )
    pooled = MarkdownTable(["labelled presses", "calibrated", "true model", "ratio", "95% interval"])
    everything_true = np.concatenate(true_by_seed)
    for count, ours in ours_by_count.items():
        ratio, low, high = pooled_ratio(ours, true_by_seed)
        interval = f"{low:.2f}-{high:.2f}"
        pooled.row([str(count), cell(np.concatenate(ours)), cell(everything_true), f"{ratio:.2f}", interval])
    print()
    write_tables("calibration", printed)


if __name__ == "__main__":
    main()
