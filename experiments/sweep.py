"""Sweeps that outgrow one machine: scenes x priors x hyperparameters of one-step imaging.

**One process.** For one prior the one-step images of every scene at every hyperparameter are
one jitted computation: with the measurement-space eigendecomposition G = U diag(g) U^T of the
normalised problem (`diffeit.inverse.LinearisedProblem`), the image at lambda is
B diag(1 / (g + lambda^2)) U^T y, B = P J_n^T U / c, so a block of H hyperparameters and S scenes
is a (H, S, M) array of coefficients and one (E, M) product: no per-point Python. Its figures of
merit are computed in the same jitted function (`_figures`): the correlation with the truth,
the amplitude error and the position error of the half-amplitude centroid. When JAX sees
several devices, the hyperparameter axis is sharded over them (`jax.sharding`): each device
computes its slice of the grid.

**Across machines.** `sweep(..., address=...)` runs the same blocks as tasks on a Dask
distributed cluster (`dask.distributed.Client(address)`); `workers=N` starts a local cluster of
N processes instead; neither runs in this process. The problem's arrays (B, g, U^T y, the
truths) are scattered to the workers once; a task is one block of hyperparameters for one prior
and returns its figures. The results equal the single-process ones (a test runs 2 local
workers).

**Plan for scale** (measured numbers in `sweep_timing.csv` and experiments/README.md): a point
(scene, prior, hyperparameter) costs one (E, M) x (M,) product and its figures, tens of
microseconds at 900 triangles; the setup per prior and mesh (Jacobian, prior solves,
eigendecomposition) costs about a second and is shared by every point. A million points at
900 triangles is minutes of compute, so the cluster pays off only for larger meshes, forward
simulations per scene (here the scenes' voltages are simulated once, in this process), or
nonlinear methods (Gauss-Newton costs a forward solve per iteration per point). For those the
work would move into the tasks: each task simulates and reconstructs its own scenes from their
parameters, and only figures travel back.

**Study** (`diffeit experiment sweep`): random -30% touches (radius 0.15-0.25 R, anywhere within
0.7 R) at medium noise, three priors, a hyperparameter grid; outputs `sweep.csv` (every point's
figures), `sweep.png` (median correlation against the hyperparameter per prior) and
`sweep_timing.csv` (seconds per point, single process and, in the full mode, a local cluster).
"""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from diffeit.inverse import LinearisedProblem

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

PRIORS = ("tikhonov", "noser", "laplace")


def scenes(count: int, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """`count` random touches: centres (count, 2) m, radii (count,) m, and their amplitude."""
    rng = np.random.default_rng(seed)
    radius = rng.uniform(0.15, 0.25, count) * RADIUS
    distance = np.sqrt(rng.uniform(0, 1, count)) * (0.7 * RADIUS)
    angle = rng.uniform(0, 2 * np.pi, count)
    return np.column_stack([distance * np.cos(angle), distance * np.sin(angle)]), radius, -0.3


@jax.jit
def _figures(basis, eigenvalues, coefficients, lambdas, truths, centres, areas, positions):
    """(H, S, 3): correlation, amplitude error and position error (m) of the one-step images
    of S scenes at H hyperparameters (module docstring)."""
    filters = 1.0 / (eigenvalues[None, :] + lambdas[:, None] ** 2)  # (H, M)
    filters = jnp.where(eigenvalues[None, :] > 0, filters, 0.0)
    images = jnp.einsum("em,hm,sm->hse", basis, filters, coefficients)  # dsigma / sigma
    weights = areas / areas.sum()

    def correlation(a, b):
        a, b = a - weights @ a, b - weights @ b
        return (weights @ (a * b)) / jnp.sqrt((weights @ a**2) * (weights @ b**2))

    corr = jax.vmap(lambda block: jax.vmap(correlation)(truths, block))(images)  # (H, S)
    peak = images.min(axis=-1)  # a touch is negative
    amplitude = jnp.abs(peak - truths.min(axis=-1)[None, :]) / jnp.abs(truths.min(axis=-1))[None, :]
    chosen = (images <= 0.5 * peak[..., None]) * areas
    centroid = jnp.einsum("hse,ec->hsc", chosen, positions) / chosen.sum(axis=-1)[..., None]
    error = jnp.linalg.norm(centroid - centres[None], axis=-1)
    return jnp.stack([corr, amplitude, error], axis=-1)


def _block(arrays: dict, lambdas: np.ndarray) -> np.ndarray:
    """`_figures` for one block, its hyperparameter axis sharded over the devices JAX sees."""
    devices = jax.devices()
    lambdas = np.asarray(lambdas, np.float64)
    if len(devices) > 1:
        padded = -len(lambdas) % len(devices)
        grid = np.concatenate([lambdas, np.full(padded, lambdas[-1])])
        sharding = NamedSharding(Mesh(np.array(devices), ("hyperparameters",)), PartitionSpec("hyperparameters"))
        figures = _figures(**arrays, lambdas=jax.device_put(grid, sharding))
        return np.asarray(figures)[: len(lambdas)]
    return np.asarray(_figures(**arrays, lambdas=lambdas))


def problem_arrays(h_fraction: float, prior: str, differences: np.ndarray, truths: np.ndarray, centres: np.ndarray):
    """The arrays of `_figures` for one mesh and prior (everything but the hyperparameters)."""
    mesh = skin(h_fraction)
    problem = LinearisedProblem(model(mesh), prior, BACKGROUND)
    return {
        "basis": problem.prior_jacobian @ problem.eigenvectors,
        "eigenvalues": problem.eigenvalues,
        "coefficients": (differences / problem.data_scale) @ problem.eigenvectors,
        "truths": truths,
        "centres": centres,
        "areas": np.asarray(mesh.element_areas),
        "positions": np.asarray(mesh.element_centroids),
    }


def sweep(
    arrays: dict[str, dict],
    hyperparameters: np.ndarray,
    *,
    block: int = 8,
    address: str | None = None,
    workers: int | None = None,
) -> dict[str, np.ndarray]:
    """Figures (H, S, 3) per prior (keys of `arrays`, each from `problem_arrays`) over the
    `hyperparameters`, in blocks of `block`: in this process, or as tasks on the Dask cluster
    at `address`, or on a local cluster of `workers` processes (module docstring)."""
    blocks = [hyperparameters[i : i + block] for i in range(0, len(hyperparameters), block)]
    if address is None and workers is None:
        return {prior: np.concatenate([_block(a, b) for b in blocks]) for prior, a in arrays.items()}
    from dask.distributed import Client, LocalCluster

    cluster = None if address else LocalCluster(n_workers=workers, threads_per_worker=1, processes=True)
    with Client(address or cluster) as client:
        # One future per prior's arrays (a dict would be scattered key by key, under shared names).
        scattered = {prior: client.scatter([a], broadcast=True)[0] for prior, a in arrays.items()}
        futures = {prior: [client.submit(_block, scattered[prior], b, pure=False) for b in blocks] for prior in arrays}
        results = {prior: np.concatenate(client.gather(f)) for prior, f in futures.items()}
    if cluster is not None:
        cluster.close()
    return results


def simulated(count: int, h_data: float, h: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`count` random touches (`scenes`) simulated on the skin meshed at `h_data` R, with medium
    noise: their voltage differences (count, M), their truths on the mesh at `h` R
    (count, E) and their centres (count, 2)."""
    centres, radii, amplitude = scenes(count, seed)
    data_mesh, mesh = skin(h_data), skin(h)
    data_model = model(data_mesh)
    reference = np.asarray(data_model.measure(np.full(data_mesh.n_elements, BACKGROUND)))
    percent = NOISE_LEVELS["medium"]

    def touched(k: int) -> np.ndarray:
        change = disc_change(data_mesh, [centres[k]], radii[k], amplitude)
        return noisy(np.asarray(data_model.measure(BACKGROUND * (1 + change))), reference, percent, k)

    differences = np.array([touched(k) - reference for k in range(count)])
    truths = np.array([disc_change(mesh, [c], r, amplitude) for c, r in zip(centres, radii, strict=True)])
    return differences, truths, centres


def run(folder: Path, *, small: bool = False, progress: bool = True) -> Findings:
    count = 12 if small else 200
    hyperparameters = np.logspace(-3, 0, 16 if small else 64)
    h_data, h = (0.08, 0.14) if small else (0.04, 0.08)
    differences, truths, centres = simulated(count, h_data, h)
    start = time.perf_counter()
    arrays = {prior: problem_arrays(h, prior, differences, truths, centres) for prior in PRIORS}
    setup = time.perf_counter() - start
    sweep(arrays, hyperparameters)  # compile
    start = time.perf_counter()
    figures = sweep(arrays, hyperparameters)
    points = len(PRIORS) * len(hyperparameters) * count
    timing = [{"where": f"this process ({len(jax.devices())} device(s))", "points": points,
               "seconds": time.perf_counter() - start, "setup_seconds": setup}]  # fmt: skip
    if not small:
        start = time.perf_counter()
        clustered = sweep(arrays, hyperparameters, workers=2)
        timing.append({"where": "Dask LocalCluster, 2 worker processes", "points": points,
                       "seconds": time.perf_counter() - start, "setup_seconds": setup})  # fmt: skip
        assert all(np.allclose(clustered[p], figures[p], rtol=1e-10, atol=1e-12) for p in PRIORS)
    for row in timing:
        row["microseconds_per_point"] = 1e6 * row["seconds"] / row["points"]
    rows = [
        {"prior": prior, "hyperparameter": float(lam), "scene": s, "correlation": float(f[k, s, 0]),
         "amplitude_error": float(f[k, s, 1]), "position_error_m": float(f[k, s, 2])}
        for prior, f in figures.items() for k, lam in enumerate(hyperparameters) for s in range(count)
    ]  # fmt: skip
    best = {prior: float(hyperparameters[np.argmax(np.median(f[..., 0], axis=1))]) for prior, f in figures.items()}
    files = [
        write_table(folder / "sweep.csv", rows),
        write_table(folder / "sweep_timing.csv", timing),
        _plot(folder / "sweep.png", figures, hyperparameters),
    ]
    statements = [
        f"{prior}: the median correlation peaks at hyperparameter {value:.3g}" for prior, value in best.items()
    ]
    statements += [f"{row['where']}: {row['microseconds_per_point']:.1f} us per point" for row in timing]
    statements.append(f"machine: {machine()}")
    return Findings(values={"best": best, "timing": timing}, statements=tuple(statements), files=tuple(files))


def _plot(path: Path, figures: dict[str, np.ndarray], hyperparameters: np.ndarray) -> Path:
    figure, ax = plt.subplots(figsize=(6, 4))
    for prior, f in figures.items():
        median = np.median(f[..., 0], axis=1)
        low, high = np.percentile(f[..., 0], [25, 75], axis=1)
        (line,) = ax.semilogx(hyperparameters, median, label=prior)
        ax.fill_between(hyperparameters, low, high, color=line.get_color(), alpha=0.2)
    ax.set_xlabel("hyperparameter")
    ax.set_ylabel("correlation with the truth (median, quartiles)")
    ax.set_title("Random touches at medium noise, one-step imaging")
    ax.legend()
    return save_figure(figure, path)


STUDY = Study(name="sweep", figure="-", title="scenes x priors x hyperparameters, batched, sharded, on Dask", run=run)
