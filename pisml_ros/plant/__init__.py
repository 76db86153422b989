"""Virtual HIL: the default grid-forming inverter, its effects, scenarios and noise."""
from .effects import EFFECTS, effect_names, resolve_effects
from .model import INPUT_NAMES, STATE_NAMES, EquilibriumError, InverterPlant
from .parameters import PARAMETER_KEYS, ParameterError, PlantParameters, load_parameters

__all__ = [
    "EFFECTS", "effect_names", "resolve_effects", "INPUT_NAMES", "STATE_NAMES", "EquilibriumError",
    "InverterPlant", "PARAMETER_KEYS", "ParameterError", "PlantParameters", "load_parameters",
]
