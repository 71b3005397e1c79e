"""Fig. 5.7: the memory effect, three identical presses on a skin that has not recovered.

**Setup.** The skin (R = 0.08 m, 0.01 S/sq) lies over foam (`diffeit.scene.over_foam()`: after
a release the response drops to about half at once and recovers with time constants of 1 s and
7.7 s, to 10% of the peak in about 7.5 s; a held press relaxes a little; the first press leaves
a permanent 5% offset; repeated presses fatigue the skin). The same press, a memoryless
dsigma/sigma = -0.3 over a disc of radius 0.2 R (0.016 m) at (0.5 R, 0) (x = 0.04 m), is applied
for 1 s at t = 1, 6 and 11 s: the gaps of 4 s are shorter than the recovery, so the second and
third presses land on a skin that still carries the first's change. Frames at 5 per second for
16 s (80), simulated by `diffeit.scene.simulate` on a finer mesh than the reconstruction's;
medium noise (0.5% of RMS(V_ref), independent per frame) is added to them.

**Images.** One-step NOSER images dsigma/sigma of every frame against the rested skin (the mean
of the 5 frames before the first press: one noisy frame would add its noise to every image as a
fixed pattern), hyperparameter 1.0: calm images, as `diffeit.fit.memory` needs (it reads each
element's time course; noise misleads it, blur does not), and calm enough that the ghosts stand
well above the noise. The same from the noise-free frames (the noise-free case), and the image
of the memoryless press, noise-free (the ideal every press should read).

**Correction.** `diffeit.fit.memory` on the images fits the memory's fractions, time constants
and relaxation (the gain, first-cycle offset and fatigue held at the preset's values, here the
truth) and returns the memoryless stimulus: the causal correction `diffeit.fit.correct_memory`
with the fitted parameters and a dead band at the images' noise level. The full mode also runs
the joint fit through the forward model (`diffeit.fit.joint`, the 5 rest frames as references)
on the first draw: its stimulus is not blurred like the one-step images.

**Definitions.** Ghost energy: over the frames from each release to the next press (and to the
end after the last), where the true stimulus is zero, the sum of the area-weighted squared
image, sum_k sum_e a_e x_ke^2 (m^2); the fraction removed is 1 - after / before. Its part due to
noise alone is that of the noisy minus the noise-free images. A press's peak: the most negative
value of its mean image over the held frames; its integral: the area integral of that image over
the disc of radius 0.4 R about the press centre (m^2; robust to the shape of a sharp stimulus);
its step: the peak of that image minus the mean of the two frames before the press (what a
reading against the last baseline reports). A profile: the mean held image along y = 0 through
the press centre (`diffeit.metrics.cross_section`); its deviation: the RMS difference from the
ideal's profile (for the joint fit's sharp stimulus this includes the one-step image's blur).

**Outputs.** `memory_presses.csv` (every draw, image kind and press: peak, step, integral, their
ratios to the first press, profile deviation), `memory_ghosts.csv` (every draw and image kind: ghost
energy and its fraction of the uncorrected one), `memory_parameters.csv` (the truth and the
fitted memory parameters, with the fits' run times), `memory_strips.png` (images during each
press and 2 s after each release: noise-free, noisy, corrected, joint), `memory_profiles.png`
(profiles through the press centre), `memory_peaks.png` (peaks, ghost energies, and the time
course at the press centre).

**Finding asserted:** the correction removes at least 80% of the ghost energy, and brings the
peaks of presses 2 and 3 within 10% of press 1's, in every draw.
"""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib
import matplotlib.tri

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm.auto import tqdm

import diffeit as de
from diffeit import fit
from diffeit import scene as sc

from ._study import (
    BACKGROUND,
    CONTACT_IMPEDANCE,
    ELECTRODE_WIDTH,
    NOISE_LEVELS,
    RADIUS,
    Findings,
    Study,
    model,
    noisy,
    save_figure,
    skin,
    write_table,
)

CENTRE = (0.5 * RADIUS, 0.0)
TARGET_RADIUS = 0.2 * RADIUS
AMPLITUDE = -0.3
STARTS = (1.0, 6.0, 11.0)
HOLD = 1.0
FRAME_RATE, DURATION = 5.0, 16.0
HYPERPARAMETER = 1.0
WINDOW = 0.4 * RADIUS
AFTER_RELEASE = 2.0  # s: when the strips show the ghost
TRUTH = sc.over_foam()
FITTED = ("fast_fraction", "fast_time", "slow_fraction", "slow_time", "relaxation")
COLOURS = {"ideal": "k", "noise-free": "0.55", "before": "C0", "after": "C1", "joint": "C2", "noise only": "C7"}
LABELS = {
    "ideal": "ideal (no memory, no noise)",
    "noise-free": "noise-free, with memory",
    "before": "noisy, uncorrected",
    "after": "corrected (fit.memory)",
    "joint": "joint fit (fit.joint)",
    "noise only": "noise alone",
}


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    h, simulation_h = (0.14, 0.08) if small else (0.1, 0.05)
    draws = range(1 if small else 3)
    # The small mode fits the memory parameters to the 20 strongest of the about 120 elements
    # above the noise: within 6% of all's fit, the same 85% of the ghosts removed, in 30 L-BFGS
    # steps instead of 670.
    max_elements = 20 if small else 200
    mesh = skin(h)
    reconstruction = model(mesh)
    scene = _scene(h, simulation_h)
    simulation = sc.simulate(scene, progress=False)
    clean, times = np.asarray(simulation.frames), np.asarray(simulation.times)
    reference = np.asarray(simulation.reference)
    truth = np.asarray(sc.stimulus(mesh, scene.touches, times))  # (T, E) memoryless, on the reconstruction mesh
    pressed = np.any(truth != 0, axis=1)
    presses = [(times >= s) & (times < s + HOLD) & pressed for s in STARTS]
    between = ~pressed & (times >= STARTS[0])
    rest = times < STARTS[0]
    one_step = de.inverse.OneStep(reconstruction, "noser", HYPERPARAMETER, BACKGROUND)

    def images_of(frames: np.ndarray) -> np.ndarray:
        return np.asarray(one_step.solve(frames - frames[rest].mean(axis=0)).value) / BACKGROUND

    # The memoryless press, noise-free: the simulation's model without the memory in between.
    data_model = model(simulation.mesh)
    fine_press = np.asarray(sc.stimulus(simulation.mesh, scene.touches, times[presses[0]][:1]))[0]
    ideal = (
        np.asarray(
            one_step.solve(
                data_model.measure(BACKGROUND * (1 + fine_press))
                - data_model.measure(np.full(fine_press.shape, BACKGROUND))
            ).value
        )
        / BACKGROUND
    )
    areas = mesh.element_areas
    window = de.mesh.disc_fraction(mesh, CENTRE, WINDOW) * areas
    ideal_profile = de.metrics.cross_section(mesh, ideal, through=CENTRE, direction=(1.0, 0.0))

    def ghost(images: np.ndarray) -> float:
        return float(np.sum(images[between] ** 2 * areas))

    def press_figures(images: np.ndarray) -> list[dict]:
        figures = []
        for held, start in zip(presses, STARTS, strict=True):
            image = images[held].mean(axis=0)
            baseline = images[(times < start)][-2:].mean(axis=0)
            profile = de.metrics.cross_section(mesh, image, through=CENTRE, direction=(1.0, 0.0))
            figures.append(
                {
                    "image": image,
                    "peak": float(image.min()),
                    "step": float((image - baseline).min()),
                    "integral": float(image @ window),
                    "profile": profile,
                    "deviation": float(np.sqrt(np.mean((profile.values - ideal_profile.values) ** 2))),
                }
            )
        return figures

    noise_free = images_of(clean)
    # Each kind of images of the first draw, with its presses' figures, for the plots.
    shown = {kind: (values, press_figures(values)) for kind, values in
             (("ideal", np.where(pressed[:, None], ideal, 0.0)), ("noise-free", noise_free))}  # fmt: skip
    press_rows, ghost_rows = [], []
    parameter_rows = [{"draw": "", "fit": "truth", "seconds": float("nan"), **_parameters(TRUTH)}]
    for kind, (_, figures) in shown.items():
        press_rows += _press_rows("", kind, figures)
    for draw in tqdm(draws, desc="memory study", disable=not progress):
        frames = noisy(clean, reference, NOISE_LEVELS["medium"], seed=draw)
        images = {"before": images_of(frames)}
        started = time.perf_counter()
        found = fit.memory(images["before"], times, max_elements=max_elements, progress=False, throw=False)
        parameter_rows.append(
            {"draw": draw, "fit": "memory", "seconds": time.perf_counter() - started, **_parameters(found.memory)}
        )
        images["after"] = np.asarray(found.stimulus)
        if not small and draw == 0:
            started = time.perf_counter()
            joint = fit.joint(
                reconstruction, frames, times, reference_frames=int(rest.sum()), progress=False, throw=False
            )
            parameter_rows.append(
                {"draw": draw, "fit": "joint", "seconds": time.perf_counter() - started, **_parameters(joint.memory)}
            )
            images["joint"] = np.asarray(joint.stimulus)
        energies = {"noise-free": ghost(noise_free), "noise only": ghost(images["before"] - noise_free)}
        energies |= {kind: ghost(values) for kind, values in images.items()}
        ghost_rows += [
            {"draw": draw, "images": kind, "ghost_energy_m2": e, "fraction_of_before": e / energies["before"]}
            for kind, e in energies.items()
        ]
        for kind, values in images.items():
            figures = press_figures(values)
            press_rows += _press_rows(draw, kind, figures)
            if draw == 0:
                shown[kind] = (values, figures)
        if draw == 0:
            shown_energies = energies

    def ratios(kind: str, name: str = "peak_ratio") -> np.ndarray:
        """(draws, 2) `name` of presses 2 and 3 (their peak or integral over press 1's)."""
        rows = [r for r in press_rows if r["images"] == kind and r["press"] > 1]
        return np.array([r[name] for r in rows]).reshape(-1, 2)

    removed = np.array([1 - r["fraction_of_before"] for r in ghost_rows if r["images"] == "after"])
    deviation = float(np.max(np.abs(ratios("after") - 1)))
    kinds = [k for k in ("noise-free", "before", "after", "joint") if k in shown]
    peak_ratio = {kind: ratios(kind).mean(axis=0).tolist() for kind in kinds}
    integral_ratio = {kind: ratios(kind, "integral_ratio").mean(axis=0).tolist() for kind in kinds}
    step_ratio = {
        kind: [float(np.mean([r["step_ratio"] for r in press_rows if r["images"] == kind and r["press"] == p]))
               for p in (2, 3)]
        for kind in kinds
    }  # fmt: skip
    corrected = bool(removed.min() >= 0.8 and deviation <= 0.1)

    files = [
        write_table(folder / "memory_presses.csv", press_rows),
        write_table(folder / "memory_ghosts.csv", ghost_rows),
        write_table(folder / "memory_parameters.csv", parameter_rows),
        _plot_strips(folder / "memory_strips.png", mesh, times, shown),
        _plot_profiles(folder / "memory_profiles.png", shown),
        _plot_peaks(folder / "memory_peaks.png", times, shown, shown_energies, mesh),
    ]
    statements = [
        f"ghost energy removed by fit.memory: {', '.join(f'{100 * r:.0f}%' for r in removed)} (per draw); "
        f"noise alone is {100 * shown_energies['noise only'] / shown_energies['before']:.0f}% of the uncorrected",
        *(
            f"{kind}: presses 2 and 3 peak at {peak_ratio[kind][0]:.3f} and {peak_ratio[kind][1]:.3f} of press 1; "
            f"their integrals at {integral_ratio[kind][0]:.3f} and {integral_ratio[kind][1]:.3f}; "
            f"their steps from the last baseline at {step_ratio[kind][0]:.3f} and {step_ratio[kind][1]:.3f}"
            for kind in kinds
        ),
        "the correction removes at least 80% of the ghost energy and brings presses 2 and 3 within 10% of press 1"
        if corrected
        else "the correction does NOT remove 80% of the ghost energy or bring presses 2 and 3 within 10% of press 1",
    ]
    if "joint" in shown:
        statements.insert(
            1,
            f"ghost energy removed by fit.joint: {100 * (1 - shown_energies['joint'] / shown_energies['before']):.0f}%",
        )
    return Findings(
        values={
            "ghost_removed": removed.tolist(),
            "ghost_removed_min": float(removed.min()),
            "ghost_removed_joint": None
            if "joint" not in shown
            else 1 - shown_energies["joint"] / shown_energies["before"],
            "peak_ratio": peak_ratio,
            "integral_ratio": integral_ratio,
            "step_ratio": step_ratio,
            "peak_deviation_after": deviation,
            "corrected": corrected,
        },
        statements=tuple(statements),
        files=tuple(files),
    )


def _scene(h: float, simulation_h: float) -> sc.Scene:
    return sc.Scene(
        skin=sc.Skin(
            geometry={"kind": "disc", "radius": RADIUS, "n_electrodes": 16, "electrode_width": ELECTRODE_WIDTH},
            h=h * RADIUS,
            simulation_h=simulation_h * RADIUS,
            contact_impedance=CONTACT_IMPEDANCE,
        ),
        background=sc.Background(BACKGROUND),
        touches=tuple(
            sc.Touch(sc.Disc(CENTRE, TARGET_RADIUS), AMPLITUDE, sc.Press(start=s, hold=HOLD)) for s in STARTS
        ),
        frame_rate=FRAME_RATE,
        duration=DURATION,
        effects=(TRUTH,),
        name="three presses on a skin over foam",
    )


def _parameters(memory: sc.MemoryParameters) -> dict[str, float]:
    return {name: float(getattr(memory, name)) for name in FITTED}


def _press_rows(draw, kind: str, figures: list[dict]) -> list[dict]:
    first = figures[0]
    return [
        {
            "draw": draw,
            "images": kind,
            "press": number,
            "peak": f["peak"],
            "peak_ratio": f["peak"] / first["peak"],
            "step": f["step"],
            "step_ratio": f["step"] / first["step"],
            "integral_m2": f["integral"],
            "integral_ratio": f["integral"] / first["integral"],
            "profile_deviation": f["deviation"],
        }
        for number, f in enumerate(figures, start=1)
    ]


def _frame_at(times: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(times - t)))


def _plot_strips(path: Path, mesh: de.Mesh, times: np.ndarray, shown: dict) -> Path:
    kinds = [k for k in ("noise-free", "before", "after", "joint") if k in shown]
    moments = [(s + 0.4 * HOLD, f"press {n}") for n, s in enumerate(STARTS, 1)]
    moments += [(s + HOLD + AFTER_RELEASE, f"{AFTER_RELEASE:g} s after release {n}") for n, s in enumerate(STARTS, 1)]
    moments.sort()
    frames = [_frame_at(times, t) for t, _ in moments]
    limit = max(np.abs(shown[k][0][frames]).max() for k in kinds)
    triangulation = matplotlib.tri.Triangulation(mesh.nodes[:, 0], mesh.nodes[:, 1], mesh.triangles)
    figure, axes = plt.subplots(
        len(kinds), len(frames), figsize=(1.9 * len(frames) + 1.2, 2.0 * len(kinds) + 0.5), layout="constrained"
    )
    for row, kind in zip(axes, kinds, strict=True):
        for ax, frame, (_, what) in zip(row, frames, moments, strict=True):
            artist = ax.tripcolor(
                triangulation, facecolors=shown[kind][0][frame], cmap="RdBu_r", vmin=-limit, vmax=limit
            )
            ax.add_patch(plt.Circle(CENTRE, TARGET_RADIUS, fill=False, linestyle="--", linewidth=0.6))
            ax.set_aspect("equal")
            ax.set_axis_off()
            ax.set_title(f"t = {times[frame]:.1f} s, {what}", fontsize=7)
        row[0].text(
            -0.08, 0.5, LABELS[kind], transform=row[0].transAxes, rotation=90, ha="right", va="center", fontsize=8
        )
    figure.colorbar(artist, ax=axes.ravel().tolist(), shrink=0.6, label="dsigma/sigma")
    figure.suptitle(
        "Three -30% presses at (0.5 R, 0), 5 s apart, on a skin over foam; "
        f"one-step NOSER, hyperparameter {HYPERPARAMETER:g}",
        fontsize=9,
    )
    return save_figure(figure, path, dpi=80)


def _plot_profiles(path: Path, shown: dict) -> Path:
    kinds = [k for k in ("ideal", "noise-free", "before", "after", "joint") if k in shown]
    figure, axes = plt.subplots(1, len(STARTS), figsize=(12, 3.8), sharey=True)
    for number, ax in enumerate(axes):
        for kind in kinds:
            profile = shown[kind][1][number]["profile"]
            style = "--" if kind == "noise-free" else "-"
            ax.plot(profile.points[:, 0], profile.values, style, color=COLOURS[kind], label=LABELS[kind])
        ax.axvspan(CENTRE[0] - TARGET_RADIUS, CENTRE[0] + TARGET_RADIUS, color="0.92")
        ax.set_xticks(np.linspace(-RADIUS, RADIUS, 5))
        ax.set_xlabel("x (m), along y = 0")
        ax.set_title(f"press {number + 1} at t = {STARTS[number]:g} s, mean over its hold", fontsize=9)
    axes[0].set_ylabel("dsigma/sigma")
    axes[0].legend(fontsize=7, loc="lower left")
    figure.suptitle("Profiles through the press centre (shaded: the true press)", fontsize=9)
    return save_figure(figure, path)


def _plot_peaks(path: Path, times: np.ndarray, shown: dict, energies: dict, mesh: de.Mesh) -> Path:
    kinds = [k for k in ("ideal", "noise-free", "before", "after", "joint") if k in shown]
    figure = plt.figure(figsize=(11, 7.5))
    grid = figure.add_gridspec(2, 2)
    bars, ghosts, course = (
        figure.add_subplot(grid[0, 0]),
        figure.add_subplot(grid[0, 1]),
        figure.add_subplot(grid[1, :]),
    )
    width = 0.8 / len(kinds)
    for k, kind in enumerate(kinds):
        peaks = [-f["peak"] for f in shown[kind][1]]
        bars.bar(
            np.arange(1, 4) + (k - (len(kinds) - 1) / 2) * width, peaks, width, color=COLOURS[kind], label=LABELS[kind]
        )
    bars.set_xticks([1, 2, 3], ["press 1", "press 2", "press 3"])
    bars.set_ylabel("peak drop, -dsigma/sigma (mean over the hold)")
    bars.set_ylim(0, 1.4 * max(-f["peak"] for kind in kinds for f in shown[kind][1]))
    bars.legend(fontsize=7, loc="upper center", ncol=2)
    bars.set_title("Press peaks", fontsize=9)
    names = [k for k in ("noise-free", "noise only", "before", "after", "joint") if k in energies]
    ghosts.bar(range(len(names)), [energies[k] for k in names], color=[COLOURS[k] for k in names])
    ghosts.set_xticks(
        range(len(names)), [LABELS[k].replace(", ", ",\n").replace(" (", "\n(") for k in names], fontsize=7
    )
    ghosts.set_yscale("log")
    ghosts.set_ylabel("ghost energy, sum a x^2 between presses (m^2)")
    ghosts.set_title("Ghost energy where the true stimulus is zero", fontsize=9)
    element = int(np.argmin(np.linalg.norm(mesh.element_centroids - np.asarray(CENTRE), axis=1)))
    for kind in kinds:
        marker = "." if kind in ("before", "after", "joint") else None
        style = "--" if kind == "noise-free" else "-"
        course.plot(
            times,
            shown[kind][0][:, element],
            style,
            color=COLOURS[kind],
            label=LABELS[kind],
            marker=marker,
            drawstyle="steps-post",  # frames hold until the next, as the memory model reads them
        )
    for start in STARTS:
        course.axvspan(start, start + HOLD, color="0.92")
    course.set_xlabel("time (s)")
    course.set_ylabel("dsigma/sigma at the press centre")
    course.legend(fontsize=7, ncol=3)
    course.set_title("Time course at the press centre (shaded: the presses)", fontsize=9)
    return save_figure(figure, path, dpi=90)


STUDY = Study(
    name="memory",
    figure="5.7",
    title="the memory effect: three presses on a skin that has not recovered",
    run=run,
)
