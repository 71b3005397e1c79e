"""Helpers shared by the benchmark scripts: meshes of a given size, Markdown tables, formats, and
the child processes that measure one mesh each."""

from __future__ import annotations

import argparse
import datetime
import io
import json
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import jax

# diffeit computes in float64; every benchmark process says so before building a model.
jax.config.update("jax_enable_x64", True)


def disc_with_about(n_triangles: int):
    """A unit disc (16 electrodes of width 0.2) with about `n_triangles` triangles (within 8%)."""
    import diffeit as de

    return with_about(lambda h: de.mesh.disc(16, electrode_width=0.2, h=h), n_triangles, 2.7 / n_triangles**0.5)


def with_about(make: Callable[[float], object], n_triangles: int, h: float, tolerance: float = 0.08, tries: int = 4):
    """`make(h)` with the mesh size h tuned from the guess `h` until the mesh has about
    `n_triangles` triangles (within `tolerance`), in at most `tries` meshes."""
    for _ in range(tries):
        mesh = make(h)
        if abs(mesh.n_elements / n_triangles - 1) < tolerance:
            break
        h *= (mesh.n_elements / n_triangles) ** 0.5
    return mesh


def format_seconds(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    if seconds < 1e-3:
        return f"{seconds * 1e6:.0f} us"
    return f"{seconds * 1e3:.1f} ms" if seconds < 1 else f"{seconds:.2f} s"


def fraction(ours: float | None, theirs: float | None) -> str:
    """ours / theirs as "1/N" (ours N times faster), or "Nx" when ours is slower."""
    if ours is None or theirs is None:
        return "-"
    return f"1/{theirs / ours:.0f}" if theirs >= ours else f"{ours / theirs:.1f}x"


def relative(seconds: float | None, reference: float | None) -> str:
    """time / reference as "0.50x" (twice as fast)."""
    if seconds is None or reference is None:
        return "-"
    ratio = seconds / reference
    return f"{ratio:.2f}x" if ratio < 10 else f"{ratio:.0f}x"


def last_json(output: str) -> dict:
    """The JSON object a child process printed last."""
    return json.loads(output.strip().splitlines()[-1])


# The environment variables that set thread counts; the benchmarks print which were set.
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "XLA_FLAGS")


def blas_environment(environment: dict[str, str], blas_threads: int | None) -> dict[str, str]:
    """`environment` with the BLAS thread count of the measuring processes set, when given."""
    environment = dict(environment)
    if blas_threads:
        for variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            environment[variable] = str(blas_threads)
    return environment


class MarkdownTable:
    """A Markdown table printed a row at a time (rows appear while a long benchmark runs)."""

    def __init__(self, columns: list[str]) -> None:
        self.columns = columns
        print(self._line(columns))
        print(self._line(["---"] * len(columns)))

    def row(self, cells: list[str]) -> None:
        if len(cells) != len(self.columns):
            raise ValueError(f"{len(cells)} cells for {len(self.columns)} columns")
        print(self._line(cells), flush=True)

    @staticmethod
    def _line(cells: list[str]) -> str:
        return "| " + " | ".join(cells) + " |"


def cpu_name() -> str:
    """The processor's model name where the system tells it (Linux), and its architecture."""
    architecture = platform.machine() or platform.processor() or "unknown architecture"
    try:
        with open("/proc/cpuinfo") as file:
            names = [line.split(":", 1)[1].strip() for line in file if line.startswith("model name")]
    except OSError:
        names = []
    return f"{names[0]} ({architecture})" if names else architecture


def describe() -> dict:
    """The machine and the software, as the header line shows them (run in a child process, so
    that the parent never initialises an accelerator that the children need)."""
    import importlib.metadata

    import jax
    import numpy as np

    try:
        pyeit_version = importlib.metadata.version("pyeit")
    except importlib.metadata.PackageNotFoundError:
        pyeit_version = None
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        blas = f"{blas['name']} {blas['version']}"
    except Exception:  # the layout of NumPy's build information is not an API
        blas = "unknown BLAS"
    device = jax.devices()[0]
    from threadpoolctl import threadpool_info

    import diffeit  # noqa: F401 (loads SciPy's BLAS beside NumPy's, as the measuring processes do)

    blas_pools = [pool for pool in threadpool_info() if pool["user_api"] == "blas"]
    pools = [f"{pool['internal_api']} {pool['num_threads']}" for pool in blas_pools]
    variables = [f"{name}={os.environ[name]}" for name in THREAD_VARIABLES if name in os.environ]
    return {
        "processor": cpu_name(),
        "cpus": os.cpu_count(),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "jax": jax.__version__,
        "numpy": np.__version__,
        "blas": blas,
        "device": device.device_kind,
        "platform": device.platform,
        "pyeit": pyeit_version,
        "threads": f"BLAS pools found: {', '.join(pools) or 'none'} threads; "
        + (f"set: {' '.join(variables)}" if variables else "no thread variables set"),
    }


def describe_machine(script: str, blas_threads: int | None) -> dict:
    """`describe()` run in a child process of `script` (with `--describe`) under the measuring
    processes' BLAS setting, plus the load average at the start and the BLAS thread count."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    command = [sys.executable, script, "--describe"]
    environment = blas_environment(os.environ, blas_threads)
    machine = last_json(subprocess.run(command, check=True, capture_output=True, text=True, env=environment).stdout)
    machine.update(load_average=load, blas_threads=blas_threads)
    return machine


def machine_line(machine: dict, *, with_pyeit: bool) -> str:
    """The header line naming the machine, the device and the software of a run."""
    load = machine["load_average"]
    return (
        f"machine: {machine['processor']}, {machine['cpus']} CPUs"
        + (f" (load average {load:.1f} at the start)" if load is not None else "")
        + f", {machine['python']}, jax {machine['jax']}, device {machine['device']} ({machine['platform']})"
        + f", NumPy {machine['numpy']} ({machine['blas']})"
        + (f", pyEIT {machine['pyeit']}" if machine["pyeit"] and with_pyeit else "")
        + f"; {machine['threads']}"
    )


def driver_arguments(parser: argparse.ArgumentParser, sizes: list[int]) -> None:
    """The options every per-mesh benchmark takes: sizes, repeats, BLAS threads, JSON output,
    and the two internal ones its child processes are started with."""
    parser.add_argument("--sizes", type=int, nargs="+", default=sizes, help="about how many triangles")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per median (after a warm-up call)")
    parser.add_argument(
        "--blas-threads",
        type=int,
        metavar="N",
        help="run the measurements with N BLAS/OpenMP threads (default: the environment's setting)",
    )
    parser.add_argument("--json", metavar="PATH", help="also save the machine and the raw rows as JSON")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: run one size, print JSON
    parser.add_argument("--describe", action="store_true", help=argparse.SUPPRESS)  # internal: the machine


def child_work(options: argparse.Namespace, run_one: Callable[[int, argparse.Namespace], dict]) -> bool:
    """Do a child process's work (`--describe` or `--one SIZE`, printing JSON); False in the parent."""
    if options.describe:
        print(json.dumps(describe()))
        return True
    if options.one:
        print(json.dumps(run_one(options.one, options)))
        return True
    return False


def measure_sizes(
    options: argparse.Namespace, command: Callable[[int], list[str]]
) -> Iterator[tuple[dict | None, str | None]]:
    """Each size of `options.sizes` measured in a process of its own (`command(size)`), under the
    chosen BLAS threads: (the row it printed, None), or (None, why it failed)."""
    environment = blas_environment(os.environ, options.blas_threads)
    for size in options.sizes:
        child = subprocess.run(command(size), capture_output=True, text=True, env=environment)
        if child.returncode != 0:
            tail = child.stderr.strip().splitlines()[-1:] or ["no output"]
            yield None, f"size {size} failed (exit status {child.returncode}): {tail[0]}"
        else:
            yield last_json(child.stdout), None


def save_json(options: argparse.Namespace, machine: dict, rows: list[dict]) -> None:
    """The machine, the options and the raw rows, to `--json` when given."""
    if options.json:
        with open(options.json, "w") as file:
            settings = {key: value for key, value in vars(options).items() if key not in ("one", "describe", "json")}
            json.dump({"machine": machine, "options": settings, "rows": rows}, file, indent=1)


# Where each benchmark's tables go: a Markdown file the documentation includes (docs/benchmarks.md).
TABLES = Path(__file__).resolve().parents[1] / "docs" / "benchmarks"


class _Tee(io.TextIOBase):
    """Writes to the terminal and keeps a copy."""

    def __init__(self, stream) -> None:
        self.stream, self.copy = stream, io.StringIO()

    def write(self, text: str) -> int:
        self.copy.write(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()


def record_output() -> _Tee:
    """From here on, what the benchmark prints goes to the terminal and is kept for
    `write_tables` (the child processes' output is their own)."""
    tee = _Tee(sys.stdout)
    sys.stdout = tee
    return tee


def skin_benchmark(
    parser: argparse.ArgumentParser, script: str, *, seeds: int | None = None, test: int | None = None
) -> tuple[argparse.Namespace, _Tee] | None:
    """Start a benchmark of simulated skins (calibration, touches, rest anchors) run as `script`:
    parse its options, with the internal `--describe` (and `--seeds`, the simulated sessions, and
    `--test`, the presses errors are measured on, with these defaults when given). In the child
    that describes the machine,
    print the description and return None; else leave out diffeit's calibration warnings, start
    keeping what it prints (`record_output`), print the machine line, and return the options and
    what is kept, for `write_tables`."""
    import warnings

    parser.add_argument("--describe", action="store_true", help=argparse.SUPPRESS)  # internal: the machine
    if seeds is not None:
        parser.add_argument("--seeds", type=int, default=seeds, help="simulated sessions (seeds 0 to N-1)")
    if test is not None:
        parser.add_argument("--test", type=int, default=test, help="presses the errors are measured on")
    options = parser.parse_args()
    if options.describe:
        print(json.dumps(describe()))
        return None
    import diffeit as de

    warnings.simplefilter("ignore", de.calibration.CalibrationWarning)
    machine = describe_machine(script, None)
    printed = record_output()
    print(machine_line(machine, with_pyeit=False))
    return options, printed


def write_tables(name: str, printed: _Tee | str, *, date: str | None = None, command: str | None = None) -> Path:
    """Write what a benchmark printed (its machine line, tables and notes) as the Markdown file
    docs/benchmarks/NAME.md, which the documentation's Benchmarks page includes; stops
    `record_output`'s copy. The file names the date (UTC) and the command of the run; every
    line that is not a table row becomes a paragraph of its own."""
    if isinstance(printed, _Tee):
        if sys.stdout is printed:
            sys.stdout = printed.stream
        printed = printed.copy.getvalue()
    date = date or datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    command = command or shlex.join(["python", os.path.relpath(sys.argv[0], TABLES.parents[1]), *sys.argv[1:]])
    blocks: list[str] = [f"Run of {date}: `{command}`"]
    table: list[str] = []
    for line in [*printed.splitlines(), ""]:
        line = line.rstrip()
        if line.startswith("|"):
            table.append(line)
            continue
        if table:
            blocks.append("\n".join(table))
            table = []
        if line:
            blocks.append(line)
    TABLES.mkdir(parents=True, exist_ok=True)
    path = TABLES / f"{name}.md"
    header = "<!-- Written by benchmarks/_common.py write_tables: `make bench` replaces it. -->"
    path.write_text(header + "\n\n" + "\n\n".join(blocks) + "\n")
    return path
