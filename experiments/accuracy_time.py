"""What accuracy costs in time: every method on the same scenes, meshes, backends and precisions.

**Scenes** (simulated on a finer mesh than any reconstruction's, h = 0.012 R, about 54,000
triangles, with noise 0.5% of RMS(V_ref), seeded draws): "touch", a -30% touch of radius 0.2 R at
(0.5 R, 0); "contrast", a +300% inclusion (a conductive object on the sheet) of radius 0.25 R
at (0.3 R, 0.3 R), far outside the linearisation's reach.

**Methods** (hyperparameters at their documented working points, not tuned per scene):
one-step with each prior (hyperparameter 0.05); GREIT (noise figure 0.5); Gauss-Newton
difference imaging capped at 1, 2, 5 and 20 iterations (Laplace prior, 0.05, stopping earlier
at the noise level); absolute Gauss-Newton (the touched frame alone, imaged as its change over
its own median level); total variation (0.05); the joint fit (`diffeit.fit.joint` on the
reference and one touched frame, memory off, its default priors). Settings: meshes of about 700
to 27,000 triangles (about 900 in the small mode); Gauss-Newton x20, absolute Gauss-Newton and
total variation up to about 13,000, the joint fit up to about 3,300 (beyond them a frame takes
minutes: the table shows the trend); for one-step and Gauss-Newton x5 also each solver backend
and float32 on the two smaller meshes.

**Errors** against the truth, on the reconstruction mesh's elements (GREIT's pixels mapped back
to elements by overlap area, `PixelGrid.to_elements`):
position error (m), amplitude error |peak - true peak| / |true peak| (relative changes), size
error |r_eq / r_true - 1| (half-amplitude equivalent radius), and 1 - correlation. **Time**: the
setup (matrix or prior factorisation, compiled once beforehand) and the time per frame, the
median of three runs over a batch of draws (one run where the warm-up took over 20 s), each
setting in a fresh process (the small mode: all in the calling one). **Converged**: for the
iterative methods, the fraction of frames whose iteration ended successfully (`RESULTS`; a
capped Gauss-Newton that stops at its cap before the noise level reads 0); empty for direct
ones. Errors are measured on every frame, converged or not.

**Outputs.** `accuracy_time.csv` (every row), `accuracy_time_front.csv` (the Pareto fronts of
amplitude error and of 1 - correlation against time per frame, per scene),
`accuracy_time_budget.csv` (per scene and error, the best setting within each time budget from 1
ms to 100 s per frame), `accuracy_time.png` (the Pareto plots, log time).

**Finding asserted:** nonlinear iterations lower the amplitude error on the high-contrast scene:
Gauss-Newton after 1 and 5 iterations against its own linearisation (the one-step image with its
prior and hyperparameter, "0 iterations"), each lower than the last.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from tqdm.auto import tqdm

import diffeit as de
from diffeit.inverse import GREIT, AbsoluteGaussNewton, GaussNewton, OneStep, TotalVariation
from diffeit.results import RESULTS, failed

from ._study import (
    BACKGROUND,
    NOISE_LEVELS,
    RADIUS,
    Findings,
    Study,
    disc_change,
    machine,
    model,
    noisy,
    save_figure,
    skin,
    write_table,
)

SCENES = {
    "touch": ((0.5 * RADIUS, 0.0), 0.2 * RADIUS, -0.3),
    "contrast": ((0.3 * RADIUS, 0.3 * RADIUS), 0.25 * RADIUS, 3.0),
}
SCENE_LABELS = {"touch": "a -30% touch of radius 0.2 R at 0.5 R", "contrast": "a +300% inclusion of radius 0.25 R"}
HYPERPARAMETER = 0.05
FRONT_ERRORS = ("amplitude_error", "one_minus_correlation")
ERROR_LABELS = {
    "amplitude_error": "amplitude error |peak - truth| / |truth|",
    "one_minus_correlation": "1 - correlation with the truth",
}
BUDGETS = (1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0)  # seconds per frame
GAUSS_NEWTON_ITERATIONS = (1, 2, 5, 20)
_LONG_RUN = 20.0  # seconds


@dataclasses.dataclass(frozen=True)
class Method:
    """A method: `build(model) -> reconstruct`, where `reconstruct(frames, reference)` maps (T, M)
    frames and the (M,) reference (volts) to (T, E) relative changes on the model's elements and,
    for an iterative method, (T,) whether each frame's iteration converged (its result code is
    `RESULTS.successful`; None for a direct method).
    `max_triangles`: the largest mesh it runs on in the full sweep (its cost grows past use)."""

    name: str
    build: Callable
    family: str
    max_triangles: int = 10**9


def _converged(result: RESULTS) -> np.ndarray:
    """(T,) or (1,) whether each frame's iteration ended successfully."""
    return ~np.atleast_1d(failed(result))


def _one_step(prior: str) -> Method:
    def build(model):
        solver = OneStep(model, prior, HYPERPARAMETER, BACKGROUND)
        return lambda frames, reference: (np.asarray(solver.solve(frames - reference).value) / BACKGROUND, None)

    return Method(f"one-step {prior}", build, "one-step")


def _greit() -> Method:
    def build(model):
        solver = GREIT(model, noise_figure=0.5, background=BACKGROUND)
        return lambda frames, reference: (
            np.asarray(solver.solve(frames - reference).value) / BACKGROUND,  # pixels averaged onto the elements
            None,
        )

    return Method("GREIT", build, "GREIT")


def _gauss_newton(iterations: int) -> Method:
    def build(model):
        solver = GaussNewton(
            model,
            "laplace",
            HYPERPARAMETER,
            background=BACKGROUND,
            max_iterations=iterations,
            noise=NOISE_LEVELS["medium"],
        )

        def reconstruct(frames, reference):
            solution = solver.solve(frames - reference, throw=False)
            return np.atleast_2d(np.asarray(solution.value)) / BACKGROUND, _converged(solution.result)

        return reconstruct

    return Method(f"Gauss-Newton x{iterations}", build, "Gauss-Newton", 15_000 if iterations > 5 else 10**9)


def _absolute() -> Method:
    def build(model):
        solver = AbsoluteGaussNewton(model, "laplace", HYPERPARAMETER, noise=NOISE_LEVELS["medium"])

        def reconstruct(frames, reference):
            solution = solver.solve(frames, throw=False)
            sigma = np.atleast_2d(np.asarray(solution.value))
            return sigma / np.median(sigma, axis=1, keepdims=True) - 1, _converged(solution.result)

        return reconstruct

    return Method("absolute Gauss-Newton", build, "absolute", 15_000)


def _total_variation() -> Method:
    def build(model):
        solver = TotalVariation(model, HYPERPARAMETER, background=BACKGROUND)

        def reconstruct(frames, reference):
            solution = solver.solve(frames - reference, throw=False)
            return np.asarray(solution.value) / BACKGROUND, _converged(solution.result)

        return reconstruct

    return Method("total variation", build, "total variation", 15_000)


def _joint_fit() -> Method:
    """`diffeit.fit.joint` on each touched frame with the reference as its untouched first frame:
    background map, contact impedances and stimulus free, the memory model switched off (one
    frame has no history to fit it from); the image is the response over the fitted background."""
    memoryless = de.scene.MemoryParameters(
        fast_fraction=0.0, slow_fraction=0.0, first_cycle_offset=0.0, fatigue_limit=0.0
    )

    def build(model):
        def reconstruct(frames, reference):
            images, converged = [], []
            for frame in frames:
                fit = de.fit.joint(
                    model,
                    np.stack([reference, frame]).astype(np.float64),
                    np.array([0.0, 1.0]),
                    free=("background", "contact_impedance", "stimulus"),
                    initial={"memory": memoryless},
                    noise=NOISE_LEVELS["medium"],
                    progress=False,
                    throw=False,
                )
                images.append(np.asarray(fit.response[1]))
                converged.append(_converged(fit.result))
            return np.stack(images), np.concatenate(converged)

        return reconstruct

    return Method("joint fit", build, "joint fit", 4_000)


def methods(small: bool) -> list[Method]:
    if small:
        return [
            _one_step("noser"),
            _one_step("laplace"),
            _greit(),
            _gauss_newton(1),
            _gauss_newton(5),
            _total_variation(),
        ]
    return [
        *(_one_step(prior) for prior in ("tikhonov", "noser", "laplace", "matern")),
        _greit(),
        *(_gauss_newton(k) for k in GAUSS_NEWTON_ITERATIONS),
        _absolute(),
        _total_variation(),
        _joint_fit(),
    ]


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    mesh_sizes = (0.1,) if small else (0.12, 0.05, 0.025, 0.017)
    draws = 2 if small else 4
    data_mesh = skin(0.05 if small else 0.012)
    data_model = model(data_mesh)
    data = {}
    for scene, (centre, radius, amplitude) in SCENES.items():
        reference = np.asarray(data_model.measure(jnp.full(data_mesh.n_elements, BACKGROUND)))
        touched = np.asarray(data_model.measure(BACKGROUND * (1 + disc_change(data_mesh, [centre], radius, amplitude))))
        frames = np.array([noisy(touched, reference, NOISE_LEVELS["medium"], seed) for seed in range(draws)])
        data[scene] = (frames, noisy(reference, reference, NOISE_LEVELS["medium"], 99))

    meshes = {h: skin(h).n_elements for h in mesh_sizes}
    settings = [
        (h, m.name, "host_sparse", "float64")
        for h in mesh_sizes
        for m in methods(small)
        if small or meshes[h] <= m.max_triangles
    ]
    if not small:  # backends and float32 where they matter: the forward-model-heavy methods
        for h in mesh_sizes[:2]:
            for name in ("one-step noser", "Gauss-Newton x5"):
                settings += [(h, name, "dense_cholesky", "float64"), (h, name, "conjugate_gradient", "float64")]
                settings += [(h, name, "host_sparse", "float32")]
    bar = {"total": len(settings), "desc": "accuracy against time", "disable": not progress}
    if small:
        measured = map(_measure, settings, [data] * len(settings), [small] * len(settings))
        rows = [row for setting_rows in tqdm(measured, **bar) for row in setting_rows]
    else:
        # Each setting in a fresh process, one at a time: timings without another setting's
        # caches, and memory given back (one process for all ran out of 24 GB at 13,000 triangles).
        rows = []
        for setting in tqdm(settings, **bar):
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
                rows += pool.submit(_measure, setting, data, small).result()

    front = [row | {"front_of": error} for error in FRONT_ERRORS for row in _pareto_front(rows, error)]
    budget = _by_budget(rows)
    files = [
        write_table(folder / "accuracy_time.csv", rows),
        write_table(folder / "accuracy_time_front.csv", front),
        write_table(folder / "accuracy_time_budget.csv", budget),
        _plot(folder / "accuracy_time.png", rows),
    ]
    # Iterations 0 is the linearisation itself: one-step with Gauss-Newton's prior and hyperparameter.
    contrast = {}
    for k, name in [(0, "one-step laplace")] + [(k, f"Gauss-Newton x{k}") for k in (1, 5)]:
        chosen = [r for r in rows if r["scene"] == "contrast" and r["method"] == name and r["backend"] == "host_sparse"]
        contrast[k] = float(np.mean([r["amplitude_error"] for r in chosen if r["precision"] == "float64"]))
    lowers = contrast[5] < contrast[1] < contrast[0]
    verdict = "lower" if lowers else "do NOT lower"
    statements = [
        "high-contrast scene, amplitude error by Gauss-Newton iterations, mean over the meshes "
        "(0: the one-step linearisation): " + ", ".join(f"{k}: {v:.3f}" for k, v in contrast.items()),
        f"nonlinear iterations {verdict} the amplitude error on the high-contrast scene",
        f"machine: {machine()}",
    ]
    for row in budget:
        statements.append(
            f"{row['scene']}, {row['error']}, within {row['budget_s']:g} s per frame: {row['method']} "
            f"({row['triangles']} triangles, {row['backend']}, {row['precision']}): {row['value']:.3f}"
        )
    return Findings(
        values={
            "gauss_newton_amplitude_error": {str(k): float(v) for k, v in contrast.items()},
            "iterations_help": bool(lowers),
            "budget": budget,
        },
        statements=tuple(statements),
        files=tuple(files),
    )


def _measure(setting: tuple[float, str, str, str], data: dict, small: bool) -> list[dict]:
    """The rows of one setting (h, method name, backend, precision): setup and time per frame of
    each scene's frames, and their errors."""
    h, name, backend, precision = setting
    method = next(m for m in methods(small) if m.name == name)
    mesh = skin(h)
    forward = de.ForwardModel(
        mesh, de.protocol.adjacent(16), contact_impedance=model(mesh).contact_impedance, solver=backend
    )
    start = time.perf_counter()
    reconstruct = method.build(forward)
    setup = time.perf_counter() - start
    rows = []
    for scene, (centre, radius, amplitude) in SCENES.items():
        frames, reference = data[scene]
        dtype = np.float32 if precision == "float32" else np.float64
        frames, reference = frames.astype(dtype), reference.astype(dtype)
        start = time.perf_counter()
        reconstruct(frames, reference)  # compile and warm caches
        # Three timed runs, or one where a run takes minutes (Gauss-Newton at 27,000 triangles).
        repeats = 3 if time.perf_counter() - start < _LONG_RUN else 1
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            images, converged = reconstruct(frames, reference)
            times.append((time.perf_counter() - start) / len(frames))
        rows.append(
            {
                "scene": scene,
                "method": method.name,
                "family": method.family,
                "triangles": mesh.n_elements,
                "backend": backend,
                "precision": precision,
                "setup_s": setup,
                "time_per_frame_s": float(np.median(times)),
                "converged": "" if converged is None else float(np.mean(converged)),
                **_errors(mesh, np.asarray(images, np.float64), centre, radius, amplitude),
            }
        )
    return rows


def _errors(mesh: de.Mesh, images: np.ndarray, centre, radius: float, amplitude: float) -> dict[str, float]:
    """Mean over the draws of each error (module docstring), on the mesh's elements."""
    truth = disc_change(mesh, [centre], radius, amplitude)
    errors = {"position_error_m": [], "amplitude_error": [], "size_error": [], "one_minus_correlation": []}
    for image in images:
        errors["position_error_m"].append(de.metrics.position_error(mesh, image, centre))
        errors["amplitude_error"].append(abs(de.metrics.peak(image) - amplitude) / abs(amplitude))
        errors["size_error"].append(abs(de.metrics.equivalent_radius(mesh, image) / radius - 1))
        errors["one_minus_correlation"].append(1 - de.metrics.correlation(mesh, truth, image))
    return {name: float(np.mean(values)) for name, values in errors.items()}


def _pareto_front(rows: list[dict], error: str) -> list[dict]:
    """Per scene, the rows no other row beats in both time per frame and `error`, fastest first."""
    front = []
    for scene in SCENES:
        chosen = sorted((r for r in rows if r["scene"] == scene), key=lambda r: (r["time_per_frame_s"], r[error]))
        best = np.inf
        for row in chosen:
            if row[error] < best:
                front.append(row)
                best = row[error]
    return front


def _by_budget(rows: list[dict]) -> list[dict]:
    """Per scene, error and time budget: the setting with the smallest error among those whose
    time per frame fits the budget (none under the fastest setting's time)."""
    table = []
    for scene in SCENES:
        for error in FRONT_ERRORS:
            for budget in BUDGETS:
                fitting = [r for r in rows if r["scene"] == scene and r["time_per_frame_s"] <= budget]
                if fitting:
                    best = min(fitting, key=lambda r: r[error])
                    table.append(
                        {
                            "scene": scene,
                            "error": error,
                            "budget_s": budget,
                            "method": best["method"],
                            "triangles": best["triangles"],
                            "backend": best["backend"],
                            "precision": best["precision"],
                            "time_per_frame_s": best["time_per_frame_s"],
                            "value": best[error],
                        }
                    )
    return table


def _plot(path: Path, rows: list[dict]) -> Path:
    figure, axes = plt.subplots(
        len(FRONT_ERRORS), len(SCENES), figsize=(6.5 * len(SCENES), 4.5 * len(FRONT_ERRORS)), squeeze=False
    )
    families = sorted({r["family"] for r in rows})
    colours = dict(zip(families, plt.cm.tab10.colors, strict=False))
    for row_axes, error in zip(axes, FRONT_ERRORS, strict=True):
        for ax, scene in zip(row_axes, SCENES, strict=True):
            chosen = [r for r in rows if r["scene"] == scene]
            for family in families:
                points = [r for r in chosen if r["family"] == family]
                ax.scatter(
                    [r["time_per_frame_s"] for r in points],
                    [r[error] for r in points],
                    s=[10 + 10 * np.log2(r["triangles"] / 500) for r in points],
                    color=colours[family],
                    label=family,
                    alpha=0.75,
                )
            line = _pareto_front(chosen, error)
            ax.step([r["time_per_frame_s"] for r in line], [r[error] for r in line], where="post", color="0.3")
            for r in line:
                ax.annotate(
                    f"{r['method']}, {r['triangles']}",
                    (r["time_per_frame_s"], r[error]),
                    fontsize=6,
                    xytext=(3, 3),
                    textcoords="offset points",
                )
            ax.set_xscale("log")
            ax.set_xlabel("time per frame (s, log)")
            ax.set_ylabel(ERROR_LABELS[error])
            ax.set_title(f"{scene}: {SCENE_LABELS[scene]}", fontsize=9)
        row_axes[0].legend(fontsize=7)
    figure.suptitle("What accuracy costs in time (grey: the Pareto front; marker size grows with the mesh)")
    return save_figure(figure, path)


STUDY = Study(
    name="accuracy_time", figure="-", title="what accuracy costs in time, every method on the same scenes", run=run
)
