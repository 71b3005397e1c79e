"""What accuracy costs in time: every method on the same scenes, meshes, backends and precisions.

**Scenes** (simulated on a mesh of twice the resolution of the finest reconstruction mesh,
h = R / 60, noise 0.5% of RMS(V_ref), seeded draws): "touch", a -30% touch of radius 0.2 R at
(0.5 R, 0); "contrast", a +300% inclusion (a conductive object on the sheet) of radius 0.25 R
at (0.3 R, 0.3 R), far outside the linearisation's reach.

**Methods** (hyperparameters at their documented working points, not tuned per scene):
one-step with each prior (hyperparameter 0.05); GREIT (noise figure 0.5); Gauss-Newton
difference imaging capped at 1, 2, 5 and 20 iterations (Laplace prior, 0.05, stopping earlier
at the noise level); absolute Gauss-Newton (the touched frame alone, imaged as its change over
its own median level); total variation (0.05). Settings: meshes of about 900 (small mode) to
27,000 triangles; for one-step and Gauss-Newton also each solver backend and float32.

**Errors** against the truth, on the reconstruction's geometry (elements; GREIT's pixels):
position error (m), amplitude error |peak - true peak| / |true peak| (relative changes), size
error |r_eq / r_true - 1| (half-amplitude equivalent radius), and 1 - correlation. **Time**: the
setup (matrix or prior factorisation, compiled once beforehand) and the time per frame, the
median of three runs over a batch of draws (one run where the warm-up took over 20 s), in a
fresh process of this machine.

**Outputs.** `accuracy_time.csv` (every row), `accuracy_time_front.csv` (the Pareto front of
amplitude error against time per frame, per scene), `accuracy_time.png` (the Pareto plot, log
time). **Finding asserted:** nonlinear iterations lower the amplitude error on the
high-contrast scene: Gauss-Newton after 1 and 5 iterations against its own linearisation (the
one-step image with its prior and hyperparameter, "0 iterations"), each lower than the last.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from tqdm.auto import tqdm

import diffeit as de
from diffeit.inverse import GREIT, GaussNewton, OneStep, TotalVariation

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
    skin,
    write_table,
)

SCENES = {
    "touch": ((0.5 * RADIUS, 0.0), 0.2 * RADIUS, -0.3),
    "contrast": ((0.3 * RADIUS, 0.3 * RADIUS), 0.25 * RADIUS, 3.0),
}
HYPERPARAMETER = 0.05
GAUSS_NEWTON_ITERATIONS = (1, 2, 5, 20)
_LONG_RUN = 20.0  # seconds


@dataclasses.dataclass(frozen=True)
class Method:
    """A method: `build(model) -> reconstruct`, where `reconstruct(frames, reference)` maps (T, M)
    frames and the (M,) reference (volts) to (T, n) relative changes on `geometry(built)`."""

    name: str
    build: Callable
    family: str


def _one_step(prior: str) -> Method:
    def build(model):
        solver = OneStep(model, prior, HYPERPARAMETER, BACKGROUND)
        return lambda frames, reference: np.asarray(solver.reconstruct(frames - reference)) / BACKGROUND, model.mesh

    return Method(f"one-step {prior}", build, "one-step")


def _greit() -> Method:
    def build(model):
        solver = GREIT(model, noise_figure=0.5, background=BACKGROUND)
        pixels = solver.grid.mask

        def reconstruct(frames, reference):
            return (
                np.asarray(solver.reconstruct(frames - reference)).reshape(len(frames), -1)[:, pixels.ravel()]
                / BACKGROUND
            )

        return reconstruct, solver.grid

    return Method("GREIT", build, "GREIT")


def _gauss_newton(iterations: int) -> Method:
    def build(model):
        solver = GaussNewton(model, "laplace", HYPERPARAMETER, max_iterations=iterations, noise=NOISE_LEVELS["medium"])

        def reconstruct(frames, reference):
            result = solver.difference(frames - reference, background=BACKGROUND, throw=False)
            return np.atleast_2d(np.asarray(result.conductivity_change)) / BACKGROUND

        return reconstruct, model.mesh

    return Method(f"Gauss-Newton x{iterations}", build, "Gauss-Newton")


def _absolute() -> Method:
    def build(model):
        solver = GaussNewton(model, "laplace", HYPERPARAMETER, noise=NOISE_LEVELS["medium"])

        def reconstruct(frames, reference):
            sigma = np.atleast_2d(np.asarray(solver.absolute(frames, throw=False).conductivity))
            return sigma / np.median(sigma, axis=1, keepdims=True) - 1

        return reconstruct, model.mesh

    return Method("absolute Gauss-Newton", build, "absolute")


def _total_variation() -> Method:
    def build(model):
        solver = TotalVariation(model, HYPERPARAMETER, background=BACKGROUND)
        return lambda frames, reference: np.asarray(solver.reconstruct(frames - reference, throw=False)) / BACKGROUND, (
            model.mesh
        )

    return Method("total variation", build, "total variation")


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
    ]


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    mesh_sizes = (0.1,) if small else (0.1, 0.05, 0.025, 0.017)
    draws = 2 if small else 4
    data_mesh = skin(0.05 if small else 1 / 60)
    data_model = model(data_mesh)
    data = {}
    for scene, (centre, radius, amplitude) in SCENES.items():
        reference = np.asarray(data_model.measure(jnp.full(data_mesh.n_elements, BACKGROUND)))
        touched = np.asarray(data_model.measure(BACKGROUND * (1 + disc_change(data_mesh, [centre], radius, amplitude))))
        frames = np.array([noisy(touched, reference, NOISE_LEVELS["medium"], seed) for seed in range(draws)])
        data[scene] = (frames, noisy(reference, reference, NOISE_LEVELS["medium"], 99))

    settings = [(h, m, "host_sparse", "float64") for h in mesh_sizes for m in methods(small)]
    if not small:  # backends and float32 where they matter: the forward-model-heavy methods
        for h in mesh_sizes[:2]:
            for m in (_one_step("noser"), _gauss_newton(5)):
                settings += [(h, m, "dense_cholesky", "float64"), (h, m, "conjugate_gradient", "float64")]
                settings += [(h, m, "host_sparse", "float32")]
    rows = []
    for h, method, backend, precision in tqdm(settings, desc="accuracy against time", disable=not progress):
        mesh = skin(h)
        forward = de.ForwardModel(
            mesh, de.protocol.adjacent(16), contact_impedance=model(mesh).contact_impedance, solver=backend
        )
        start = time.perf_counter()
        reconstruct, geometry = method.build(forward)
        setup = time.perf_counter() - start
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
                images = reconstruct(frames, reference)
                times.append((time.perf_counter() - start) / len(frames))
            truth = _truth(geometry, mesh, centre, radius, amplitude)
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
                    **_errors(geometry, np.asarray(images, np.float64), truth, centre, radius, amplitude),
                }
            )

    front = _pareto_front(rows)
    files = [
        write_table(folder / "accuracy_time.csv", rows),
        write_table(folder / "accuracy_time_front.csv", front),
        _plot(folder / "accuracy_time.png", rows, front),
    ]
    # Iterations 0 is the linearisation itself: one-step with Gauss-Newton's prior and hyperparameter.
    contrast = {}
    for k, name in [(0, "one-step laplace")] + [(k, f"Gauss-Newton x{k}") for k in (1, 5)]:
        chosen = [r for r in rows if r["scene"] == "contrast" and r["method"] == name and r["backend"] == "host_sparse"]
        contrast[k] = float(np.mean([r["amplitude_error"] for r in chosen if r["precision"] == "float64"]))
    lowers = contrast[5] < contrast[1] < contrast[0]
    verdict = "lower" if lowers else "do NOT lower"
    statements = [
        "high-contrast scene, amplitude error by Gauss-Newton iterations (0: the one-step linearisation): "
        + ", ".join(f"{k}: {v:.3f}" for k, v in contrast.items()),
        f"nonlinear iterations {verdict} the amplitude error on the high-contrast scene",
        f"machine: {machine()}",
    ]
    for scene in SCENES:
        points = [
            f"{r['method']} @ {r['triangles']} tri: {r['time_per_frame_s']:.2g} s, {r['amplitude_error']:.3f}"
            for r in front
            if r["scene"] == scene
        ]
        statements.append(f"{scene}: Pareto front (time per frame, amplitude error) " + "; ".join(points))
    return Findings(
        values={
            "gauss_newton_amplitude_error": {str(k): float(v) for k, v in contrast.items()},
            "iterations_help": bool(lowers),
        },
        statements=tuple(statements),
        files=tuple(files),
    )


def _truth(geometry, mesh: de.Mesh, centre, radius: float, amplitude: float) -> np.ndarray:
    """The true relative change on `geometry` (the mesh's elements, or GREIT's pixels in the image)."""
    change = disc_change(mesh, [centre], radius, amplitude)
    if isinstance(geometry, de.Mesh):
        return change
    return geometry.render(change)[geometry.mask]


def _errors(
    geometry, images: np.ndarray, truth: np.ndarray, centre, radius: float, amplitude: float
) -> dict[str, float]:
    """Mean over the draws of each error (module docstring)."""
    if not isinstance(geometry, de.Mesh):
        full = np.zeros((len(images), *geometry.shape))
        full[:, geometry.mask] = images
        images = full
        truth_image = np.zeros(geometry.shape)
        truth_image[geometry.mask] = truth
        truth = truth_image
    errors = {"position_error_m": [], "amplitude_error": [], "size_error": [], "one_minus_correlation": []}
    for image in images:
        errors["position_error_m"].append(de.metrics.position_error(geometry, image, centre))
        errors["amplitude_error"].append(abs(de.metrics.peak(image) - amplitude) / abs(amplitude))
        errors["size_error"].append(abs(de.metrics.equivalent_radius(geometry, image) / radius - 1))
        errors["one_minus_correlation"].append(1 - de.metrics.correlation(geometry, truth, image))
    return {name: float(np.mean(values)) for name, values in errors.items()}


def _pareto_front(rows: list[dict]) -> list[dict]:
    """Per scene, the rows no other row beats in both time per frame and amplitude error."""
    front = []
    for scene in SCENES:
        chosen = sorted(
            (r for r in rows if r["scene"] == scene), key=lambda r: (r["time_per_frame_s"], r["amplitude_error"])
        )
        best = np.inf
        for row in chosen:
            if row["amplitude_error"] < best:
                front.append(row)
                best = row["amplitude_error"]
    return front


def _plot(path: Path, rows: list[dict], front: list[dict]) -> Path:
    figure, axes = plt.subplots(1, len(SCENES), figsize=(6 * len(SCENES), 4.5), squeeze=False)
    families = sorted({r["family"] for r in rows})
    colours = dict(zip(families, plt.cm.tab10.colors, strict=False))
    for ax, scene in zip(axes[0], SCENES, strict=True):
        chosen = [r for r in rows if r["scene"] == scene]
        for family in families:
            points = [r for r in chosen if r["family"] == family]
            ax.scatter(
                [r["time_per_frame_s"] for r in points],
                [r["amplitude_error"] for r in points],
                s=[12 + 8 * np.log2(r["triangles"] / 300) for r in points],
                color=colours[family],
                label=family,
                alpha=0.8,
            )
        line = [r for r in front if r["scene"] == scene]
        ax.step([r["time_per_frame_s"] for r in line], [r["amplitude_error"] for r in line], where="post", color="0.3")
        for r in line:
            label = f"{r['method']}, {r['triangles']}"
            ax.annotate(
                label,
                (r["time_per_frame_s"], r["amplitude_error"]),
                fontsize=6,
                xytext=(3, 3),
                textcoords="offset points",
            )
        ax.set_xscale("log")
        ax.set_xlabel("time per frame (s, log)")
        ax.set_ylabel("amplitude error |peak - truth| / |truth|")
        ax.set_title(f"{scene}: marker size grows with the mesh")
        ax.legend(fontsize=7)
    figure.suptitle("What accuracy costs in time (Pareto front in grey)")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


STUDY = Study(
    name="accuracy_time", figure="-", title="what accuracy costs in time, every method on the same scenes", run=run
)
