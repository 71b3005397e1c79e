"""The effects a scene can declare, by the names scene files give them."""

from __future__ import annotations

from typing import Any

from ..memory import MemoryParameters
from ._instrument import (
    CommonModeDrift,
    ContactDrift,
    ElectrodePositionError,
    MeasurementNoise,
    OpenElectrodes,
    ReadingGains,
    ReadoutMixing,
)

# Names of the effects in scene files, and their types.
EFFECTS: dict[str, type] = {
    "memory": MemoryParameters,
    "noise": MeasurementNoise,
    "common_mode_drift": CommonModeDrift,
    "contact_drift": ContactDrift,
    "open_electrode": OpenElectrodes,
    "electrode_position_error": ElectrodePositionError,
    "readout_mixing": ReadoutMixing,
    "reading_gains": ReadingGains,
}
EFFECT_NAMES = tuple(EFFECTS)


def effect_name(effect: Any) -> str:
    """The name of `effect` (an instance of a type of `EFFECTS`); ValueError for anything else."""
    for name, kind in EFFECTS.items():
        if isinstance(effect, kind):
            return name
    raise ValueError(f"not an effect: {effect!r}; effects are {EFFECT_NAMES}")
