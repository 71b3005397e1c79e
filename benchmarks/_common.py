"""Helpers shared by the benchmark scripts: meshes of a given size, Markdown tables, formats, and
the child processes that measure one mesh each."""

from __future__ import annotations

import json


def disc_with_about(n_triangles: int):
    """A unit disc (16 electrodes of width 0.2) with about `n_triangles` triangles (within 8%)."""
    import diffeit as de

    h = 2.7 / n_triangles**0.5
    for _ in range(4):
        mesh = de.mesh.disc(16, electrode_width=0.2, h=h)
        if abs(mesh.n_elements / n_triangles - 1) < 0.08:
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
