"""diffeit's studies: the tactile-skin dissertation's Chapter 5 reproduced, each a module with a
`STUDY` (`experiments.Study`) that writes its figures (PNG) and tables (CSV) into a folder and
returns its headline findings.

Run one with `diffeit experiment NAME [--small] [-o DIR]` or `experiments.run(NAME, DIR)`;
`diffeit experiment --list` names them. `--small` is the quick mode CI runs: fewer settings
and coarser meshes, the same findings asserted. The full modes' outputs are committed under
`experiments/results/`; `experiments/README.md` discusses them study by study.
"""

from __future__ import annotations

from pathlib import Path

from ._study import Findings, Study
from .accuracy_time import STUDY as _ACCURACY_TIME
from .background import STUDY as _BACKGROUND
from .curvature import STUDY as _CURVATURE
from .hyperparameter import STUDY as _HYPERPARAMETER
from .memory import STUDY as _MEMORY
from .metrics import STUDY as _METRICS
from .scaling import STUDY as _SCALING
from .size import STUDY as _SIZE
from .stimuli import STUDY as _STIMULI
from .sweep import STUDY as _SWEEP

STUDIES: dict[str, Study] = {
    study.name: study
    for study in (
        _METRICS,
        _HYPERPARAMETER,
        _STIMULI,
        _SCALING,
        _BACKGROUND,
        _MEMORY,
        _SIZE,
        _ACCURACY_TIME,
        _SWEEP,
        _CURVATURE,
    )
}


def run(name: str, output: str | Path, *, small: bool = False, progress: bool = True) -> Findings:
    """Run the study `name` (a key of `STUDIES`), writing into the folder `output` (created when
    missing); returns its findings. Raises `ValueError` for an unknown name."""
    if name not in STUDIES:
        raise ValueError(f"no study {name!r}; the studies are {', '.join(STUDIES)}")
    folder = Path(output)
    folder.mkdir(parents=True, exist_ok=True)
    return STUDIES[name].run(folder, small=small, progress=progress)


__all__ = ["STUDIES", "Findings", "Study", "run"]
