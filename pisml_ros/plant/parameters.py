"""Nameplate parameters of the default grid-forming inverter (virtual HIL).

All values are per unit on the inverter base (ωb = 2π·60 rad/s); the power
filter cut-off ``wc`` is in rad/s. Keys are a contract (DESIGN.md): parameter
files in YAML or JSON use exactly these names.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Mapping

OMEGA_BASE = 2.0 * math.pi * 60.0

#: keys accepted in a parameter file, in the order of the paper's table
PARAMETER_KEYS = (
    "Lf", "Rf", "Cf", "Rd", "Lg", "Rg", "mp", "mq", "wc",
    "KpV", "KiV", "KpC", "KiC", "F", "Pset", "Qset", "Vset", "wset", "wg",
)

#: passive (circuit) parameters: those that `param_drift` may change in the plant
PASSIVE_KEYS = ("Lf", "Rf", "Cf", "Rd", "Lg", "Rg")


class ParameterError(ValueError):
    """A parameter file or value that cannot be used; the message names it."""


@dataclasses.dataclass(frozen=True)
class PlantParameters:
    """Circuit, controller and set-point parameters of the droop inverter."""

    Lf: float = 0.10
    Rf: float = 0.02
    Cf: float = 0.05
    Rd: float = 0.05
    Lg: float = 0.05
    Rg: float = 0.01
    mp: float = 0.05
    mq: float = 0.05
    wc: float = 10.0 * math.pi
    KpV: float = 0.8
    KiV: float = 3.0
    KpC: float = 0.2
    KiC: float = 4.0
    F: float = 0.75
    Pset: float = 0.5
    Qset: float = 0.0
    Vset: float = 1.0
    wset: float = 1.0
    wg: float = 1.0

    def __post_init__(self):
        for key in PARAMETER_KEYS:
            value = getattr(self, key)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise ParameterError(f"parameter {key}: expected a finite number, got {value!r}")
        for key in ("Lf", "Cf", "Lg", "wc"):
            if getattr(self, key) <= 0:
                raise ParameterError(f"parameter {key}: must be > 0, got {getattr(self, key)}")
        for key in ("Rf", "Rd", "Rg"):
            if getattr(self, key) < 0:
                raise ParameterError(f"parameter {key}: must be >= 0, got {getattr(self, key)}")

    def replace(self, **changes: float) -> "PlantParameters":
        """Return a copy with some values changed (unknown keys are an error)."""
        unknown = sorted(set(changes) - set(PARAMETER_KEYS))
        if unknown:
            raise ParameterError(f"unknown parameter(s) {unknown}; known: {list(PARAMETER_KEYS)}")
        return dataclasses.replace(self, **{k: float(v) for k, v in changes.items()})

    def to_dict(self) -> dict[str, float]:
        return {key: float(getattr(self, key)) for key in PARAMETER_KEYS}

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], source: str = "parameters") -> "PlantParameters":
        """Build from a mapping; keys not given keep their defaults."""
        if not isinstance(values, Mapping):
            raise ParameterError(f"{source}: expected a mapping of parameter names to numbers")
        unknown = sorted(set(values) - set(PARAMETER_KEYS))
        if unknown:
            raise ParameterError(f"{source}: unknown parameter(s) {unknown}; known: {list(PARAMETER_KEYS)}")
        clean = {}
        for key, value in values.items():
            try:
                clean[key] = float(value)
            except (TypeError, ValueError):
                raise ParameterError(f"{source}: parameter {key}: not a number: {value!r}") from None
        try:
            return cls(**clean)
        except ParameterError as err:
            raise ParameterError(f"{source}: {err}") from None


def load_parameters(path: str | Path) -> PlantParameters:
    """Load plant parameters from a YAML or JSON file.

    The file holds a flat mapping of the keys in :data:`PARAMETER_KEYS`
    (optionally nested under a top-level ``parameters`` key). Missing keys keep
    the paper's nameplate values.

    Parameters
    ----------
    path : str or Path
        ``.yaml``/``.yml`` or ``.json`` file.

    Returns
    -------
    PlantParameters
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ParameterError(f"{path}: cannot read parameter file ({err.strerror})") from None
    try:
        if path.suffix.lower() == ".json":
            values = json.loads(text)
        else:
            import yaml

            values = yaml.safe_load(text)
    except Exception as err:  # yaml and json raise different types; both are user errors here
        raise ParameterError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'}: "
                             f"{str(err).splitlines()[0]}") from None
    if values is None:
        values = {}
    if isinstance(values, Mapping) and "parameters" in values and isinstance(values["parameters"], Mapping):
        values = values["parameters"]
    return PlantParameters.from_mapping(values, source=str(path))
