"""Named, switchable effects of the virtual HIL (all off by default).

Each effect is a physically meaningful departure from the ideal average model,
with a few parameters. The registry below is the single home of the names, the
defaults and the meaning of every parameter; the plant reads it, the CLI lists
it, and the gap workflow fits these same parameters.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

from .parameters import PASSIVE_KEYS, ParameterError

#: controller gains that `gain_mismatch` may change in the plant
GAIN_KEYS = ("KpV", "KiV", "KpC", "KiC", "mp", "mq", "F", "wc")


@dataclasses.dataclass(frozen=True)
class EffectSpec:
    """Definition of one named effect: its parameters, defaults and meanings."""

    name: str
    description: str
    defaults: Mapping[str, float]
    meanings: Mapping[str, str]
    positive: tuple[str, ...] = ()  # parameters that must be > 0
    # values under which the effect leaves every signal as it is (the same bits), so that plants
    # with and without it can be simulated as one stack (plant.stack); None: it changes the plant's
    # parameters instead (param_drift, gain_mismatch) or its states (delay)
    neutral: Mapping[str, float] | None = None


EFFECTS: dict[str, EffectSpec] = {
    spec.name: spec
    for spec in (
        EffectSpec(
            "current_limit",
            "magnitude limit of the current reference il* with back-calculation anti-windup "
            "of the voltage-PI integrators",
            {"imax": 1.2, "kaw": 10.0},
            {"imax": "limit of |il*| (p.u.)", "kaw": "back-calculation gain (1/s per p.u.)"},
            positive=("imax",),
            neutral={"imax": math.inf, "kaw": 0.0},
        ),
        EffectSpec(
            "current_clamp",
            "per-axis clamp of the current reference: |il*_d| <= imax_d, |il*_q| <= imax_q",
            {"imax_d": 1.0, "imax_q": 1.0},
            {"imax_d": "clamp of |il*_d| (p.u.)", "imax_q": "clamp of |il*_q| (p.u.)"},
            positive=("imax_d", "imax_q"),
            neutral={"imax_d": math.inf, "imax_q": math.inf},
        ),
        EffectSpec(
            "voltage_limit",
            "magnitude limit of the inverter voltage command (modulation saturation), with "
            "back-calculation anti-windup of the current-PI integrators",
            {"vmax": 1.1, "kaw": 10.0},
            {"vmax": "limit of |vi*| (p.u.)", "kaw": "back-calculation gain (1/s per p.u.)"},
            positive=("vmax",),
            neutral={"vmax": math.inf, "kaw": 0.0},
        ),
        EffectSpec(
            "delay",
            "computation + PWM delay of the inverter voltage, Padé approximation on each dq axis "
            "(adds 2·order hidden states)",
            {"td": 1.5e-4, "order": 1.0},
            {"td": "delay (s)", "order": "Padé order, 1 or 2"},
            positive=("td",),
        ),
        EffectSpec(
            "virtual_impedance",
            "virtual impedance on the voltage reference: constant r + jx, plus a current-limiting "
            "part that acts when |ig| exceeds a threshold (R = k_r·(|ig| - i_th), X = xr·R)",
            {"r": 0.0, "x": 0.0, "i_th": 1.0, "k_r": 0.0, "xr": 5.0},
            {"r": "constant virtual resistance (p.u.)", "x": "constant virtual reactance (p.u.)",
             "i_th": "threshold of |ig| for the current-limiting part (p.u.)",
             "k_r": "virtual resistance per p.u. of current above the threshold",
             "xr": "X/R ratio of the current-limiting part"},
            neutral={"r": 0.0, "x": 0.0, "i_th": math.inf, "k_r": 0.0, "xr": 0.0},
        ),
        EffectSpec(
            "param_drift",
            "the plant's passive components differ from the nameplate the controller uses "
            "(values are the plant's actual values; keys not given stay at nameplate)",
            {},
            {key: f"actual {key} of the plant (p.u.)" for key in PASSIVE_KEYS},
        ),
        EffectSpec(
            "gain_mismatch",
            "the controller runs with gains that differ from its documentation "
            "(values are the gains actually used; keys not given stay at nameplate)",
            {},
            {key: f"actual {key} of the controller" for key in GAIN_KEYS},
        ),
        EffectSpec(
            "frequency_limit",
            "limit of the droop frequency deviation: |w - wset| <= dw_max",
            {"dw_max": 0.005},
            {"dw_max": "largest frequency deviation (p.u.)"},
            positive=("dw_max",),
            neutral={"dw_max": math.inf},
        ),
    )
}


def effect_names() -> list[str]:
    """Names of the effects the virtual HIL knows, in a stable order."""
    return list(EFFECTS)


def resolve_effects(effects: Mapping[str, Mapping[str, Any]] | None) -> dict[str, dict[str, float]]:
    """Validate effect settings and fill in defaults.

    Parameters
    ----------
    effects : mapping or None
        ``{name: {param: value}}``; an empty inner mapping switches the effect
        on with its defaults.

    Returns
    -------
    dict
        ``{name: {param: float}}`` with every parameter of each active effect.

    Raises
    ------
    ParameterError
        Unknown effect or parameter name, or a value that is not a valid number.
    """
    resolved: dict[str, dict[str, float]] = {}
    for name, values in (effects or {}).items():
        if name not in EFFECTS:
            raise ParameterError(f"unknown effect {name!r}; known effects: {effect_names()}")
        spec = EFFECTS[name]
        values = dict(values or {})
        allowed = set(spec.meanings)
        unknown = sorted(set(values) - allowed)
        if unknown:
            raise ParameterError(f"effect {name}: unknown parameter(s) {unknown}; known: {sorted(allowed)}")
        merged = dict(spec.defaults)
        for key, value in values.items():
            try:
                merged[key] = float(value)
            except (TypeError, ValueError):
                raise ParameterError(f"effect {name}: parameter {key}: not a number: {value!r}") from None
            if not math.isfinite(merged[key]):
                raise ParameterError(f"effect {name}: parameter {key}: must be finite, got {value!r}")
        for key in spec.positive:
            if merged[key] <= 0:
                raise ParameterError(f"effect {name}: parameter {key} must be > 0, got {merged[key]}")
        if name == "delay" and merged["order"] not in (1.0, 2.0):
            raise ParameterError(f"effect delay: parameter order must be 1 or 2, got {merged['order']}")
        if name == "param_drift":
            for key, value in merged.items():
                if value < 0 or (key in ("Lf", "Cf", "Lg") and value == 0):
                    raise ParameterError(f"effect param_drift: {key} must be positive, got {value}")
        if name == "gain_mismatch":
            for key, value in merged.items():
                if value < 0 or (key == "wc" and value == 0):
                    raise ParameterError(f"effect gain_mismatch: {key} must be positive, got {value}")
        resolved[name] = merged
    return resolved


def parse_effect_assignments(names: list[str], assignments: list[str]) -> dict[str, dict[str, float]]:
    """Turn CLI ``--effect NAME`` and ``--effect-param NAME.KEY=VALUE`` into settings.

    An assignment for an effect not named with ``--effect`` switches it on too.
    """
    effects: dict[str, dict[str, Any]] = {name: {} for name in names}
    for text in assignments:
        head, sep, value = text.partition("=")
        name, dot, key = head.partition(".")
        if not sep or not dot or not name or not key or not value:
            raise ParameterError(f"--effect-param {text!r}: expected NAME.KEY=VALUE, e.g. current_limit.imax=1.1")
        effects.setdefault(name, {})[key] = value
    return resolve_effects(effects)
