"""Fig. 5.3: the hyperparameter against the number of stimuli (one, two, three touches).

**Setup.** One, two or three equal touches (each dsigma/sigma = -0.3 over a disc of radius
0.2 R = 0.016 m, R = 0.08 m) at 0.5 R = 0.04 m from the centre, at the angles 10 deg, 130 deg and
250 deg (the first one, two or all three; 0.87 R = 0.069 m apart, centre to centre), are
simulated on a fine mesh of the skin (background 0.01 S/sq) and imaged one-step (NOSER prior) on
a coarser one, for every hyperparameter of a log-spaced grid, at medium noise (0.5 % of
RMS(V_ref) on the touched and on the reference frame; several draws, the same noise for every
number of touches, so that only the touches differ). The pattern is turned 10 deg off the
electrode at 0 deg: at 0, 120 and 240 deg the finer reconstruction mesh's image of the touch at
240 deg often splits off a single element joined to it by a corner only, inside the touch,
which counts as an artifact and raised three touches' optimal hyperparameter two-fold there.

**Weaker touches.** The half-amplitude threshold is half of the image's overall peak, so a touch
imaged more weakly than the others (one nearer the centre, where the skin is least sensitive)
could fall below it without being lost. Here the touches are equal and at the same radius, so
they image alike: noise-free, their peaks differ by about 5 % at most (`peak_spread`, the
smallest over the largest touch peak at the optimal hyperparameter), and a touch missing from
an image is lost to noise or merged with its neighbour, not to its position.

**The image-based optimal hyperparameter** (the definition of `hyperparameter`, for several
touches): a grid value is clean when every draw's half-amplitude image has exactly one component
per touch, each matched to its touch (`diffeit.metrics.target_figures` with all the centres; a
component matches a touch only if its centroid lies inside the touch's disc, so that a speck far
away does not stand in for a touch merged with its neighbour), and no artifact. For one touch
the clean values run from a lowest one up to (nearly) the grid's end; for several touches they
stop too, where the hyperparameter is so large that the blurred touches join into one
component. The clean range is the longest run of consecutive clean grid values (at least three; the rule
of `hyperparameter`, `experiments._study.clean_range`); the optimal
hyperparameter is its lower end (the sharpest image without artifacts) and the merge limit its
upper end. Beside them: GCV and the L-curve's corner (`diffeit.inverse.select_hyperparameter`)
of all the draws together.

**Outputs.** `stimuli_images.csv` (every image's matched touches, artifacts, components and
weakest over strongest touch peak), `stimuli_optimal.csv` (per number of touches: the optimal
hyperparameter, the merge limit, GCV, L-curve, the noise-free peak spread),
`stimuli_optimal.png` (the choices against the number of touches, the clean range shaded),
`stimuli_clean.png` (the fraction of clean draws against the hyperparameter),
`stimuli_images.png` (images of one, two and three touches across hyperparameters).

**Finding asserted:** with more touches the hyperparameter must come down. The clean range
closes from above: two or three touches merge at a hyperparameter (the merge limit, about 1)
less than half of where one touch's clean range ends; and GCV and the L-curve choose smaller
values for each touch added (the data carry more signal over the same noise). The optimal
hyperparameter, the lower end, is set by the noise, the same for every number of touches: it
shows no consistent shift (reported: within a factor of 2 of one touch's, either way from one
set of draws to another).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm.auto import tqdm

import diffeit as de
from diffeit.inverse import LinearisedProblem, select_hyperparameter
from diffeit.inverse.linearised import regularised_inverse

from ._study import (
    BACKGROUND,
    NOISE_LEVELS,
    RADIUS,
    Findings,
    Study,
    clean_range,
    disc_change,
    draw_image,
    is_clean,
    model,
    noisy,
    save_figure,
    skin,
    write_table,
)

ANGLES = (10.0, 130.0, 250.0)  # degrees; n touches take the first n
CENTRES = [(0.5 * RADIUS * np.cos(np.radians(a)), 0.5 * RADIUS * np.sin(np.radians(a))) for a in ANGLES]
TARGET_RADIUS = 0.2 * RADIUS
AMPLITUDE = -0.3
NOISE = "medium"
COUNTS = (1, 2, 3)
# Several touches' merge limit lies below one touch's clean range's end by at least this factor.
MERGE_FACTOR = 2.0
# Hyperparameters of the image figure's columns: too small (noise), working, near and past merging.
SHOWN = (0.02, 0.2, 1.0, 3.2)


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    hyperparameters = np.logspace(-2, 1, 31 if small else 61)
    seeds = range(8 if small else 16)
    data_mesh, mesh = (skin(0.08), skin(0.14)) if small else (skin(0.04), skin(0.08))
    data_model, reconstruction = model(data_mesh), model(mesh)
    percent = NOISE_LEVELS[NOISE]
    problem = LinearisedProblem(reconstruction, "noser", BACKGROUND)
    inverses = [regularised_inverse(problem, value) for value in hyperparameters]
    reference = np.asarray(data_model.measure(np.full(data_mesh.n_elements, BACKGROUND)))
    # The same draws for every number of touches: only the touches differ between them.
    noise = np.array(
        [
            noisy(0 * reference, reference, percent, 2 * s) - noisy(0 * reference, reference, percent, 2 * s + 1)
            for s in seeds
        ]
    )

    rows, optimal_rows, clean_fractions, shown_images = [], [], {}, {}
    for count in tqdm(COUNTS, desc="stimuli study", disable=not progress):
        centres = CENTRES[:count]
        touched = np.asarray(
            data_model.measure(BACKGROUND * (1 + disc_change(data_mesh, centres, TARGET_RADIUS, AMPLITUDE)))
        )
        clean_difference = touched - reference
        differences = clean_difference + noise
        data = differences / problem.data_scale
        fractions = np.zeros(len(hyperparameters))
        for k, (value, inverse) in enumerate(zip(hyperparameters, inverses, strict=True)):
            images = data @ inverse.T  # dsigma / sigma, (seeds, E)
            for seed, image in zip(seeds, images, strict=True):
                figures = de.metrics.target_figures(mesh, image, centres, max_distance=TARGET_RADIUS)
                clean = is_clean(figures)
                fractions[k] += clean / len(seeds)
                rows.append(
                    {
                        "touches": count,
                        "hyperparameter": float(value),
                        "seed": seed,
                        "matched": int(figures.matched.sum()),
                        "artifacts": figures.n_artifacts,
                        "components": figures.components.count,
                        "clean": int(clean),
                        "peak_ratio": _peak_spread(figures.peak),
                    }
                )
            if value in _nearest(hyperparameters, SHOWN):
                shown_images[count, float(value)] = images[0]
        clean_fractions[count] = fractions
        lower, upper = clean_range(fractions == 1.0)
        optimal = float(hyperparameters[lower]) if lower is not None else float("nan")
        merge_limit = float(hyperparameters[upper]) if upper is not None else float("nan")
        spread = float("nan")
        if lower is not None:
            noise_free = (clean_difference / problem.data_scale) @ inverses[lower].T
            spread = _peak_spread(de.metrics.target_figures(mesh, noise_free, centres, max_distance=TARGET_RADIUS).peak)
        chosen = {
            method: float(
                select_hyperparameter(
                    reconstruction, differences, method, background=BACKGROUND, throw=False, problem=problem
                ).value
            )
            for method in ("gcv", "lcurve")
        }
        optimal_rows.append(
            {
                "touches": count,
                "optimal": optimal,
                "merge_limit": merge_limit,
                "grid_end": float(hyperparameters[-1]),
                "gcv": chosen["gcv"],
                "lcurve": chosen["lcurve"],
                "peak_spread": spread,
            }
        )

    files = [
        write_table(folder / "stimuli_images.csv", rows),
        write_table(folder / "stimuli_optimal.csv", optimal_rows),
        _plot_optimal(folder / "stimuli_optimal.png", optimal_rows),
        _plot_clean(folder / "stimuli_clean.png", hyperparameters, clean_fractions, optimal_rows),
        _plot_images(folder / "stimuli_images.png", mesh, shown_images),
    ]
    column = {name: [row[name] for row in optimal_rows] for name in optimal_rows[0]}
    merge = column["merge_limit"]
    closes = bool(max(merge[1:]) * MERGE_FACTOR <= merge[0])
    automatic_falls = bool(np.all(np.diff(column["gcv"]) < 0) and np.all(np.diff(column["lcurve"]) < 0))
    comes_down = closes and automatic_falls
    lower_shift = [float(v / column["optimal"][0]) for v in column["optimal"]]

    def listed(name: str) -> str:
        return ", ".join(f"{n}: {v:.3g}" for n, v in zip(COUNTS, column[name], strict=True))

    statements = [
        f"image-based optimal hyperparameter (lower end of the clean range) by number of touches: {listed('optimal')}",
        f"merge limit (upper end of the clean range; grid end {hyperparameters[-1]:g}): {listed('merge_limit')}",
        f"GCV: {listed('gcv')}; L-curve: {listed('lcurve')}",
        f"noise-free weakest over strongest touch peak at the optimal hyperparameter: {listed('peak_spread')}",
        "optimal hyperparameter over one touch's: "
        + ", ".join(f"{n}: {v:.2f}" for n, v in zip(COUNTS, lower_shift, strict=True)),
        "with more touches the hyperparameter must come down: the clean range closes from above (touches merge) "
        "and GCV and the L-curve fall"
        if comes_down
        else "the hyperparameter does NOT come down with more touches as asserted",
    ]
    return Findings(
        values={
            "touches": list(COUNTS),
            "optimal": column["optimal"],
            "merge_limit": column["merge_limit"],
            "gcv": column["gcv"],
            "lcurve": column["lcurve"],
            "peak_spread": column["peak_spread"],
            "closes_from_above": closes,
            "automatic_choices_fall": automatic_falls,
            "optimal_over_one_touch": lower_shift,
            "comes_down": comes_down,
            "table": optimal_rows,
        },
        statements=tuple(statements),
        files=tuple(files),
    )


def _touches(count: int) -> str:
    return f"{count} touch" + ("es" if count > 1 else "")


def _peak_spread(peaks: np.ndarray) -> float:
    """The weakest matched touch peak over the strongest (1: equal); NaN if a touch is unmatched."""
    magnitudes = np.abs(peaks)
    return float(magnitudes.min() / magnitudes.max()) if np.all(np.isfinite(magnitudes)) else float("nan")


def _nearest(grid: np.ndarray, values: tuple[float, ...]) -> list[float]:
    return [float(grid[np.argmin(np.abs(np.log(grid / v)))]) for v in values]


def _plot_optimal(path: Path, rows: list[dict]) -> Path:
    figure, ax = plt.subplots(figsize=(6, 4))
    counts = [r["touches"] for r in rows]
    lower, upper = [r["optimal"] for r in rows], [r["merge_limit"] for r in rows]
    ax.fill_between(counts, lower, upper, color="0.85", label="clean range (every draw)")
    ax.semilogy(counts, lower, "o-", label="image-based optimal (lower end)")
    ax.semilogy(counts, upper, "^-", label="merge limit (upper end)")
    ax.semilogy(counts, [r["gcv"] for r in rows], "s:", label="GCV")
    ax.semilogy(counts, [r["lcurve"] for r in rows], "d--", label="L-curve")
    ax.set_xticks(counts)
    ax.set_xlabel("number of touches")
    ax.set_ylabel("hyperparameter")
    ax.set_title("Hyperparameter against the number of stimuli (medium noise)")
    ax.legend(fontsize=8)
    return save_figure(figure, path)


def _plot_clean(path: Path, hyperparameters: np.ndarray, fractions: dict, rows: list[dict]) -> Path:
    figure, ax = plt.subplots(figsize=(6, 4))
    for count, row in zip(COUNTS, rows, strict=True):
        (line,) = ax.semilogx(hyperparameters, fractions[count], marker="o", markersize=3, label=_touches(count))
        ax.axvline(row["optimal"], color=line.get_color(), linestyle=":", linewidth=1)
    ax.set_xlabel("hyperparameter")
    ax.set_ylabel("fraction of draws clean")
    ax.set_title("One component per touch and no artifact (dotted: optimal)")
    ax.legend()
    return save_figure(figure, path)


def _plot_images(path: Path, mesh, images: dict) -> Path:
    values = sorted({value for _, value in images})
    figure, axes = plt.subplots(len(COUNTS), len(values), figsize=(3 * len(values), 2.6 * len(COUNTS)), squeeze=False)
    for row, count in zip(axes, COUNTS, strict=True):
        for ax, value in zip(row, values, strict=True):
            draw_image(
                ax, mesh, images[count, value], CENTRES[:count], TARGET_RADIUS, f"{_touches(count)}, hp {value:.3g}"
            )
    figure.suptitle("One-step NOSER images of -30% touches at 0.5 R, medium noise (circles: the truth)")
    return save_figure(figure, path, dpi=80)


STUDY = Study(
    name="stimuli",
    figure="5.3",
    title="the hyperparameter against the number of stimuli",
    run=run,
)
