"""Fig. 5.6: a non-uniform background, and the relative change dsigma/sigma on it.

**Setup.** The skin (R = 0.08 m) is 0.01 S/sq on its left half (x < 0) and 0.002 S/sq on its
right half (the edge blurred within the elements it crosses). Two identical touches,
dsigma/sigma = -0.3 over discs of radius 0.2 R (0.016 m) at (-0.5 R, 0) and (0.5 R, 0)
(x = -/+0.04 m), one on each half: the same loading and gauge factor, so the same relative
change. Each draw simulates, on a finer mesh than the reconstruction's, 10 untouched frames and
30 frames of the held touches (3 s at 10 frames per second), each with medium noise (0.5% of
RMS(V_ref), independent per frame); the difference is the mean touched frame minus the mean
untouched one. (A peak is one element's value: with fewer frames its noise, not the
background, decides the ratio below.)

**Three backgrounds for the reconstruction.** The one-step NOSER reconstruction is linearised
at an assumed background sigma_b, and its image, the change dsigma divided by sigma_b, is the
relative change dsigma/sigma on that background:

- (a) uniform: the best homogeneous level sigma_h of the untouched frames (one value, S/sq);
- (b) the true map (on the reconstruction mesh);
- (c) the map fitted by `diffeit.fit.background` to the untouched frames (Gauss-Newton on
  ln sigma, smoothness prior, its hyperparameter by the discrepancy principle).

The headline uses the hyperparameter 0.1 (unit-free, `diffeit.inverse.LinearisedProblem`);
0.05, 0.2 and 0.5 are reported beside it.

**Definitions.** A touch's window is the disc of radius 0.4 R about its centre (each lies
within its half). Its peak: the most negative value among the elements whose area lies mostly
in the window; its integral: the area integral of dsigma/sigma over the window (m^2; the truth
is -0.3 pi (0.2 R)^2 = -2.41e-4 m^2). The ratio of the two touches (right / left, ideally 1)
says how differently the same touch reads on the two backgrounds. A map's region means:
area-weighted means over the elements whose centroids lie at least 0.1 R from the edge, per
half.

**Outputs.** `background_touches.csv` (every draw, background and hyperparameter: both touches'
peaks and integrals and their ratios), `background_maps.csv` (every draw: sigma_h, the fitted
map's region means and its fit's hyperparameter, misfit and result), `background_maps.png`
(true map, fitted map and the uniform assumption; below, the three dsigma/sigma images),
`background_ratios.png` (the ratios against the hyperparameter).

**Finding asserted:** with the fitted map the two touches' peaks agree within 10% (the mean ratio
over the draws; the spread between draws is reported) and the map's region means are within 10%
of the truth, while the uniform assumption misreports the touch on the less conductive half (its
ratio is reported).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm.auto import tqdm

import diffeit as de
from diffeit import fit
from diffeit import scene as sc
from diffeit.inverse import LinearisedProblem
from diffeit.inverse.linearised import regularised_inverse
from diffeit.plotting import plot_elements
from diffeit.results import RESULTS

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

LOW = 0.002  # S/sq, the right half
CENTRES = ((-0.5 * RADIUS, 0.0), (0.5 * RADIUS, 0.0))
TARGET_RADIUS = 0.2 * RADIUS
AMPLITUDE = -0.3
WINDOW = 0.4 * RADIUS
EDGE_BAND = 0.1 * RADIUS
HYPERPARAMETER = 0.1
HYPERPARAMETERS = (0.05, 0.1, 0.2, 0.5)
N_REFERENCE, N_TOUCHED = 10, 30
ASSUMPTIONS = ("uniform", "true", "fitted")
# The right half as a polygon reaching well beyond the rim.
HALVES = sc.Background(
    BACKGROUND,
    regions=(
        sc.Region(
            sc.Polygon([[0.0, -2 * RADIUS], [2 * RADIUS, -2 * RADIUS], [2 * RADIUS, 2 * RADIUS], [0.0, 2 * RADIUS]]),
            LOW,
        ),
    ),
)


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    data_mesh, mesh = (skin(0.08), skin(0.14)) if small else (skin(0.05), skin(0.1))
    draws = range(2 if small else 10)  # small: two draws, still a spread between them
    data_model, reconstruction = model(data_mesh), model(mesh)
    true_data = np.asarray(HALVES.values_on(data_mesh))
    true_map = np.asarray(HALVES.values_on(mesh))
    reference = np.asarray(data_model.measure(true_data))
    touched = np.asarray(
        data_model.measure(true_data * (1 + disc_change(data_mesh, CENTRES, TARGET_RADIUS, AMPLITUDE)))
    )
    percent = NOISE_LEVELS["medium"]
    windows = [de.mesh.disc_fraction(mesh, centre, WINDOW) for centre in CENTRES]
    x, areas = mesh.element_centroids[:, 0], mesh.element_areas
    halves = {"left": x < -EDGE_BAND, "right": x > EDGE_BAND}

    def region_means(values: np.ndarray) -> dict[str, float]:
        return {side: float(values[m] @ areas[m] / areas[m].sum()) for side, m in halves.items()}

    true_problem = LinearisedProblem(reconstruction, "noser", true_map)
    touch_rows, map_rows, shown = [], [], {}
    for draw in tqdm(draws, desc="background study", disable=not progress):
        seeds = 100 * draw + np.arange(N_REFERENCE + N_TOUCHED)
        untouched = np.array([noisy(reference, reference, percent, s) for s in seeds[:N_REFERENCE]])
        held = np.array([noisy(touched, reference, percent, s) for s in seeds[N_REFERENCE:]])
        fitted = fit.background(reconstruction, untouched, progress=False, throw=False)
        means = region_means(fitted.conductivity)
        map_rows.append(
            {
                "draw": draw,
                "homogeneous": fitted.homogeneous,
                "fitted_left": means["left"],
                "fitted_right": means["right"],
                "true_left": BACKGROUND,
                "true_right": LOW,
                "fit_hyperparameter": fitted.hyperparameter,
                "fit_misfit": fitted.misfit,
                "fit_successful": fitted.result == RESULTS.successful,
            }
        )
        difference = held.mean(axis=0) - untouched.mean(axis=0)
        problems = {
            "uniform": LinearisedProblem(reconstruction, "noser", fitted.homogeneous),
            "true": true_problem,
            "fitted": LinearisedProblem(reconstruction, "noser", fitted.conductivity),
        }
        for assumption, problem in problems.items():
            data = difference / problem.data_scale
            for value in HYPERPARAMETERS:
                image = regularised_inverse(problem, value) @ data  # dsigma / sigma_b
                peaks = [float(image[w > 0.5].min()) for w in windows]
                integrals = [float(image @ (w * areas)) for w in windows]
                touch_rows.append(
                    {
                        "draw": draw,
                        "background": assumption,
                        "hyperparameter": value,
                        "peak_left": peaks[0],
                        "peak_right": peaks[1],
                        "peak_ratio": peaks[1] / peaks[0],
                        "integral_left_m2": integrals[0],
                        "integral_right_m2": integrals[1],
                        "integral_ratio": integrals[1] / integrals[0],
                    }
                )
                if draw == 0 and value == HYPERPARAMETER:
                    shown[assumption] = image
        if draw == 0:
            shown["map"] = fitted.conductivity
            shown["homogeneous"] = fitted.homogeneous

    def column(name: str, assumption: str) -> np.ndarray:
        """`name` of every draw, at the headline's hyperparameter."""
        return np.array(
            [r[name] for r in touch_rows if r["background"] == assumption and r["hyperparameter"] == HYPERPARAMETER]
        )

    def mean_of(name: str, assumption: str) -> float:
        return float(np.mean(column(name, assumption)))

    peak_ratio = {a: mean_of("peak_ratio", a) for a in ASSUMPTIONS}
    peak_spread = {a: float(np.std(column("peak_ratio", a), ddof=1)) for a in ASSUMPTIONS}
    integral_ratio = {a: mean_of("integral_ratio", a) for a in ASSUMPTIONS}
    fitted_means = {side: float(np.mean([r[f"fitted_{side}"] for r in map_rows])) for side in halves}
    truth_means = {"left": BACKGROUND, "right": LOW}
    map_error = max(abs(fitted_means[s] / truth_means[s] - 1) for s in halves)
    homogeneous = float(np.mean([r["homogeneous"] for r in map_rows]))
    truth_integral = AMPLITUDE * np.pi * TARGET_RADIUS**2

    files = [
        write_table(folder / "background_touches.csv", touch_rows),
        write_table(folder / "background_maps.csv", map_rows),
        _plot_maps(folder / "background_maps.png", mesh, true_map, shown),
        _plot_ratios(folder / "background_ratios.png", touch_rows),
    ]
    agree = abs(peak_ratio["fitted"] - 1) <= 0.1 and map_error <= 0.1
    statements = [
        f"fitted map: region means {fitted_means['left']:.4g} and {fitted_means['right']:.4g} S/sq "
        f"(truth 0.01 and 0.002; largest error {100 * map_error:.1f}%); uniform level {homogeneous:.4g} S/sq",
        *(
            f"{a} background: right/left touch ratio {peak_ratio[a]:.3f} in peak (draws' standard deviation "
            f"{peak_spread[a]:.3f}), {integral_ratio[a]:.3f} in integral"
            f" (integrals {mean_of('integral_left_m2', a) / truth_integral:.2f} and"
            f" {mean_of('integral_right_m2', a) / truth_integral:.2f} of the truth)"
            for a in ASSUMPTIONS
        ),
        "with the fitted map the two touches agree within 10% in peak"
        if agree
        else "with the fitted map the two touches do NOT agree within 10% in peak (or the map is off)",
    ]
    return Findings(
        values={
            "peak_ratio": peak_ratio,
            "peak_ratio_spread": peak_spread,
            "integral_ratio": integral_ratio,
            "fitted_region_means": fitted_means,
            "map_error": map_error,
            "homogeneous": homogeneous,
            "fitted_agrees": bool(agree),
        },
        statements=tuple(statements),
        files=tuple(files),
    )


def _plot_maps(path: Path, mesh: de.Mesh, true_map: np.ndarray, shown: dict) -> Path:
    figure, axes = plt.subplots(2, 3, figsize=(12, 7.5))
    maps = {
        "true map": true_map,
        "fitted map (fit.background)": shown["map"],
        f"uniform assumption, {shown['homogeneous']:.4g} S/sq": np.full(mesh.n_elements, shown["homogeneous"]),
    }
    top = 1.1 * max(true_map.max(), shown["map"].max())
    for ax, (title, values) in zip(axes[0], maps.items(), strict=True):
        artist = plot_elements(ax, mesh, values, cmap="viridis", symmetric=False, label="sigma (S/sq)")
        artist.set_clim(0.0, top)
        ax.set_title(title, fontsize=9)
    limit = max(np.abs(shown[a]).max() for a in ASSUMPTIONS)
    for ax, assumption in zip(axes[1], ASSUMPTIONS, strict=True):
        artist = plot_elements(ax, mesh, shown[assumption], label="dsigma/sigma")
        artist.set_clim(-limit, limit)
        for centre in CENTRES:
            ax.add_patch(plt.Circle(centre, TARGET_RADIUS, fill=False, linestyle="--", linewidth=0.8))
        ax.set_title(f"dsigma/sigma on the {assumption} background", fontsize=9)
    figure.suptitle(
        f"Two -30% touches on 0.01 | 0.002 S/sq, medium noise, one-step NOSER (hyperparameter {HYPERPARAMETER:g}); "
        "dashed: the true touches",
        fontsize=9,
    )
    return save_figure(figure, path, dpi=80)


def _plot_ratios(path: Path, rows: list[dict]) -> Path:
    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, column, what in zip(axes, ("peak_ratio", "integral_ratio"), ("peak", "integral"), strict=True):
        ax.axhspan(0.9, 1.1, color="0.9", label="within 10%")
        ax.axhline(1.0, color="0.5", linewidth=0.8)
        for assumption in ASSUMPTIONS:
            values = np.array(
                [[r[column] for r in rows if r["background"] == assumption and r["hyperparameter"] == v]
                 for v in HYPERPARAMETERS]
            )  # fmt: skip
            mean = values.mean(axis=1)
            spread = [mean - values.min(axis=1), values.max(axis=1) - mean]
            ax.errorbar(HYPERPARAMETERS, mean, yerr=spread, marker="o", capsize=3, label=f"{assumption} background")
        ax.set_xscale("log")
        ax.set_xticks(HYPERPARAMETERS, [f"{v:g}" for v in HYPERPARAMETERS])
        ax.minorticks_off()
        ax.set_xlabel("hyperparameter")
        ax.set_ylabel(f"right / left touch, {what} of dsigma/sigma")
        ax.set_title(f"Touch {what}: 0.002 S/sq half over 0.01 S/sq half", fontsize=9)
        ax.legend(fontsize=8)
    figure.suptitle("Mean over the draws (bars: smallest to largest)", fontsize=9)
    return save_figure(figure, path)


STUDY = Study(
    name="background",
    figure="5.6",
    title="a non-uniform background: uniform, true and fitted maps",
    run=run,
)
