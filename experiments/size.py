"""Fig. 5.8: stimulus size.

**Setup.** Centred touches (dsigma/sigma = -0.3 over a disc about the skin's centre) of radius
0.1 R, 0.2 R, 0.5 R and a tiny one of 0.025 R (8, 16, 40 and 2 mm; R = 0.08 m) are simulated
on a fine mesh of the skin and imaged one-step (NOSER prior) on a coarser one, for every
hyperparameter of a log-spaced grid from 1 down to 0.003 (with the working points inserted),
noise-free and at low (0.1%) and medium (0.5% of RMS(V_ref)) noise, several seeded draws.
The working point is the image-based optimal hyperparameter of the hyperparameter study
(Fig. 5.2): 0.05 at low noise (also used noise-free), 0.2 at medium noise.

**Reconstructed size:** the equivalent radius sqrt(area / pi) of the half-amplitude component
matched to the touch (`diffeit.metrics.target_figures`), as a fraction of R; beside it the
image's peak dsigma/sigma and the artifacts (other half-amplitude components). The touch's
signal is the RMS of its noise-free voltage change, in percent of RMS(V_ref), to compare with
the noise levels.

**Outputs.** `size_table.csv` (every image: touch radius, noise, hyperparameter, draw,
equivalent radius, peak, position error, artifacts), `size_summary.csv` (means over the draws
and the touch's signal), `size_against_hp.png` (equivalent radius and |peak| against the
hyperparameter per touch radius, one panel per noise level; hollow markers where some draw
has artifacts), `size_images.png` (images across hyperparameters per touch radius at low
noise, and the tiny touch noise-free).

**Findings asserted:** at the working point the reconstructed radius orders with the true
radius, 0.1 R < 0.2 R < 0.5 R, noise-free and at low noise (at medium noise it is reported
only: the 0.1 R touch's signal is below that noise and its images carry artifacts). Noise-free,
the reconstructed radius of every touch up to 0.2 R shrinks as the hyperparameter decreases
(the 0.5 R touch, wider than the resolution, stays near 0.4-0.47 R); at low and medium noise
the 0.1 R and 0.2 R touches are smaller at the working point than at 1, and at 0.003 every
image has broken up into artifacts. The 0.025 R touch is imaged, noise-free, at least five
times larger than it is, with a peak under 5% of the 0.2 R touch's and about in proportion to
its area (the resolution limit: below about 0.2 R the size is lost, the peak still scales with
the area); its signal is below the low noise level, so with noise it is not seen at all.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm.auto import tqdm

import diffeit as de
from diffeit.inverse import LinearisedProblem
from diffeit.inverse.linearised import regularised_inverse
from diffeit.plotting import plot_elements

from ._study import (
    BACKGROUND,
    NOISE_LEVELS,
    RADIUS,
    Findings,
    Study,
    disc_change,
    model,
    noisy,
    save_figure,
    skin,
    write_table,
)
from .metrics import WORKING_POINTS

CENTRE = (0.0, 0.0)
SIZES = (0.025, 0.1, 0.2, 0.5)  # touch radius, fraction of R
AMPLITUDE = -0.3
NOISES = ("noise-free", "low", "medium")
WORKING = {"noise-free": WORKING_POINTS["low"], **WORKING_POINTS}
SHOWN = (1.0, 0.2, 0.05, 0.01, 0.003)  # the hyperparameters of the image panels


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    grid = np.logspace(0, np.log10(0.003), 11 if small else 21)
    hyperparameters = np.unique(np.round(np.concatenate([grid, list(WORKING.values()), SHOWN]), 12))[::-1]
    n_draws = 3 if small else 8
    data_mesh, mesh = (skin(0.08), skin(0.14)) if small else (skin(0.04), skin(0.08))
    data_model = model(data_mesh)
    reference = np.asarray(data_model.measure(np.full(data_mesh.n_elements, BACKGROUND)))
    problem = LinearisedProblem(model(mesh), "noser", BACKGROUND)
    inverses = [regularised_inverse(problem, value) for value in hyperparameters]

    rows, summary, shown = [], [], {}
    for size in tqdm(SIZES, desc="size study", disable=not progress):
        touched = np.asarray(
            data_model.measure(BACKGROUND * (1 + disc_change(data_mesh, [CENTRE], size * RADIUS, AMPLITUDE)))
        )
        signal = 100 * np.sqrt(np.mean((touched - reference) ** 2) / np.mean(reference**2))
        for noise in NOISES:
            percent = NOISE_LEVELS[noise]
            draws = range(1 if percent == 0 else n_draws)
            differences = [
                noisy(touched, reference, percent, 2 * s) - noisy(reference, reference, percent, 2 * s + 1)
                for s in draws
            ]
            data = np.array(differences) / problem.data_scale
            for value, inverse in zip(hyperparameters, inverses, strict=True):
                images = data @ inverse.T  # dsigma / sigma, (draws, E)
                chosen = []
                for draw, image in zip(draws, images, strict=True):
                    figures = de.metrics.target_figures(mesh, image, [CENTRE])
                    chosen.append(
                        {
                            "touch_radius_R": size,
                            "noise": noise,
                            "hyperparameter": float(value),
                            "draw": draw,
                            "equivalent_radius_R": float(figures.equivalent_radius[0] / RADIUS),
                            "equivalent_radius_m": float(figures.equivalent_radius[0]),
                            "peak": de.metrics.peak(image),
                            "position_error_R": float(figures.position_error[0] / RADIUS),
                            "artifacts": figures.n_artifacts,
                        }
                    )
                rows += chosen
                for panel in SHOWN:
                    if np.isclose(value, panel):
                        shown[size, noise, panel] = images[0]
                summary.append(
                    {
                        "touch_radius_R": size,
                        "noise": noise,
                        "hyperparameter": float(value),
                        "draws": len(chosen),
                        "signal_percent": float(signal),
                        "equivalent_radius_R": float(np.mean([r["equivalent_radius_R"] for r in chosen])),
                        "equivalent_radius_R_std": float(np.std([r["equivalent_radius_R"] for r in chosen])),
                        "peak": float(np.mean([r["peak"] for r in chosen])),
                        "peak_magnitude": float(np.mean([abs(r["peak"]) for r in chosen])),
                        "artifacts": float(np.mean([r["artifacts"] for r in chosen])),
                        "draws_with_artifacts": sum(r["artifacts"] > 0 for r in chosen),
                    }
                )

    files = [
        write_table(folder / "size_table.csv", rows),
        write_table(folder / "size_summary.csv", summary),
        _plot_curves(folder / "size_against_hp.png", summary),
        _plot_images(folder / "size_images.png", mesh, shown),
    ]
    values, statements = _findings(summary, hyperparameters)
    return Findings(values=values, statements=tuple(statements), files=tuple(files))


def _findings(summary: list[dict], hyperparameters: np.ndarray) -> tuple[dict, list[str]]:
    def pick(size: float, noise: str, value: float) -> dict:
        return next(
            r
            for r in summary
            if r["touch_radius_R"] == size and r["noise"] == noise and np.isclose(r["hyperparameter"], value)
        )

    def curve(size: float, noise: str) -> np.ndarray:
        return np.array([pick(size, noise, value)["equivalent_radius_R"] for value in hyperparameters])

    at_working = {n: {s: pick(s, n, WORKING[n])["equivalent_radius_R"] for s in SIZES} for n in NOISES}
    ordered = {n: bool(at_working[n][0.1] < at_working[n][0.2] < at_working[n][0.5]) for n in NOISES}
    dirty = {n: {s: pick(s, n, WORKING[n])["draws_with_artifacts"] for s in SIZES} for n in NOISES}
    # Noise-free: shrinking along the decreasing grid, up to a step of 0.01 R (the mesh's cells
    # enter and leave the half-amplitude set one at a time).
    small_sizes = [s for s in SIZES if s <= 0.2]
    shrinks = {s: bool(np.all(np.diff(curve(s, "noise-free")) <= 0.01)) for s in small_sizes}
    shrink_ratio = {s: float(curve(s, "noise-free")[0] / curve(s, "noise-free")[-1]) for s in small_sizes}
    # With noise: smaller from 1 to the working point, broken up (artifacts) at the smallest value.
    noisy_shrinks = {
        n: {
            s: bool(
                pick(s, n, hyperparameters[0])["equivalent_radius_R"] > pick(s, n, WORKING[n])["equivalent_radius_R"]
            )
            for s in (0.1, 0.2)
        }
        for n in ("low", "medium")
    }
    smallest = {n: [pick(s, n, hyperparameters[-1]) for s in SIZES] for n in ("low", "medium")}
    broken = {
        n: {r["touch_radius_R"]: r["draws_with_artifacts"] / r["draws"] for r in rows} for n, rows in smallest.items()
    }
    mean_artifacts = {n: float(np.mean([r["artifacts"] for r in rows])) for n, rows in smallest.items()}
    tiny, reference = pick(0.025, "noise-free", WORKING["noise-free"]), pick(0.2, "noise-free", WORKING["noise-free"])
    tenth = pick(0.1, "noise-free", WORKING["noise-free"])
    big = curve(0.5, "noise-free")
    values = {
        "working_points": WORKING,
        "radius_at_working_point_R": {n: {str(s): v for s, v in r.items()} for n, r in at_working.items()},
        "ordered_at_working_point": ordered,
        "draws_with_artifacts_at_working_point": {n: {str(s): v for s, v in r.items()} for n, r in dirty.items()},
        "noise_free_shrinks": {str(s): v for s, v in shrinks.items()},
        "noise_free_shrink_ratio": {str(s): v for s, v in shrink_ratio.items()},
        "noisy_shrinks_to_working_point": {n: {str(s): v for s, v in r.items()} for n, r in noisy_shrinks.items()},
        "fraction_with_artifacts_at_smallest_hp": {n: {str(s): v for s, v in r.items()} for n, r in broken.items()},
        "tiny_radius_over_true": tiny["equivalent_radius_R"] / 0.025,
        "tiny_peak": tiny["peak"],
        "tiny_peak_over_0.2R_peak": tiny["peak"] / reference["peak"],
        "tiny_peak_over_0.1R_peak": tiny["peak"] / tenth["peak"],
        "signal_percent": {str(s): pick(s, "noise-free", 1.0)["signal_percent"] for s in SIZES},
        "large_radius_range_R": [float(big.min()), float(big.max())],
    }
    statements = [
        f"{n}, hp {WORKING[n]:g}: reconstructed radius "
        + ", ".join(
            f"{s:g} R -> {v:.3f} R ({dirty[n][s]}/{pick(s, n, WORKING[n])['draws']} draws with artifacts)"
            for s, v in at_working[n].items()
        )
        + ("; 0.1 R < 0.2 R < 0.5 R" if ordered[n] else "; NOT ordered 0.1 R < 0.2 R < 0.5 R")
        for n in NOISES
    ]
    statements += [
        "noise-free, hp 1 -> "
        f"{hyperparameters[-1]:g}: the radius shrinks by "
        + ", ".join(f"{shrink_ratio[s]:.2f}x for {s:g} R" for s in small_sizes)
        + ("" if all(shrinks.values()) else " (NOT monotonically)")
        + f"; the 0.5 R touch stays at {big.min():.2f}-{big.max():.2f} R",
        f"at hp {hyperparameters[-1]:g} the images break up: "
        + "; ".join(
            f"{n} noise, artifacts in "
            + ("every image" if min(broken[n].values()) == 1 else f"{100 * min(broken[n].values()):.0f}% or more")
            + f", {mean_artifacts[n]:.1f} on average"
            for n in broken
        ),
        f"the 0.025 R touch, noise-free at hp {WORKING['noise-free']:g}: radius {tiny['equivalent_radius_R']:.3f} R "
        f"({values['tiny_radius_over_true']:.1f}x true), peak {tiny['peak']:.4f} "
        f"({100 * values['tiny_peak_over_0.2R_peak']:.1f}% of the 0.2 R touch's, "
        f"{100 * values['tiny_peak_over_0.1R_peak']:.1f}% of the 0.1 R touch's; area ratio 6.25%); its signal "
        f"{tiny['signal_percent']:.3f}% of RMS(V_ref) is below the low noise (0.1%)",
    ]
    return values, statements


def _plot_curves(path: Path, summary: list[dict]) -> Path:
    figure, axes = plt.subplots(2, len(NOISES), figsize=(5 * len(NOISES), 8), sharex=True, squeeze=False)
    colours = dict(zip(SIZES, plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False))
    for column, noise in enumerate(NOISES):
        radius_ax, peak_ax = axes[:, column]
        for size in SIZES:
            chosen = [r for r in summary if r["touch_radius_R"] == size and r["noise"] == noise]
            hp = np.array([r["hyperparameter"] for r in chosen])
            radius = np.array([r["equivalent_radius_R"] for r in chosen])
            peak = np.array([r["peak_magnitude"] for r in chosen])
            clean = np.array([r["draws_with_artifacts"] == 0 for r in chosen])
            colour = colours[size]
            for ax, y in ((radius_ax, radius), (peak_ax, peak)):
                ax.plot(hp, y, color=colour, label=f"touch {size:g} R")
                ax.plot(hp[clean], y[clean], "o", color=colour, markersize=4)
                ax.plot(hp[~clean], y[~clean], "o", markerfacecolor="none", color=colour, markersize=4)
            radius_ax.axhline(size, color=colour, linestyle="--", linewidth=0.8)
        for ax in (radius_ax, peak_ax):
            ax.set_xscale("log")
            ax.axvline(WORKING[noise], color="0.5", linestyle=":", linewidth=1)
        peak_ax.invert_xaxis()  # once: the column's axes share x
        peak_ax.set_yscale("log")
        peak_ax.axhline(-AMPLITUDE, color="k", linestyle="--", linewidth=0.8)
        radius_ax.set_title(f"{noise} ({NOISE_LEVELS[noise]:g}% of RMS(V_ref)); working point dotted", fontsize=9)
        radius_ax.set_ylabel("equivalent radius / R (dashed: true)")
        peak_ax.set_ylabel("|peak dsigma/sigma|, mean (dashed: true 0.3)")
        peak_ax.set_xlabel("hyperparameter (decreasing)")
        radius_ax.legend(fontsize=7, title="hollow: artifacts in some draw", title_fontsize=7)
    figure.suptitle("Reconstructed size of centred -30% touches against the hyperparameter (mean over draws)")
    return save_figure(figure, path, dpi=90)


def _plot_images(path: Path, mesh, shown: dict) -> Path:
    panels = [(size, "low") for size in SIZES] + [(0.025, "noise-free")]
    figure, axes = plt.subplots(len(panels), len(SHOWN), figsize=(2.9 * len(SHOWN), 2.5 * len(panels)), squeeze=False)
    angle = np.linspace(0, 2 * np.pi, 100)
    for row, (size, noise) in zip(axes, panels, strict=True):
        for ax, value in zip(row, SHOWN, strict=True):
            plot_elements(ax, mesh, shown[size, noise, value], electrodes=False)
            ax.plot(size * RADIUS * np.cos(angle), size * RADIUS * np.sin(angle), "k--", linewidth=0.8)
            ax.set_title(f"{size:g} R, {noise}, hp {value:g}", fontsize=8)
    figure.suptitle("One-step NOSER images of centred -30% touches (dsigma/sigma; dashed: the true touch)")
    return save_figure(figure, path, dpi=70)


STUDY = Study(name="size", figure="5.8", title="stimulus size", run=run)
