"""The catalogue of named candidate effects the gap workflow fits.

Each candidate is one physically meaningful augmentation of the reference with
one to three parameters, fitted in log space within bounds. ``param_drift`` and
``gain_mismatch`` give one candidate per parameter (the parameter name travels
in the fitted params).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..plant.effects import GAIN_KEYS
from ..plant.parameters import PASSIVE_KEYS, PlantParameters


@dataclasses.dataclass
class Candidate:
    """One effect hypothesis: which effect, which of its parameters are fitted, their bounds."""

    name: str
    keys: tuple
    lower: tuple
    upper: tuple
    fixed: dict = dataclasses.field(default_factory=dict)
    main: str = ""  # the parameter whose accuracy matters most
    label: str = ""

    def settings(self, values) -> dict:
        """Effect settings ``{name: {param: value}}`` for fitted values."""
        params = dict(self.fixed)
        params.update({k: float(v) for k, v in zip(self.keys, values)})
        return {self.name: params}

    nominal: tuple = ()  # where a drift/mismatch candidate starts (the nameplate value)
    points: int = 3  # screening points of a bounds-spanning grid
    scale_of: str = ""  # limit candidates: the reference signal whose observed maximum scales the grid

    def grid(self, context: dict) -> list[np.ndarray]:
        """Screening values. Limits: fractions of the largest value the reference reaches in the data
        (a limit above it would be invisible); others: log-spaced across the bounds."""
        if self.scale_of and context.get(self.scale_of):
            top = context[self.scale_of]
            # a hidden limit can sit far below what the reference reaches: geometric fractions
            first = [np.clip(f * top, self.lower[0], self.upper[0]) for f in (0.04, 0.12, 0.35, 0.8)]
            rest = [np.sqrt(np.multiply(self.lower[1:], self.upper[1:]))] if len(self.keys) > 1 else []
            return [np.array([v, *np.ravel(rest)]) if rest else np.array([v]) for v in first]
        lo, hi = np.log(self.lower), np.log(self.upper)
        return [np.exp(lo + (hi - lo) * f) for f in np.linspace(0.25, 0.75, self.points)]


def catalogue(params: PlantParameters) -> list[Candidate]:
    """All candidates for a plant reference with nameplate ``params``."""
    cands = [
        Candidate("current_limit", ("imax", "kaw"), (0.2, 0.5), (20.0, 200.0), main="imax", scale_of="ilref_max"),
        Candidate("current_clamp", ("imax_d", "imax_q"), (0.05, 0.05), (20.0, 20.0), main="imax_d",
                  scale_of="ilref_axis_max"),
        Candidate("voltage_limit", ("vmax", "kaw"), (0.3, 0.5), (3.0, 200.0), main="vmax", scale_of="vi_max"),
        # first- and second-order Padé: the information criterion picks the one the data supports
        # (a dense grid: a delay can push the LCL resonance unstable, and the fit is multimodal there)
        Candidate("delay", ("td",), (1e-5,), (2e-3,), fixed={"order": 1.0}, main="td", label="delay", points=9),
        Candidate("delay", ("td",), (1e-5,), (2e-3,), fixed={"order": 2.0}, main="td", label="delay (Padé 2)",
                  points=9),
        Candidate("virtual_impedance", ("r", "x"), (1e-4, 1e-4), (1.0, 1.0), main="x", label="virtual_impedance"),
        Candidate("virtual_impedance", ("i_th", "k_r"), (0.1, 1e-3), (10.0, 5.0), main="k_r",
                  label="virtual_impedance (current-limiting)", scale_of="ig_max"),
        Candidate("frequency_limit", ("dw_max",), (1e-5,), (0.1,), main="dw_max", scale_of="dw_max"),
    ]
    for key in PASSIVE_KEYS:
        nominal = getattr(params, key)
        lo, hi = (nominal / 5, nominal * 5) if nominal > 0 else (1e-4, 0.5)
        cands.append(Candidate("param_drift", (key,), (lo,), (hi,), main=key, label=f"param_drift.{key}",
                               nominal=(max(nominal, 1e-3),)))
    for key in GAIN_KEYS:
        nominal = getattr(params, key)
        lo, hi = (nominal / 10, nominal * 10) if nominal > 0 else (1e-3, 10.0)
        cands.append(Candidate("gain_mismatch", (key,), (lo,), (hi,), main=key, label=f"gain_mismatch.{key}",
                               nominal=(max(nominal, 1e-3),)))
    for c in cands:
        c.label = c.label or c.name
    return cands
