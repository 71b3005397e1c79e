"""The model options of the commands that reconstruct frames (`reconstruct`, `live`): defined
once, with their defaults, and the sheet, forward model and one-step solver they describe."""

from __future__ import annotations

import argparse
import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..forward import ForwardModel
    from ..mesh import Mesh
    from ..protocol import Protocol


@dataclasses.dataclass(frozen=True, kw_only=True)
class ModelSettings:
    """What the model options say, each the option when given, else a default.

    - `prior`: the prior of `diffeit.inverse.OneStep`, by name.
    - `hyperparameter`: unit-free, or the name of a selection method of
      `diffeit.inverse.select_hyperparameter` (where the command offers them).
    - `background`: background conductivity, S/sq.
    - `contact_impedance`: ohm m.
    - `h`: element size (m) of the unit-disc mesh of frames that come without their sheet.
    """

    prior: str = "noser"
    hyperparameter: float | str = 0.1
    background: float = 1.0
    contact_impedance: float = 0.01
    h: float = 0.08

    @classmethod
    def from_arguments(
        cls, arguments: argparse.Namespace, *, methods: tuple[str, ...] = (), **fallbacks: float
    ) -> ModelSettings:
        """The settings the parsed options name. An option not given takes its value from
        `fallbacks` (say a simulated file's background), else the default. `methods`: the
        hyperparameter selection methods the command accepts besides numbers. Raises
        `ValueError` for a hyperparameter that is neither."""
        given = {field.name: getattr(arguments, field.name) for field in dataclasses.fields(cls)}
        settings = {**fallbacks, **{name: value for name, value in given.items() if value is not None}}
        if "hyperparameter" in settings:
            settings["hyperparameter"] = _hyperparameter(settings["hyperparameter"], methods)
        return cls(**settings)

    def unit_disc(self, n_electrodes: int) -> Mesh:
        """The sheet of frames that name none: a unit disc with `n_electrodes` electrodes."""
        from ..mesh import disc

        return disc(n_electrodes, electrode_width=min(0.2, math.pi / n_electrodes), h=self.h)

    def model(self, mesh: Mesh, protocol: Protocol) -> ForwardModel:
        """The forward model on `mesh` under `protocol`, with the settings' contact impedance."""
        from ..forward import ForwardModel

        return ForwardModel(mesh, protocol, contact_impedance=self.contact_impedance)

    def hyperparameter_at(self, model: ForwardModel, background: float | np.ndarray) -> float:
        """The hyperparameter as a number: "auto" (the `live` command, which cannot see the frames
        to come) is the value of noise figure 0.5 for `model` at `background` (S/sq), which needs
        no frames (`diffeit.inverse.select_hyperparameter`)."""
        if self.hyperparameter != "auto":
            return float(self.hyperparameter)
        from ..inverse import select_hyperparameter

        silent = np.zeros((1, model.n_measurements))
        return select_hyperparameter(model, silent, "noise_figure", prior=self.prior, background=background).value


_DEFAULTS = ModelSettings()


def add_model_options(
    parser: argparse.ArgumentParser, *, methods: tuple[str, ...] = (), hyperparameter_default: float | str | None = None
) -> None:
    """Add --prior, --hyperparameter, --background, --contact-impedance and --h to `parser`,
    all defaulting to None: `ModelSettings.from_arguments` fills in the defaults. `methods`:
    the hyperparameter selection methods the command accepts; `hyperparameter_default`: the
    command's own default when it is not the settings' (the command passes it as a fallback)."""
    choices = f", or a method choosing it from the data: {', '.join(methods)}" if methods else ""
    default = _DEFAULTS.hyperparameter if hyperparameter_default is None else hyperparameter_default
    parser.add_argument("--prior", help=f"prior of diffeit.inverse.OneStep (default {_DEFAULTS.prior})")
    parser.add_argument("--hyperparameter", help=f"unit-free regularisation weight (default {default}){choices}")
    parser.add_argument(
        "--background", type=float, help=f"background conductivity, S/sq (default {_DEFAULTS.background})"
    )
    parser.add_argument(
        "--contact-impedance", type=float, help=f"contact impedance, ohm m (default {_DEFAULTS.contact_impedance})"
    )
    parser.add_argument(
        "--h",
        type=float,
        help=f"element size of the unit-disc mesh of frames without their sheet (default {_DEFAULTS.h})",
    )


def _hyperparameter(value: float | str, methods: tuple[str, ...]) -> float | str:
    """--hyperparameter: a number, or one of `methods`."""
    if value in methods:
        return value
    try:
        return float(value)
    except ValueError:
        names = "".join(f" or {method}" for method in methods)
        raise ValueError(f"--hyperparameter must be a number{names}; got {value!r}") from None
