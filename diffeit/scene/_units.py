"""Quantities with units in scene files.

A number in a scene file is in the SI unit its field documents (metres, seconds, S/sq, ...).
A string "<number> <unit>" names its unit instead, converted here; a unit of the wrong kind
(a radius in seconds) is an error naming the field. Saved scenes write plain SI numbers.
"""

from __future__ import annotations

import re
from typing import Any

# Each kind of quantity: its SI unit first, then the other units accepted, as factors to SI.
UNITS: dict[str, dict[str, float]] = {
    "length": {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6},
    "time": {"s": 1.0, "ms": 1e-3, "min": 60.0},
    "frequency": {"Hz": 1.0, "kHz": 1e3},
    "sheet conductivity": {"S/sq": 1.0, "mS/sq": 1e-3, "uS/sq": 1e-6},
    "contact impedance": {"ohm m": 1.0, "ohm cm": 1e-2, "ohm mm": 1e-3, "kohm m": 1e3},
    "current": {"A": 1.0, "mA": 1e-3, "uA": 1e-6},
    "voltage": {"V": 1.0, "mV": 1e-3, "uV": 1e-6},
    "voltage rate": {"V/s": 1.0, "mV/s": 1e-3, "uV/s": 1e-6},
    "pressure": {"kPa": 1.0, "Pa": 1e-3, "MPa": 1e3},
    "angle": {"rad": 1.0, "deg": 3.141592653589793 / 180},
    "rate": {"1/s": 1.0, "1/min": 1 / 60},
    "ratio": {"": 1.0, "%": 1e-2},
    "percent": {"%": 1.0},  # a quantity given in percent (noise levels): "0.5 %" is 0.5
    "decibel": {"dB": 1.0},
}
# Sheet resistance is the reciprocal of sheet conductivity: "100 ohm/sq" is 0.01 S/sq.
_SHEET_RESISTANCE = {"ohm/sq": 1.0, "kohm/sq": 1e3}

_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")


def _unit_kind(unit: str) -> str | None:
    if unit in _SHEET_RESISTANCE:
        return "sheet conductivity"
    return next((kind for kind, units in UNITS.items() if unit in units), None)


def quantity(value: Any, kind: str, field: str) -> float:
    """`value` (a number in the SI unit of `kind`, or a string "<number> <unit>") in SI units;
    ValueError naming `field` for anything else."""
    if isinstance(value, bool):
        raise ValueError(f"{field} must be a number (in {next(iter(UNITS[kind])) or 'no unit'}); got {value!r}")
    if isinstance(value, int | float):
        return float(value)
    if not isinstance(value, str):
        raise ValueError(f"{field} must be a number or a string with a unit; got {value!r}")
    match = _QUANTITY.match(value)
    if match is None:
        raise ValueError(f"{field}: cannot read {value!r} as a number with a unit, such as '5 mm'")
    number, unit = float(match.group(1)), match.group(2).replace("Ω", "ohm").replace("*", " ")
    unit = " ".join(unit.split())
    if kind == "sheet conductivity" and unit in _SHEET_RESISTANCE:
        if number <= 0:
            raise ValueError(f"{field}: a sheet resistance must be positive; got {value!r}")
        return 1.0 / (number * _SHEET_RESISTANCE[unit])
    if unit in UNITS[kind]:
        return number * UNITS[kind][unit]
    if not unit:  # a number written as a string: in the SI unit, as a bare number
        return number
    found = _unit_kind(unit)
    accepted = ", ".join(repr(u) for u in UNITS[kind] if u) or "none"
    if kind == "sheet conductivity":
        accepted += ", 'ohm/sq', 'kohm/sq'"
    what = f"a {found}" if found else "an unknown unit"
    raise ValueError(f"{field}: {value!r} is {what}; expected a {kind} (units {accepted})")


def quantities(values: Any, kind: str, field: str) -> list:
    """A (nested) list of quantities, each converted by `quantity`; a single value passes through."""
    if isinstance(values, list | tuple):
        return [quantities(v, kind, f"{field}[{k}]") for k, v in enumerate(values)]
    return quantity(values, kind, field)
