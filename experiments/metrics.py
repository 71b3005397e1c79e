"""Fig. 5.1: the image metrics on one scene.

**Setup.** A touch (dsigma/sigma = -0.3 over a disc of radius 0.2 R = 16 mm at (0.5 R, 0) =
(40 mm, 0), R = 0.08 m) is simulated on a fine mesh of the skin, with medium noise (0.5% of
RMS(V_ref), several seeded draws), and imaged one-step (NOSER prior) on a coarser mesh at
three hyperparameters: the working point for medium noise, 0.2 (the image-based optimal
hyperparameter of the hyperparameter study, Fig. 5.2, at this noise: about 0.18); 0.05, the
working point at low noise (0.1%), already too small here; and 0.003, far too small.

**Metrics** (`diffeit.metrics`, on the image dsigma/sigma per element): the peak (signed value
of largest magnitude); the half-amplitude set (elements at or beyond half the peak, on the
peak's side) and its connected components; the component matched to the touch gives the
equivalent radius sqrt(area / pi) (m and fraction of R), the position error |centroid - true
centre| (m and fraction of R) and the shape deformation (fraction of its area outside the disc
of equal area about its centroid); every other component is an artifact. Beside them: the
area-weighted correlation with the true change on the coarse mesh, and the cross-section along
x through the peak against the true profile.

**Outputs.** `metrics_table.csv` (every draw's figures at each hyperparameter),
`metrics_summary.csv` (per hyperparameter: means, worst position error, draws with artifacts),
`metrics_images.png` (per hyperparameter: the image, the half-amplitude set with the touch's
component and the artifacts, and the cross-section through the peak against the truth).

**Finding asserted:** at the working point every draw's half-amplitude set is one component at
the touch, no artifact, position error under 0.15 R; at 0.003 every draw has artifacts.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import matplotlib.tri
import numpy as np
from matplotlib.colors import ListedColormap
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

CENTRE = (0.5 * RADIUS, 0.0)
TARGET_RADIUS = 0.2 * RADIUS
AMPLITUDE = -0.3
NOISE = "medium"
# The image-based optimal hyperparameter (hyperparameter study) per noise level, rounded.
WORKING_POINTS = {"low": 0.05, "medium": 0.2}
TOO_SMALL = 0.003
HYPERPARAMETERS = (WORKING_POINTS["medium"], WORKING_POINTS["low"], TOO_SMALL)


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    draws = range(3 if small else 8)
    data_mesh, mesh = (skin(0.08), skin(0.14)) if small else (skin(0.04), skin(0.08))
    data_model = model(data_mesh)
    truth = disc_change(mesh, [CENTRE], TARGET_RADIUS, AMPLITUDE)
    reference = np.asarray(data_model.measure(np.full(data_mesh.n_elements, BACKGROUND)))
    touched = np.asarray(
        data_model.measure(BACKGROUND * (1 + disc_change(data_mesh, [CENTRE], TARGET_RADIUS, AMPLITUDE)))
    )
    percent = NOISE_LEVELS[NOISE]
    differences = np.array(
        [noisy(touched, reference, percent, 2 * s) - noisy(reference, reference, percent, 2 * s + 1) for s in draws]
    )
    problem = LinearisedProblem(model(mesh), "noser", BACKGROUND)
    data = differences / problem.data_scale

    rows, summary, shown = [], [], {}
    for value in tqdm(HYPERPARAMETERS, desc="metrics study", disable=not progress):
        images = data @ regularised_inverse(problem, value).T  # dsigma / sigma, (draws, E)
        chosen = []
        for draw, image in zip(draws, images, strict=True):
            figures = de.metrics.target_figures(mesh, image, [CENTRE])
            row = {
                "hyperparameter": value,
                "draw": draw,
                "peak": de.metrics.peak(image),
                "equivalent_radius_m": float(figures.equivalent_radius[0]),
                "equivalent_radius_R": float(figures.equivalent_radius[0] / RADIUS),
                "position_error_m": float(figures.position_error[0]),
                "position_error_R": float(figures.position_error[0] / RADIUS),
                "shape_deformation": float(figures.shape_deformation[0]),
                "components": figures.components.count,
                "artifacts": figures.n_artifacts,
                "correlation": de.metrics.correlation(mesh, truth, image),
            }
            rows.append(row)
            chosen.append(row)
        shown[value] = images[0]
        summary.append(
            {
                "hyperparameter": value,
                "draws": len(chosen),
                **{
                    f"mean_{name}": float(np.nanmean([r[name] for r in chosen]))
                    for name in ("peak", "equivalent_radius_R", "position_error_R", "shape_deformation", "correlation")
                },
                "worst_position_error_R": float(np.nanmax([r["position_error_R"] for r in chosen])),
                "draws_with_artifacts": sum(r["artifacts"] > 0 for r in chosen),
                "fewest_artifacts": min(r["artifacts"] for r in chosen),
                "most_artifacts": max(r["artifacts"] for r in chosen),
            }
        )

    files = [
        write_table(folder / "metrics_table.csv", rows),
        write_table(folder / "metrics_summary.csv", summary),
        _plot(folder / "metrics_images.png", mesh, shown),
    ]
    working, low, too_small = summary
    clean = working["draws_with_artifacts"] == 0 and all(
        r["components"] == 1 for r in rows if r["hyperparameter"] == working["hyperparameter"]
    )
    statements = [
        f"hp {s['hyperparameter']:g} ({NOISE} noise, {s['draws']} draws): peak {s['mean_peak']:.3f}, "
        f"equivalent radius {s['mean_equivalent_radius_R']:.3f} R (true 0.2 R), position error "
        f"{s['mean_position_error_R']:.3f} R (worst {s['worst_position_error_R']:.3f} R), shape deformation "
        f"{s['mean_shape_deformation']:.2f}, correlation {s['mean_correlation']:.2f}, artifacts in "
        f"{s['draws_with_artifacts']}/{s['draws']} draws ({s['fewest_artifacts']}-{s['most_artifacts']})"
        for s in summary
    ]
    statements.append(
        f"at the working point {working['hyperparameter']:g} the half-amplitude set is "
        + ("one component at the touch in every draw" if clean else "NOT one clean component in every draw")
        + f"; at {too_small['hyperparameter']:g} "
        + ("every draw has artifacts" if too_small["fewest_artifacts"] > 0 else "some draws have NO artifact")
    )
    return Findings(
        values={
            "working_point": working["hyperparameter"],
            "working_clean": bool(clean),
            "working_worst_position_error_R": working["worst_position_error_R"],
            "working_mean_equivalent_radius_R": working["mean_equivalent_radius_R"],
            "low_noise_point_draws_with_artifacts": low["draws_with_artifacts"],
            "too_small": too_small["hyperparameter"],
            "too_small_fewest_artifacts": too_small["fewest_artifacts"],
            "table": summary,
        },
        statements=tuple(statements),
        files=tuple(files),
    )


def _plot(path: Path, mesh, images: dict[float, np.ndarray]) -> Path:
    figure, axes = plt.subplots(len(images), 3, figsize=(12, 3.4 * len(images)), squeeze=False)
    triangulation = matplotlib.tri.Triangulation(mesh.nodes[:, 0] / RADIUS, mesh.nodes[:, 1] / RADIUS, mesh.triangles)
    angle = np.linspace(0, 2 * np.pi, 200)
    outline = np.array(CENTRE)[:, None] / RADIUS + TARGET_RADIUS / RADIUS * np.array([np.cos(angle), np.sin(angle)])
    for (image_ax, set_ax, section_ax), (value, image) in zip(axes, images.items(), strict=True):
        plot_elements(image_ax, mesh, image, label="dsigma/sigma", electrodes=False)
        image_ax.plot(*(outline * RADIUS), "k--", linewidth=1)
        image_ax.set_title(f"hp {value:g}: image", fontsize=9)

        figures = de.metrics.target_figures(mesh, image, [CENTRE])
        labels = figures.components.labels
        # 0 outside the set, 1 the touch's component, 2 an artifact.
        kinds = np.where(labels < 0, 0, np.where(labels == figures.component[0], 1, 2))
        set_ax.tripcolor(
            triangulation, facecolors=kinds, cmap=ListedColormap(["0.93", "tab:blue", "tab:red"]), vmin=0, vmax=2
        )
        set_ax.plot(*outline, "k--", linewidth=1, label="true touch")
        set_ax.plot(*(figures.centroid[0] / RADIUS), "k+", markersize=10, label="centroid")
        set_ax.set_aspect("equal")
        set_ax.set_xlabel("x / R")
        set_ax.set_ylabel("y / R")
        set_ax.set_title(
            f"half-amplitude set: touch (blue), {figures.n_artifacts} artifact(s) (red)\n"
            f"r_eq {figures.equivalent_radius[0] / RADIUS:.2f} R, error {figures.position_error[0] / RADIUS:.2f} R, "
            f"SD {figures.shape_deformation[0]:.2f}",
            fontsize=9,
        )
        set_ax.legend(fontsize=7, loc="lower left")

        section = de.metrics.cross_section(mesh, image)
        x = section.points[:, 0] / RADIUS
        inside = np.linalg.norm(section.points - np.array(CENTRE), axis=1) < TARGET_RADIUS
        section_ax.plot(x, section.values, label="image")
        section_ax.plot(x, np.where(inside, AMPLITUDE, 0.0), "k--", label="truth")
        peak = de.metrics.peak(image)
        section_ax.axhline(peak / 2, color="0.5", linewidth=0.8, linestyle=":", label="half the peak")
        section_ax.set_xlabel(f"x / R (y = {section.points[0, 1] / RADIUS:.2f} R, through the peak)")
        section_ax.set_ylabel("dsigma/sigma")
        section_ax.set_title(f"cross-section through the peak ({peak:.2f})", fontsize=9)
        section_ax.legend(fontsize=7)
    figure.suptitle(f"A -30% touch of radius 0.2 R at (0.5 R, 0), {NOISE} noise, one-step NOSER, first draw")
    return save_figure(figure, path, dpi=80)


STUDY = Study(name="metrics", figure="5.1", title="the image metrics on one scene", run=run)
