"""Signal roles: which column is the angle, the dq voltage/current pairs, the grid inputs...

Configuration, not code: another inverter type with other names is identified by
giving its roles (YAML ``roles:`` section or :meth:`SignalRoles.from_mapping`).
"""
from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence


class RoleError(ValueError):
    """Roles that name signals the data does not have, or are malformed."""


@dataclasses.dataclass(frozen=True)
class SignalRoles:
    """Roles of the signals of one inverter.

    Attributes
    ----------
    angle : str or None
        Angle of the inverter frame relative to the grid.
    grid_magnitude, grid_phase : str or None
        Grid voltage inputs (grid terms are ``mag*cos(phase - angle)``, ``mag*sin(phase - angle)``).
    voltage : (str, str)
        dq voltage pair used for the power terms.
    current : (str, str)
        dq current pair used for the power terms (p = v_d·i_d + v_q·i_q, q = v_q·i_d − v_d·i_q).
    other_currents : tuple of (str, str)
        Further dq current pairs (enter the products of the extended library).
    power : tuple of str
        Filtered-power (droop) states.
    integrators : tuple of str
        Controller integrator states, a loop's d and q axes next to each other (the voltage loop's
        d, q, then the current loop's d, q: :meth:`integrator_loops`).
    frequency : str or None
        The state the dq frame's frequency follows (the droop power state of a grid-forming
        inverter, a PLL frequency state otherwise): rotating-frame cross-coupling makes each dq
        signal's derivative carry ``frequency * <other axis>`` products. None: no such terms.
        Kept only where the data tell them apart from the plain signals
        (``IdentConfig.coupling_min_separation``).
    """

    angle: str | None = "delta"
    grid_magnitude: str | None = "ug"
    grid_phase: str | None = "theta_g"
    voltage: tuple = ("vc_d", "vc_q")
    current: tuple = ("ig_d", "ig_q")
    other_currents: tuple = (("il_d", "il_q"),)
    power: tuple = ("Pf", "Qf")
    integrators: tuple = ("phi_d", "phi_q", "gamma_d", "gamma_q")
    frequency: str | None = "Pf"

    @classmethod
    def from_mapping(cls, values: Mapping) -> "SignalRoles":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise RoleError(f"roles: unknown key(s) {unknown}; known: {sorted(known)}")
        clean = dict(values)
        for key in ("voltage", "current"):
            if key in clean:
                clean[key] = tuple(clean[key])
        if "other_currents" in clean:
            clean["other_currents"] = tuple(tuple(pair) for pair in clean["other_currents"])
        for key in ("power", "integrators"):
            if key in clean:
                clean[key] = tuple(clean[key])
        return cls(**clean)

    def check(self, states: Sequence[str], inputs: Sequence[str]) -> None:
        """Raise RoleError naming any role signal the data lacks."""
        names = set(states) | set(inputs)
        wanted = [self.angle, self.grid_magnitude, self.grid_phase, *self.dq_signals(), *self.power,
                  *self.integrators, self.frequency]
        missing = [w for w in wanted if w is not None and w not in names]
        if missing:
            raise RoleError(f"roles name signals the data does not have: {missing} (signals: {sorted(names)})")
        for key in ("voltage", "current"):
            if len(getattr(self, key)) != 2:
                raise RoleError(f"roles: {key} must be a dq pair, got {getattr(self, key)}")

    def electrical(self) -> list[str]:
        """Power states and all dq voltage/current signals (the factors of the product terms)."""
        return list(dict.fromkeys([*self.power, *self.dq_signals()]))

    def dq_signals(self) -> list[str]:
        """All dq voltage and current signals (the voltage pair, the current pair, other currents)."""
        out = list(self.voltage) + list(self.current)
        for pair in self.other_currents:
            out += list(pair)
        return list(dict.fromkeys(out))

    def integrator_loops(self) -> list[tuple]:
        """The integrators grouped by control loop: consecutive (d, q) pairs, or one state per loop
        where their number is odd (no pairing can be read from the order then)."""
        names = list(self.integrators)
        if len(names) % 2:
            return [(name,) for name in names]
        return [tuple(names[k:k + 2]) for k in range(0, len(names), 2)]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
