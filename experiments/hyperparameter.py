"""Fig. 5.2: the hyperparameter against noise and background conductivity.

**Setup.** A touch (dsigma/sigma = -0.3 over a disc of radius 0.2 R at (0.5 R, 0), R = 0.08 m)
is simulated on a fine mesh of the skin and imaged one-step (NOSER prior) on a coarser one,
for every hyperparameter of a log-spaced grid, at each noise level (percent of RMS(V_ref),
`NOISE_LEVELS`; several seeded draws) and background (0.001, 0.01 and 0.02 S/sq).

**The image-based optimal hyperparameter** (defined here, `experiments._study.clean_range`; the
dissertation chose it by eye): the lower end of the longest run, at least three values long, of
grid values (quarter-decade steps in the small mode, tenth-decade in the full one) at which
every draw's half-amplitude image is one component at the touch and nothing else (no
artifact). Smaller values sharpen the image until
it breaks up into blobs of noise; very large ones (about 8 and more) blur it into the sheet's
smoothest mode, whose far lobe passes half the peak again. Beside it: GCV and the
L-curve's corner (`diffeit.inverse.select_hyperparameter`) of all the draws together.

**Outputs.** `hyperparameter_images.csv` (every image's artifact count, position error,
correlation with the truth), `hyperparameter_optimal.csv` (the three choices per background
and noise), `hyperparameter_artifacts.png` (artifacts against the hyperparameter, the 5.2
count), `hyperparameter_optimal.png` (the optimal hyperparameter against noise per
background), `hyperparameter_images.png` (images across hyperparameters and noise).

**Finding asserted:** the optimal hyperparameter rises with noise.
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
from diffeit.plotting import plot_elements

from ._study import (
    NOISE_LEVELS,
    RADIUS,
    Findings,
    Study,
    clean_range,
    disc_change,
    is_clean,
    model,
    noisy,
    save_figure,
    skin,
    write_table,
)

CENTRE = (0.5 * RADIUS, 0.0)
TARGET_RADIUS = 0.2 * RADIUS
AMPLITUDE = -0.3


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    backgrounds = (0.01,) if small else (0.001, 0.01, 0.02)
    noises = ("low", "medium", "high") if small else tuple(NOISE_LEVELS)
    hyperparameters = np.logspace(-4, 1, 21 if small else 51)
    seeds = range(2 if small else 5)
    data_mesh, mesh = (skin(0.08), skin(0.14)) if small else (skin(0.04), skin(0.08))
    data_model, reconstruction = model(data_mesh), model(mesh)
    truth = disc_change(mesh, [CENTRE], TARGET_RADIUS, AMPLITUDE)

    rows, optimal_rows, kept_images = [], [], {}
    cases = [(b, n) for b in backgrounds for n in noises]
    for background, noise in tqdm(cases, desc="hyperparameter study", disable=not progress):
        reference = np.asarray(data_model.measure(np.full(data_mesh.n_elements, background)))
        touched = np.asarray(
            data_model.measure(background * (1 + disc_change(data_mesh, [CENTRE], TARGET_RADIUS, AMPLITUDE)))
        )
        percent = NOISE_LEVELS[noise]
        differences = np.array(
            [noisy(touched, reference, percent, 2 * s) - noisy(reference, reference, percent, 2 * s + 1) for s in seeds]
        )
        problem = LinearisedProblem(reconstruction, "noser", background)
        data = differences / problem.data_scale
        clean = np.ones(len(hyperparameters), bool)
        for k, value in enumerate(hyperparameters):
            images = data @ regularised_inverse(problem, value).T  # dsigma / sigma, (seeds, E)
            for seed, image in zip(seeds, images, strict=True):
                figures = de.metrics.target_figures(mesh, image, [CENTRE])
                clean[k] &= is_clean(figures)
                rows.append(
                    {
                        "background": background,
                        "noise": noise,
                        "noise_percent": percent,
                        "hyperparameter": float(value),
                        "seed": seed,
                        "artifacts": figures.n_artifacts,
                        "position_error_m": float(figures.position_error[0]),
                        "correlation": de.metrics.correlation(mesh, truth, image),
                        "peak": float(figures.peak[0]),
                    }
                )
            if background == 0.01:
                kept_images[noise, k] = images[0]
        lower, _ = clean_range(clean)
        optimal = float(hyperparameters[lower]) if lower is not None else float("nan")
        chosen = {}
        for method in ("gcv", "lcurve"):
            selection = select_hyperparameter(
                reconstruction, differences, method, background=background, throw=False, problem=problem
            )
            chosen[method] = float(selection.value)
        optimal_rows.append(
            {
                "background": background,
                "noise": noise,
                "noise_percent": percent,
                "optimal": optimal,
                "gcv": chosen["gcv"],
                "lcurve": chosen["lcurve"],
            }
        )

    files = [
        write_table(folder / "hyperparameter_images.csv", rows),
        write_table(folder / "hyperparameter_optimal.csv", optimal_rows),
        _plot_artifacts(folder / "hyperparameter_artifacts.png", rows, noises),
        _plot_optimal(folder / "hyperparameter_optimal.png", optimal_rows, backgrounds),
        _plot_images(folder / "hyperparameter_images.png", mesh, kept_images, noises, hyperparameters),
    ]
    by_noise = {
        background: [next(r["optimal"] for r in optimal_rows if r["background"] == background and r["noise"] == n)
                     for n in noises if NOISE_LEVELS[n] > 0]
        for background in backgrounds
    }  # fmt: skip
    rises = all(np.all(np.diff(values) >= 0) and values[-1] > values[0] for values in by_noise.values())
    statements = [
        f"background {background:g} S/sq: optimal hyperparameter "
        + ", ".join(f"{n} {v:.3g}" for n, v in zip([n for n in noises if NOISE_LEVELS[n] > 0], values, strict=True))
        for background, values in by_noise.items()
    ]
    statements.append(
        "the optimal hyperparameter rises with noise"
        if rises
        else "the optimal hyperparameter does NOT rise with noise"
    )
    return Findings(
        values={
            "optimal": {str(b): v for b, v in by_noise.items()},
            "rises_with_noise": bool(rises),
            "table": optimal_rows,
        },
        statements=tuple(statements),
        files=tuple(files),
    )


def _plot_artifacts(path: Path, rows: list[dict], noises: tuple[str, ...]) -> Path:
    figure, ax = plt.subplots(figsize=(6, 4))
    for noise in noises:
        chosen = [r for r in rows if r["noise"] == noise and r["background"] == 0.01]
        values = sorted({r["hyperparameter"] for r in chosen})
        mean = [np.mean([r["artifacts"] for r in chosen if r["hyperparameter"] == v]) for v in values]
        ax.semilogx(values, mean, marker="o", markersize=3, label=f"{noise} ({chosen[0]['noise_percent']:g}%)")
    ax.set_xlabel("hyperparameter (unit-free)")
    ax.set_ylabel("artifacts (extra half-amplitude blobs), mean over draws")
    ax.set_title("Artifacts against the hyperparameter (0.01 S/sq)")
    ax.legend()
    return save_figure(figure, path)


def _plot_optimal(path: Path, rows: list[dict], backgrounds: tuple[float, ...]) -> Path:
    figure, ax = plt.subplots(figsize=(6, 4))
    for background in backgrounds:
        chosen = [r for r in rows if r["background"] == background and r["noise_percent"] > 0]
        noise = [r["noise_percent"] for r in chosen]
        (line,) = ax.loglog(
            noise, [r["optimal"] for r in chosen], marker="o", label=f"image-based, {background:g} S/sq"
        )
        ax.loglog(
            noise, [r["lcurve"] for r in chosen], "--", color=line.get_color(), label=f"L-curve, {background:g} S/sq"
        )
        ax.loglog(noise, [r["gcv"] for r in chosen], ":", color=line.get_color(), label=f"GCV, {background:g} S/sq")
    ax.set_xlabel("noise, % of RMS(V_ref)")
    ax.set_ylabel("hyperparameter")
    optimal = {b: [r["optimal"] for r in rows if r["background"] == b] for b in backgrounds}
    same = len(backgrounds) > 1 and all(np.allclose(v, optimal[backgrounds[0]]) for v in optimal.values())
    note = "\n(the backgrounds' curves coincide: the hyperparameter is unit-free)" if same else ""
    ax.set_title("Optimal hyperparameter against noise" + note, fontsize=10)
    ax.legend(fontsize=7)
    return save_figure(figure, path)


def _plot_images(path: Path, mesh, images: dict, noises: tuple[str, ...], hyperparameters: np.ndarray) -> Path:
    columns = np.unique(np.linspace(0, len(hyperparameters) - 1, 5).round().astype(int))
    figure, axes = plt.subplots(len(noises), len(columns), figsize=(3 * len(columns), 2.6 * len(noises)), squeeze=False)
    for row, noise in zip(axes, noises, strict=True):
        for ax, k in zip(row, columns, strict=True):
            plot_elements(ax, mesh, images[noise, k], label="dsigma/sigma", electrodes=False)
            ax.set_title(f"{noise}, hp {hyperparameters[k]:.3g}", fontsize=8)
    figure.suptitle("One-step NOSER images of a -30% touch at (0.5 R, 0), 0.01 S/sq")
    return save_figure(figure, path, dpi=80)


STUDY = Study(
    name="hyperparameter",
    figure="5.2",
    title="the hyperparameter against noise and background conductivity",
    run=run,
)
