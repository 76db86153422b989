"""Assembly of several inverter models into one microgrid: a network of buses, lines and loads,
with a grid source, and its equilibrium, linearisation and modes.

Each inverter is any model with ``vector_field(x, u)`` and ``jacobian(x, u, wrt)`` over inputs
(``ug``, ``theta_g``): an identified :class:`~pisml_ros.model.ExplicitModel` (the black box) or a
known analytic one (the virtual HIL's plant with other gains). An inverter sees the voltage of
the bus it is connected to as its grid voltage (magnitude and phase in the network's frame) and
injects its grid-side current, rotated from its own frame by its angle state, into that bus.
This is the paper's system-level use (section 4, the 3-bus microgrid): before a black-box
inverter is connected, its identified equations are put beside the known units and the network,
and the modes of the whole system say whether the connection is safe and which unit takes part
in the weakest mode.

Conventions (those of the virtual HIL, ``../shared/DESIGN.md``): per-unit quantities, time in
seconds, complex dq quantities ``x_D + j·x_Q`` in a frame rotating at the grid frequency ``wg``
(1 p.u.); an inductive branch obeys ``(L/ωb)·di/dt = v_from − v_to − R·i − j·wg·L·i``, a bus
capacitor ``(C/ωb)·dv/dt = Σ i_in − j·wg·C·v``; L and C in p.u. of the base impedance.
Every bus carries a shunt capacitance: it keeps the inductive branches that meet at a bus from
forming an algebraic loop (the inverters' grid-side inductors are inside their models), as in
Pogaku et al. (2007), whose virtual resistor plays the same part. The grid source is an ideal
voltage ``E∠θ`` behind a line; its magnitude and phase are the microgrid's inputs, so the
microgrid is itself a system with ``equilibrium``, ``jacobian`` and ``eigenvalues`` over
(``ug``, ``theta_g``), and everything in :mod:`pisml_ros.analysis` applies to it.

The equilibrium and modes are hand-assembled from the units' own exact Jacobians by the chain
rule (no library assembles a network of arbitrary vector fields), then solved by scipy.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from ..equilibrium import EquilibriumNotFound, root

GRID = "grid"
#: the virtual HIL's base angular frequency (2π·60 rad/s, ``pisml_ros.plant.parameters.OMEGA_BASE``)
DEFAULT_BASE_HZ = 60.0


class MicrogridError(ValueError):
    """A microgrid description that cannot be assembled (names the part and the value)."""


@dataclasses.dataclass(frozen=True)
class Bus:
    """A network node: shunt capacitance ``capacitance`` (p.u., > 0) and an optional load
    ``load_r + j·load_x`` (p.u.; ``load_r`` None: no load; ``load_x`` 0: a resistive load, no state)."""

    name: str
    capacitance: float = 0.05
    load_r: float | None = None
    load_x: float = 0.0


@dataclasses.dataclass(frozen=True)
class Line:
    """An RL branch ``r + j·x`` (p.u., x > 0) from bus ``start`` to bus ``end`` (or ``"grid"``:
    the grid source); its current flows from ``start`` to ``end``."""

    start: str
    end: str
    r: float = 0.01
    x: float = 0.05


@dataclasses.dataclass
class Unit:
    """An inverter at bus ``bus``: ``system`` (``vector_field``, ``jacobian(x, u, wrt)``, state
    names in ``state_names``, inputs ``ug, theta_g``), its angle state ``angle`` (the inverter
    frame's angle in the network frame) and its grid-side current pair ``current`` (injected into
    the bus)."""

    name: str
    system: object
    bus: str
    angle: str = "delta"
    current: tuple = ("ig_d", "ig_q")

    def __post_init__(self):
        names = list(getattr(self.system, "state_names", ()))
        missing = [s for s in (self.angle, *self.current) if s not in names]
        if missing:
            raise MicrogridError(f"unit {self.name!r}: state(s) {missing} not among its states {names}")
        inputs = list(getattr(self.system, "input_names", ("ug", "theta_g")))
        if len(inputs) != 2:
            raise MicrogridError(f"unit {self.name!r}: a unit takes the grid voltage magnitude and phase as its two "
                                 f"inputs, this one has {inputs}")
        self.state_names = tuple(names)
        self.n_states = int(getattr(self.system, "n_states", len(names)))
        if self.n_states != len(names):
            # a plant with hidden states (a delay's Padé states): its full state is what it integrates
            self.state_names = tuple(names) + tuple(getattr(self.system, "hidden_state_names", ()))
        self.i_angle = names.index(self.angle)
        self.i_current = (names.index(self.current[0]), names.index(self.current[1]))


class Microgrid:
    """Inverter models, buses, lines and a grid source assembled into one system.

    Parameters
    ----------
    units : sequence of Unit
    buses : sequence of Bus
    lines : sequence of Line
        At least one ends at ``"grid"``: the grid source pins the frequency (the inverters' angle
        states are relative to a grid at ``wg``, as in their identification), so an islanded
        network has an equilibrium only where its droops happen to balance; it is refused.
    base_hz : float
        Base frequency of the per-unit system (ωb = 2π·base_hz; the virtual HIL's is 60 Hz).
    wg : float
        Frequency of the grid source and of the network frame (p.u.).

    Attributes
    ----------
    state_names : tuple of str
        ``<unit>.<state>`` for every unit, then ``<bus>.v_D``, ``<bus>.v_Q``, ``<bus>.iload_D/Q``
        (inductive loads), ``line<k>.i_D/Q``.
    input_names : tuple of str
        ``ug``, ``theta_g``: the grid source's magnitude and phase.
    """

    input_names = ("ug", "theta_g")

    def __init__(self, units: Sequence[Unit], buses: Sequence[Bus], lines: Sequence[Line],
                 base_hz: float = DEFAULT_BASE_HZ, wg: float = 1.0):
        self.units, self.buses, self.lines = list(units), list(buses), list(lines)
        self.wb = 2.0 * math.pi * float(base_hz)
        self.wg = float(wg)
        if not self.units:
            raise MicrogridError("a microgrid needs at least one unit")
        names = [b.name for b in self.buses]
        if len(set(names)) != len(names) or GRID in names:
            raise MicrogridError(f"bus names must be unique and not {GRID!r}: {names}")
        self.bus_index = {name: k for k, name in enumerate(names)}
        for b in self.buses:
            if not b.capacitance > 0:
                raise MicrogridError(f"bus {b.name!r}: capacitance must be > 0 p.u., got {b.capacitance}")
            if b.load_r is not None and (b.load_r < 0 or b.load_x < 0 or b.load_r + b.load_x <= 0):
                raise MicrogridError(f"bus {b.name!r}: load r={b.load_r}, x={b.load_x} (p.u., both >= 0, not both 0)")
        unit_names = [u.name for u in self.units]
        if len(set(unit_names)) != len(unit_names):
            raise MicrogridError(f"unit names must be unique: {unit_names}")
        for u in self.units:
            if u.bus not in self.bus_index:
                raise MicrogridError(f"unit {u.name!r}: bus {u.bus!r} is not among the buses {names}")
        for k, line in enumerate(self.lines):
            for end in (line.start, line.end):
                if end != GRID and end not in self.bus_index:
                    raise MicrogridError(f"line {k} ({line.start} -> {line.end}): bus {end!r} is not among {names}")
            if line.start == line.end or line.start == GRID:
                raise MicrogridError(f"line {k}: goes from {line.start!r} to {line.end!r} (from a bus to another "
                                     f"bus or to {GRID!r})")
            if not line.x > 0 or line.r < 0:
                raise MicrogridError(f"line {k} ({line.start} -> {line.end}): needs x > 0 and r >= 0 p.u., got "
                                     f"r={line.r}, x={line.x}")
        if not any(line.end == GRID for line in self.lines):
            raise MicrogridError(f"no line ends at {GRID!r}: an islanded microgrid is not supported (the units' angles "
                                 f"are relative to a grid source; without one the network frame drifts)")
        # the state layout: units, then bus voltages, inductive load currents, line currents
        offsets, start = [], 0
        for u in self.units:
            offsets.append(start)
            start += u.n_states
        self.unit_offset = offsets
        self.n_unit_states = start
        self.v_offset = {b.name: start + 2 * k for k, b in enumerate(self.buses)}
        start += 2 * len(self.buses)
        self.load_offset = {}
        for b in self.buses:
            if b.load_r is not None and b.load_x > 0:
                self.load_offset[b.name] = start
                start += 2
        self.line_offset = [start + 2 * k for k in range(len(self.lines))]
        self.n_states = start + 2 * len(self.lines)
        names_out = [f"{u.name}.{s}" for u in self.units for s in u.state_names]
        names_out += [f"{b.name}.v_{ax}" for b in self.buses for ax in "DQ"]
        names_out += [f"{b}.iload_{ax}" for b in self.load_offset for ax in "DQ"]
        names_out += [f"line{k}.i_{ax}" for k in range(len(self.lines)) for ax in "DQ"]
        self.state_names = tuple(names_out)

    # ---------------------------------------------------------------- pieces
    def _unit_inputs(self, x, unit):
        o = self.v_offset[unit.bus]
        vd, vq = x[o], x[o + 1]
        return np.array([math.hypot(vd, vq), math.atan2(vq, vd)])

    def _unit_current(self, x, k):
        """The current unit ``k`` injects, in the network frame, and its derivative in (angle, i_d, i_q)."""
        unit, o = self.units[k], self.unit_offset[k]
        delta = x[o + unit.i_angle]
        i_d, i_q = x[o + unit.i_current[0]], x[o + unit.i_current[1]]
        c, s = math.cos(delta), math.sin(delta)
        current = np.array([i_d * c - i_q * s, i_d * s + i_q * c])
        # columns: ∂/∂angle, ∂/∂i_d, ∂/∂i_q
        slope = np.array([[-i_d * s - i_q * c, c, -s], [i_d * c - i_q * s, s, c]])
        return current, slope

    @staticmethod
    def _rotate(value, w):
        """−j·w·value for a (D, Q) pair: (w·Q, −w·D)."""
        return np.array([w * value[1], -w * value[0]])

    def _source(self, u):
        return np.array([u[0] * math.cos(u[1]), u[0] * math.sin(u[1])])

    # ---------------------------------------------------------------- the system
    def vector_field(self, x, u) -> np.ndarray:
        """dx/dt (1/s) of the whole microgrid at state ``x`` and grid source ``u = (ug, theta_g)``."""
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        out = np.zeros(self.n_states)
        injected = {b.name: np.zeros(2) for b in self.buses}
        for k, unit in enumerate(self.units):
            o = self.unit_offset[k]
            out[o:o + unit.n_states] = unit.system.vector_field(x[o:o + unit.n_states], self._unit_inputs(x, unit))
            injected[unit.bus] += self._unit_current(x, k)[0]
        wb, wg = self.wb, self.wg
        for b in self.buses:
            v = x[self.v_offset[b.name]:self.v_offset[b.name] + 2]
            if b.name in self.load_offset:
                o = self.load_offset[b.name]
                i = x[o:o + 2]
                out[o:o + 2] = wb / b.load_x * (v - b.load_r * i) + wb * self._rotate(i, wg)
                injected[b.name] -= i
            elif b.load_r is not None:
                injected[b.name] -= v / b.load_r
        for k, line in enumerate(self.lines):
            o = self.line_offset[k]
            i = x[o:o + 2]
            v_from = x[self.v_offset[line.start]:self.v_offset[line.start] + 2]
            v_to = self._source(u) if line.end == GRID else x[self.v_offset[line.end]:self.v_offset[line.end] + 2]
            out[o:o + 2] = wb / line.x * (v_from - v_to - line.r * i) + wb * self._rotate(i, wg)
            injected[line.start] -= i
            if line.end != GRID:
                injected[line.end] += i
        for b in self.buses:
            o = self.v_offset[b.name]
            out[o:o + 2] = wb / b.capacitance * injected[b.name] + wb * self._rotate(x[o:o + 2], wg)
        return out

    def jacobian(self, x, u, wrt: str = "x") -> np.ndarray:
        """Exact Jacobian of :meth:`vector_field` (the units' own Jacobians, chained through the
        bus voltages they see and the currents they inject).

        Parameters
        ----------
        wrt : {"x", "u"}
            The state (A matrix) or the grid source's magnitude and phase (B).
        """
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        wb, wg = self.wb, self.wg
        if wrt == "u":
            out = np.zeros((self.n_states, 2))
            dsource = np.array([[math.cos(u[1]), -u[0] * math.sin(u[1])], [math.sin(u[1]), u[0] * math.cos(u[1])]])
            for k, line in enumerate(self.lines):
                if line.end == GRID:
                    o = self.line_offset[k]
                    out[o:o + 2] = -wb / line.x * dsource
            return out
        if wrt != "x":
            raise ValueError(f"wrt must be 'x' or 'u', got {wrt!r}")
        n = self.n_states
        a = np.zeros((n, n))
        rot = np.array([[0.0, wg], [-wg, 0.0]])  # −j·wg as a 2×2 map on (D, Q)
        for k, unit in enumerate(self.units):
            o, m = self.unit_offset[k], unit.n_states
            xu, uu = x[o:o + m], self._unit_inputs(x, unit)
            a[o:o + m, o:o + m] = unit.system.jacobian(xu, uu, wrt="x")
            # inputs (|v|, ∠v) of the bus voltage (v_D, v_Q)
            ov = self.v_offset[unit.bus]
            vd, vq = x[ov], x[ov + 1]
            mag2 = max(vd * vd + vq * vq, 1e-300)
            mag = math.sqrt(mag2)
            dinputs = np.array([[vd / mag, vq / mag], [-vq / mag2, vd / mag2]])
            a[o:o + m, ov:ov + 2] = np.asarray(unit.system.jacobian(xu, uu, wrt="u"), dtype=float) @ dinputs
            # its current into the bus
            _, slope = self._unit_current(x, k)
            cols = [o + unit.i_angle, o + unit.i_current[0], o + unit.i_current[1]]
            bus = self.buses[self.bus_index[unit.bus]]
            a[np.ix_(range(ov, ov + 2), cols)] += wb / bus.capacitance * slope
        for b in self.buses:
            ov = self.v_offset[b.name]
            a[ov:ov + 2, ov:ov + 2] += wb * rot
            if b.name in self.load_offset:
                o = self.load_offset[b.name]
                a[o:o + 2, ov:ov + 2] += wb / b.load_x * np.eye(2)
                a[o:o + 2, o:o + 2] += -wb * b.load_r / b.load_x * np.eye(2) + wb * rot
                a[ov:ov + 2, o:o + 2] += -wb / b.capacitance * np.eye(2)
            elif b.load_r is not None:
                a[ov:ov + 2, ov:ov + 2] += -wb / (b.capacitance * b.load_r) * np.eye(2)
        for k, line in enumerate(self.lines):
            o = self.line_offset[k]
            a[o:o + 2, o:o + 2] += -wb * line.r / line.x * np.eye(2) + wb * rot
            start = self.v_offset[line.start]
            a[o:o + 2, start:start + 2] += wb / line.x * np.eye(2)
            cap = self.buses[self.bus_index[line.start]].capacitance
            a[start:start + 2, o:o + 2] += -wb / cap * np.eye(2)
            if line.end != GRID:
                end = self.v_offset[line.end]
                a[o:o + 2, end:end + 2] += -wb / line.x * np.eye(2)
                cap = self.buses[self.bus_index[line.end]].capacitance
                a[end:end + 2, o:o + 2] += wb / cap * np.eye(2)
        return a

    # ---------------------------------------------------------------- operating point
    def _network_steady(self, x, u):
        """The network's states in steady state with the units' states held (the network is
        linear in its own states: one solve)."""
        x = np.array(x, dtype=float)
        net = slice(self.n_unit_states, self.n_states)
        a = self.jacobian(x, u)[net, net]
        x[net] = 0.0
        x[net] = np.linalg.solve(a, -self.vector_field(x, u)[net])
        return x

    def initial_guess(self, ug: float, theta_g: float = 0.0) -> np.ndarray:
        """A start for :meth:`equilibrium`: each unit at its own equilibrium on a bus at the grid
        source's voltage, the network in steady state with those currents, then each unit again at
        the voltage of its bus (a few rounds)."""
        u = np.array([ug, theta_g], dtype=float)
        x = np.zeros(self.n_states)
        for b in self.buses:
            x[self.v_offset[b.name]:self.v_offset[b.name] + 2] = self._source(u)
        for _ in range(4):
            for k, unit in enumerate(self.units):
                o = self.unit_offset[k]
                inputs = self._unit_inputs(x, unit)
                try:
                    x[o:o + unit.n_states] = unit.system.equilibrium(*inputs)
                except Exception as exc:  # noqa: BLE001 - any model's failure to find one
                    raise EquilibriumNotFound(f"unit {unit.name!r} has no equilibrium of its own at its bus voltage "
                                              f"{inputs[0]:.4g} p.u., {inputs[1]:.4g} rad: {exc}") from exc
            x = self._network_steady(x, u)
        return x

    def equilibrium(self, ug: float = 1.0, theta_g: float = 0.0, x0=None, tol: float = 1e-8) -> np.ndarray:
        """The microgrid's operating point (f = 0) with the grid source at ``ug``∠``theta_g``
        (scipy's hybrid Powell with the exact Jacobian, from :meth:`initial_guess`)."""
        u = np.array([ug, theta_g], dtype=float)
        start = self.initial_guess(ug, theta_g) if x0 is None else np.asarray(x0, dtype=float)
        scale = np.maximum(np.abs(self.jacobian(start, u)).sum(axis=1), 1.0)

        def accept(x, u_now):
            return bool(np.all(np.abs(self.vector_field(x, u_now)) <= tol * scale))

        x = root(self.vector_field, self.jacobian, u, start, accept)
        if x is None:
            raise EquilibriumNotFound(f"microgrid: no equilibrium found with the grid source at {ug} p.u., {theta_g} rad")
        return x

    def eigenvalues(self, ug: float = 1.0, theta_g: float = 0.0) -> np.ndarray:
        """Eigenvalues (1/s) of the microgrid linearised at :meth:`equilibrium`."""
        return np.linalg.eigvals(self.jacobian(self.equilibrium(ug, theta_g), [ug, theta_g]))

    def unit_shares(self, participation_row: np.ndarray) -> dict:
        """How much of one mode's participation (a row of
        :attr:`~pisml_ros.analysis.modal.ModalSummary.participation`) sits in each unit's states
        and in the network's (fractions summing to 1)."""
        row = np.asarray(participation_row, dtype=float)
        total = max(float(row.sum()), 1e-300)
        shares = {u.name: float(row[o:o + u.n_states].sum()) / total for u, o in zip(self.units, self.unit_offset)}
        shares["network"] = float(row[self.n_unit_states:].sum()) / total
        return shares
