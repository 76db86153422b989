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
(``ug``, ``theta_g``), and everything in :mod:`pisml_ros.analysis` applies to it. Without a line
to the grid the microgrid is islanded: the droops and the load set its frequency, the network's
frame turns with the first unit's, whose angle is then the reference and not a state.

The equilibrium and modes are hand-assembled from the units' own exact Jacobians by the chain
rule (no library assembles a network of arbitrary vector fields), then solved by scipy.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..equilibrium import EquilibriumNotFound, root

GRID = "grid"
#: a unit's share of a mode's participation from which its identified bandwidth is noted on the mode
MODE_SHARE_NOTED = 0.1
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
    the bus); ``rating``, its rating in units of the network's base power (its own per-unit
    currents times ``rating`` are the network's; voltages share one base)."""

    name: str
    system: object
    bus: str
    angle: str = "delta"
    current: tuple = ("ig_d", "ig_q")
    rating: float = 1.0

    def __post_init__(self):
        if not (math.isfinite(self.rating) and self.rating > 0):
            raise MicrogridError(f"unit {self.name!r}: rating must be > 0 (of the network's base power), "
                                 f"got {self.rating}")
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
    """Inverter models, buses, lines and (optionally) a grid source assembled into one system.

    Parameters
    ----------
    units : sequence of Unit
    buses : sequence of Bus
    lines : sequence of Line
        A line that ends at ``"grid"`` ties the microgrid to the grid source, which pins the
        frequency at ``wg``: the network's frame rotates with it. Without one the microgrid is
        islanded: its frequency is set by the droops and the load, the network's frame rotates
        with the first unit's frame, and that unit's angle is the reference (not a state).
    base_hz : float
        Base frequency of the per-unit system (ωb = 2π·base_hz; the virtual HIL's is 60 Hz).
    wg : float
        Frequency of the grid source (p.u.), the frame the units' angles are identified against.

    Attributes
    ----------
    state_names : tuple of str
        ``<unit>.<state>`` for every unit (islanded: the first unit's angle left out), then
        ``<bus>.v_D``, ``<bus>.v_Q``, ``<bus>.iload_D/Q`` (inductive loads), ``line<k>.i_D/Q``.
    input_names : tuple of str
        ``ug``, ``theta_g``: the grid source's magnitude and phase (ignored when islanded).
    islanded : bool
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
        self.islanded = not any(line.end == GRID for line in self.lines)
        # the state layout: units, then bus voltages, inductive load currents, line currents; each
        # unit's local state k sits at slots[k] (-1: the islanded reference angle, fixed at 0)
        slots, start = [], 0
        for k, u in enumerate(self.units):
            free = np.ones(u.n_states, dtype=bool)
            if self.islanded and k == 0:
                free[u.i_angle] = False
            slot = np.full(u.n_states, -1)
            slot[free] = start + np.arange(int(free.sum()))
            slots.append(slot)
            start += int(free.sum())
        self.unit_slots = slots
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
        names_out = [f"{u.name}.{s}" for u, slot in zip(self.units, slots)
                     for s, g in zip(u.state_names, slot) if g >= 0]
        names_out += [f"{b.name}.v_{ax}" for b in self.buses for ax in "DQ"]
        names_out += [f"{b}.iload_{ax}" for b in self.load_offset for ax in "DQ"]
        names_out += [f"line{k}.i_{ax}" for k in range(len(self.lines)) for ax in "DQ"]
        self.state_names = tuple(names_out)

    # ---------------------------------------------------------------- pieces
    def _unit_inputs(self, x, unit):
        o = self.v_offset[unit.bus]
        vd, vq = x[o], x[o + 1]
        return np.array([math.hypot(vd, vq), math.atan2(vq, vd)])

    def unit_state(self, x, k) -> np.ndarray:
        """Unit ``k``'s own state (its angle in the network's frame) at microgrid state ``x``."""
        slot = self.unit_slots[k]
        out = np.zeros(slot.size)
        free = slot >= 0
        out[free] = np.asarray(x, dtype=float)[..., slot[free]]
        return out

    def _local(self, x, k):
        """Unit ``k``'s state and inputs in the frame of its bus voltage: its angle taken from
        the bus voltage's phase, and a grid phase of 0. For a model invariant to a common rotation
        (the plant, whose equations see only δ − θ_g) it is the same thing as the network frame; an
        identified model may also use the angle alone (``sin(delta)``: in its records δ stayed near
        θ_g), and holds only near the grid phase it was identified at, its test rig's reference."""
        unit = self.units[k]
        inputs = self._unit_inputs(x, unit)
        local = self.unit_state(x, k)
        local[unit.i_angle] -= inputs[1]
        return local, np.array([inputs[0], 0.0])

    def _current_slope(self, x, k):
        """The derivative of the current unit ``k`` injects (:meth:`injected_currents`) in its
        (angle, i_d, i_q), a 2 × 3 matrix."""
        unit = self.units[k]
        own = self.unit_state(x, k)
        delta = own[unit.i_angle]
        i_d, i_q = own[unit.i_current[0]], own[unit.i_current[1]]
        c, s = unit.rating * math.cos(delta), unit.rating * math.sin(delta)
        return np.array([[-i_d * s - i_q * c, c, -s], [i_d * c - i_q * s, s, c]])

    @staticmethod
    def _rotate(value, w):
        """−j·w·value for a (D, Q) pair: (w·Q, −w·D)."""
        return np.array([w * value[1], -w * value[0]])

    def _source(self, u):
        return np.array([u[0] * math.cos(u[1]), u[0] * math.sin(u[1])])

    def frequency(self, x, u=(1.0, 0.0)) -> float:
        """The network frame's frequency (p.u.): the grid source's, or islanded the first unit's
        (``wg`` plus its angle's rate over ωb)."""
        if not self.islanded:
            return self.wg
        local, inputs = self._local(np.asarray(x, dtype=float), 0)
        return self.wg + float(self.units[0].system.vector_field(local, inputs)[self.units[0].i_angle]) / self.wb

    # ---------------------------------------------------------------- the system
    def vector_field(self, x, u) -> np.ndarray:
        """dx/dt (1/s) of the whole microgrid at state ``x`` and grid source ``u = (ug, theta_g)``."""
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        out = np.zeros(self.n_states)
        injected = {b.name: np.zeros(2) for b in self.buses}
        rates = []
        for unit, current in zip(self.units, self.injected_currents(x)):
            injected[unit.bus] += current
        for k, unit in enumerate(self.units):
            local, inputs = self._local(x, k)
            rates.append(np.asarray(unit.system.vector_field(local, inputs), dtype=float))
        # islanded, the frame turns with the first unit: every angle's rate is relative to its rate
        reference = rates[0][self.units[0].i_angle] if self.islanded else 0.0
        w = self.wg + reference / self.wb
        for k, unit in enumerate(self.units):
            rate = rates[k]
            rate[unit.i_angle] -= reference
            free = self.unit_slots[k] >= 0
            out[self.unit_slots[k][free]] = rate[free]
        wb = self.wb
        for b in self.buses:
            v = x[self.v_offset[b.name]:self.v_offset[b.name] + 2]
            if b.name in self.load_offset:
                o = self.load_offset[b.name]
                i = x[o:o + 2]
                out[o:o + 2] = wb / b.load_x * (v - b.load_r * i) + wb * self._rotate(i, w)
                injected[b.name] -= i
            elif b.load_r is not None:
                injected[b.name] -= v / b.load_r
        for k, line in enumerate(self.lines):
            o = self.line_offset[k]
            i = x[o:o + 2]
            v_from = x[self.v_offset[line.start]:self.v_offset[line.start] + 2]
            v_to = self._source(u) if line.end == GRID else x[self.v_offset[line.end]:self.v_offset[line.end] + 2]
            out[o:o + 2] = wb / line.x * (v_from - v_to - line.r * i) + wb * self._rotate(i, w)
            injected[line.start] -= i
            if line.end != GRID:
                injected[line.end] += i
        for b in self.buses:
            o = self.v_offset[b.name]
            out[o:o + 2] = wb / b.capacitance * injected[b.name] + wb * self._rotate(x[o:o + 2], w)
        return out

    def jacobian(self, x, u, wrt: str = "x") -> np.ndarray:
        """Exact Jacobian of :meth:`vector_field` (the units' own Jacobians, chained through the
        bus voltages they see and the currents they inject; islanded, also through the frame's
        frequency, the first unit's).

        Parameters
        ----------
        wrt : {"x", "u"}
            The state (A matrix) or the grid source's magnitude and phase (B).
        """
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        wb = self.wb
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
        rows = []  # per unit: the derivatives of its local rates in the microgrid's states (m × n)
        reference = 0.0
        for k, unit in enumerate(self.units):
            m, slot = unit.n_states, self.unit_slots[k]
            free = slot >= 0
            local, inputs = self._local(x, k)
            block = np.asarray(unit.system.jacobian(local, inputs, wrt="x"), dtype=float)
            full = np.zeros((m, n))
            full[:, slot[free]] = block[:, free]
            # the bus voltage (v_D, v_Q) -> its magnitude (the unit's ug) and its phase, which
            # enters through the unit's angle in the bus frame (δ − θ_bus)
            ov = self.v_offset[unit.bus]
            vd, vq = x[ov], x[ov + 1]
            mag2 = max(vd * vd + vq * vq, 1e-300)
            mag = math.sqrt(mag2)
            dinputs = np.array([[vd / mag, vq / mag], [-vq / mag2, vd / mag2]])
            by_input = np.column_stack([np.asarray(unit.system.jacobian(local, inputs, wrt="u"), dtype=float)[:, 0],
                                        -block[:, unit.i_angle]])
            full[:, ov:ov + 2] += by_input @ dinputs
            rows.append(full)
            if self.islanded and k == 0:
                reference = float(unit.system.vector_field(local, inputs)[unit.i_angle])
        w = self.wg + reference / wb
        # islanded: ∂w/∂x·ωb, the first unit's angle rate's slope (every angle's rate is relative to it)
        dw = rows[0][self.units[0].i_angle].copy() if self.islanded else np.zeros(n)
        rot = np.array([[0.0, w], [-w, 0.0]])  # −j·w as a 2×2 map on (D, Q)
        for k, unit in enumerate(self.units):
            slot = self.unit_slots[k]
            full = rows[k]
            full[unit.i_angle] -= dw
            free = slot >= 0
            a[slot[free]] += full[free]
            # its current into the bus
            slope = self._current_slope(x, k)
            cols = slot[[unit.i_angle, *unit.i_current]]
            keep = cols >= 0
            ov = self.v_offset[unit.bus]
            bus = self.buses[self.bus_index[unit.bus]]
            a[np.ix_(range(ov, ov + 2), cols[keep])] += wb / bus.capacitance * slope[:, keep]

        def rotation(o):
            """The −j·w·(ωb·value) term of the pair at ``o``: its own 2×2 block, and the frame
            frequency's slope (islanded)."""
            a[o:o + 2, o:o + 2] += wb * rot
            if self.islanded:
                a[o:o + 2] += np.outer(self._rotate(x[o:o + 2], 1.0), dw)

        for b in self.buses:
            ov = self.v_offset[b.name]
            rotation(ov)
            if b.name in self.load_offset:
                o = self.load_offset[b.name]
                a[o:o + 2, ov:ov + 2] += wb / b.load_x * np.eye(2)
                a[o:o + 2, o:o + 2] += -wb * b.load_r / b.load_x * np.eye(2)
                rotation(o)
                a[ov:ov + 2, o:o + 2] += -wb / b.capacitance * np.eye(2)
            elif b.load_r is not None:
                a[ov:ov + 2, ov:ov + 2] += -wb / (b.capacitance * b.load_r) * np.eye(2)
        for k, line in enumerate(self.lines):
            o = self.line_offset[k]
            a[o:o + 2, o:o + 2] += -wb * line.r / line.x * np.eye(2)
            rotation(o)
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
        """Each unit at its own equilibrium on the grid source's voltage, and the network in
        steady state with those currents: the exact operating point of a network without
        impedance (the start of :meth:`equilibrium`'s path)."""
        u = np.array([ug, theta_g], dtype=float)
        x = np.zeros(self.n_states)
        for b in self.buses:
            x[self.v_offset[b.name]:self.v_offset[b.name] + 2] = (1.0, 0.0) if self.islanded else self._source(u)
        for k, unit in enumerate(self.units):
            at = (1.0, 0.0) if self.islanded else (ug, 0.0)  # islanded: the units' nominal voltage
            try:
                own = np.array(unit.system.equilibrium(*at), dtype=float)  # in its bus frame (see _local)
            except Exception as exc:  # noqa: BLE001 - any model's failure to find one
                raise EquilibriumNotFound(f"unit {unit.name!r} has no equilibrium of its own at {at[0]:.4g} p.u., "
                                          f"{theta_g:.4g} rad: {exc}") from exc
            own[unit.i_angle] += 0.0 if self.islanded else theta_g
            free = self.unit_slots[k] >= 0
            x[self.unit_slots[k][free]] = own[free]
        return self._network_steady(x, u)

    def scaled(self, level: float) -> "Microgrid":
        """The same microgrid with every line's impedance times ``level`` and every load's
        divided by it (``level`` → 0: every bus at the grid source's voltage, no load)."""
        buses = [dataclasses.replace(b, load_r=b.load_r / level, load_x=b.load_x / level) if b.load_r is not None else b
                 for b in self.buses]
        lines = [dataclasses.replace(line, r=line.r * level, x=line.x * level) for line in self.lines]
        return Microgrid(self.units, buses, lines, base_hz=self.wb / (2.0 * math.pi), wg=self.wg)

    def equilibrium(self, ug: float = 1.0, theta_g: float = 0.0, x0=None, tol: float = 1e-8,
                    start_level: float = 1e-3) -> np.ndarray:
        """The microgrid's operating point (f = 0) with the grid source at ``ug``∠``theta_g``.

        Followed from the network without impedance (:meth:`initial_guess`, exact there) as the
        lines' impedances and the loads grow to their values (:meth:`scaled`, levels from
        ``start_level`` to 1 in steps of up to 3x, shorter where one fails; scipy's hybrid Powell
        with the exact Jacobian at each): the operating point connected to each unit's own, not another root
        of the network equations (a start from the units' equilibria on a heavily loaded network
        found one with every angle near π). With ``x0``, one solve from there.
        """
        u = np.array([ug, theta_g], dtype=float)

        def solve(grid, start):
            scale = np.maximum(np.abs(grid.jacobian(start, u)).sum(axis=1), 1.0)

            def accept(x, u_now):
                return bool(np.all(np.isfinite(x)) and np.all(np.abs(grid.vector_field(x, u_now)) <= tol * scale))

            return root(grid.vector_field, grid.jacobian, u, start, accept)

        if self.islanded and x0 is None:
            # no source to start from: the units at their own nominal points, the network in
            # steady state with them, then the whole (lm on the row-scaled residual if Powell stalls)
            start = self.initial_guess(ug, theta_g)
            x = solve(self, start)
            if x is None:
                import scipy.optimize

                scale = np.maximum(np.abs(self.jacobian(start, u)).sum(axis=1), 1.0)
                sol = scipy.optimize.root(lambda z: self.vector_field(z, u) / scale, start,
                                          jac=lambda z: self.jacobian(z, u) / scale[:, None], method="lm",
                                          options={"xtol": 1e-14, "ftol": 1e-14})
                x = sol.x if np.all(np.abs(self.vector_field(sol.x, u)) <= tol * scale) else None
            if x is None:
                raise EquilibriumNotFound("islanded microgrid: no operating point found from the units' own nominal "
                                          "ones (is the load within what the units can supply?)")
            return x
        if x0 is not None:
            x = solve(self, np.asarray(x0, dtype=float))
            if x is None:
                raise EquilibriumNotFound(f"microgrid: no equilibrium found from the given start at {ug} p.u., "
                                          f"{theta_g} rad")
            return x
        level = float(start_level)
        x = solve(self.scaled(level), self.scaled(level).initial_guess(ug, theta_g))
        if x is None:
            raise EquilibriumNotFound(f"microgrid: no equilibrium even with the lines' impedances and the loads scaled "
                                      f"by {level:g} (grid source {ug} p.u., {theta_g} rad)")
        ratio = 3.0
        while level < 1.0:
            trial = min(1.0, level * ratio)
            found = solve(self if trial == 1.0 else self.scaled(trial), x)
            if found is None:
                ratio = math.sqrt(ratio)
                if ratio < 1.0 + 1e-3:
                    raise EquilibriumNotFound(f"microgrid: the operating point is lost with the network at {level:.4g} "
                                              f"of its impedances and loads (grid source {ug} p.u., {theta_g} rad): "
                                              f"no equilibrium of this microgrid on that branch")
                continue
            x, level = found, trial
            ratio = min(3.0, ratio * 1.5)
        return x

    def eigenvalues(self, ug: float = 1.0, theta_g: float = 0.0) -> np.ndarray:
        """Eigenvalues (1/s) of the microgrid linearised at :meth:`equilibrium`."""
        return np.linalg.eigvals(self.jacobian(self.equilibrium(ug, theta_g), [ug, theta_g]))

    def injected_currents(self, x) -> np.ndarray:
        """The current each unit injects into its bus, in the network frame, at state(s) ``x``:
        shape (..., n_units, 2) (D, Q)."""
        x = np.asarray(x, dtype=float)
        out = []
        for k, unit in enumerate(self.units):
            slot = self.unit_slots[k]
            delta = x[..., slot[unit.i_angle]] if slot[unit.i_angle] >= 0 else np.zeros(x.shape[:-1])
            i_d, i_q = x[..., slot[unit.i_current[0]]], x[..., slot[unit.i_current[1]]]
            c, s = unit.rating * np.cos(delta), unit.rating * np.sin(delta)
            out.append(np.stack([i_d * c - i_q * s, i_d * s + i_q * c], axis=-1))
        return np.stack(out, axis=-2)

    uncertainty_basis = ("the identified units' coefficient covariances (measurement noise alone, the units "
                         "independent), first order, the operating point held")

    def max_real_std(self, x, u=(1.0, 0.0)) -> float | None:
        """Standard deviation (1/s) of the microgrid's largest real part at state ``x`` from its
        identified units' coefficient covariances (:mod:`~pisml_ros.analysis.uncertainty`; the
        units independent), to first order with the operating point held, as for one model. None
        where no unit carries a covariance or the eigenvalue is defective.

        The Jacobian is affine in each coefficient at a fixed state, so its derivative is one
        difference of two Jacobians, exact up to rounding: simpler than the chain rule through the
        bus voltages, the frames and (islanded) the reference frequency, and cheap (one Jacobian per
        coefficient).
        """
        from .uncertainty import coefficient_covariance, max_real_slope

        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        stored = [(unit.system, coefficient_covariance(unit.system)) for unit in self.units]
        stored = [(system, found) for system, found in stored if found is not None]
        if not stored:
            return None
        a = self.jacobian(x, u)
        d_re = max_real_slope(a)
        if d_re is None:
            return None
        variance = 0.0
        for system, (entries, cov) in stored:
            coefficients = system.coefficients
            sensitivity = np.zeros(len(entries))
            for n, (t, j) in enumerate(entries):
                old = coefficients[t, j]
                step = 1e-3 * max(1.0, abs(old))
                try:
                    coefficients[t, j] = old + step
                    sensitivity[n] = float(np.sum(d_re * (self.jacobian(x, u) - a))) / step
                finally:
                    coefficients[t, j] = old
            variance += float(sensitivity @ cov @ sensitivity)
        return float(np.sqrt(max(variance, 0.0)))

    def alternative_max_reals(self, x, u=(1.0, 0.0)) -> list:
        """The microgrid's largest real part with each alternative of its identified units
        (:meth:`~pisml_ros.model.explicit.ExplicitModel.alternatives`: candidates that fitted the
        unit's records about as well) in that unit's place, one at a time, at the operating point
        followed from ``x``: ``[{"unit", "name", "max_real"}]`` (None: no operating point there).
        For :func:`~pisml_ros.analysis.operating_point.alternative_verdicts`."""
        from .operating_point import max_real_near

        x = np.asarray(x, dtype=float)
        out = []
        for unit in self.units:
            alternatives = getattr(unit.system, "alternatives", None)
            if not callable(alternatives):
                continue
            own = unit.system
            for name, model in alternatives(unit.name):
                try:
                    unit.system = model
                    value = max_real_near(self, x, u)
                finally:
                    unit.system = own
                out.append({"unit": unit.name, "name": name, "max_real": value})
        return out

    def unit_shares(self, participation_row: np.ndarray) -> dict:
        """How much of one mode's participation (a row of
        :attr:`~pisml_ros.analysis.modal.ModalSummary.participation`) sits in each unit's states
        and in the network's (fractions summing to 1)."""
        row = np.asarray(participation_row, dtype=float)
        total = max(float(row.sum()), 1e-300)
        shares = {u.name: float(row[slot[slot >= 0]].sum()) / total for u, slot in zip(self.units, self.unit_slots)}
        shares["network"] = float(row[self.n_unit_states:].sum()) / total
        return shares


# -------------------------------------------------------------------- configuration and reports
_BUS_KEYS = {"name", "capacitance", "load"}
_LINE_KEYS = {"name", "from", "to", "r", "x"}
_UNIT_KEYS = {"name", "bus", "model", "plant", "angle", "current", "rating"}
_TOP_KEYS = {"base_hz", "grid", "buses", "lines", "units"}


def _number(value, where: str, positive: bool = False, nonnegative: bool = False) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise MicrogridError(f"{where}: expected a number, got {value!r}") from None
    if not math.isfinite(out) or (positive and not out > 0) or (nonnegative and out < 0):
        need = "> 0" if positive else ">= 0" if nonnegative else "finite"
        raise MicrogridError(f"{where}: must be {need}, got {value!r}")
    return out


def _entries(config: dict, key: str, source: str) -> list:
    entries = config.get(key)
    if not isinstance(entries, list) or not entries:
        raise MicrogridError(f"{source}: '{key}' must be a non-empty list")
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise MicrogridError(f"{source}: {key}[{k}] must be a mapping, got {entry!r}")
    return entries


def _unknown(entry: dict, allowed: set, where: str):
    extra = sorted(set(entry) - allowed)
    if extra:
        raise MicrogridError(f"{where}: unknown key(s) {extra}; allowed: {sorted(allowed)}")


def read_microgrid_config(path) -> dict:
    """The microgrid description in a YAML or JSON file (its ``microgrid:`` section, or the whole
    file), for :func:`microgrid_from_config`; a file that cannot be read or parsed raises
    :class:`MicrogridError` naming it."""
    import yaml

    try:
        config = yaml.safe_load(Path(path).read_text())
    except OSError as err:
        raise MicrogridError(f"{path}: {err.strerror or err}") from None
    except yaml.YAMLError as err:
        raise MicrogridError(f"{path}: not YAML or JSON: {err}") from None
    return config["microgrid"] if isinstance(config, dict) and "microgrid" in config else config


def microgrid_from_config(config: dict, base_dir=".", source: str = "microgrid", loaded: dict | None = None) -> tuple:
    """A :class:`Microgrid` and its grid source's operating point from a configuration mapping
    (the ``microgrid:`` section of a YAML or JSON file; README, "Microgrid")::

        base_hz: 60                      # optional (the virtual HIL's)
        grid: {ug: 1.0, theta_g: 0.0}    # the grid source (optional: 1.0 p.u., 0 rad)
        buses:  [{name: b1, capacitance: 0.02}, {name: pcc, capacitance: 0.05, load: {r: 0.9, x: 0.4358}}]
        lines:  [{from: b1, to: pcc, r: 0.01, x: 0.05}, {from: pcc, to: grid, r: 0.02, x: 0.2}]
        units:  [{name: target, model: target.json, bus: b1},     # an identified explicit model
                 {name: aux, plant: {KpV: 2.0, KiV: 4.0}, bus: b1, rating: 0.5}]  # the virtual HIL's inverter,
                                                              # these parameters, half the base power

    ``model`` paths are relative to ``base_dir``; ``loaded``, a dict, keeps the models read
    (path -> model) for the next call (a parameter sweep rebuilds the microgrid at every value).
    Returns ``(microgrid, (ug, theta_g))``.
    """
    from ..model import ExplicitModel

    if not isinstance(config, dict):
        raise MicrogridError(f"{source}: expected a mapping, got {type(config).__name__}")
    _unknown(config, _TOP_KEYS, source)
    grid = config.get("grid") or {}
    if not isinstance(grid, dict):
        raise MicrogridError(f"{source}: 'grid' must be a mapping with ug and theta_g, got {grid!r}")
    _unknown(grid, {"ug", "theta_g"}, f"{source}: grid")
    inputs = (_number(grid.get("ug", 1.0), f"{source}: grid.ug", positive=True),
              _number(grid.get("theta_g", 0.0), f"{source}: grid.theta_g"))
    buses = []
    for k, entry in enumerate(_entries(config, "buses", source)):
        where = f"{source}: buses[{k}]"
        _unknown(entry, _BUS_KEYS, where)
        load = entry.get("load")
        if load is not None and not isinstance(load, dict):
            raise MicrogridError(f"{where}.load: a mapping with r and x (p.u.), got {load!r}")
        if load is not None:
            _unknown(load, {"r", "x"}, f"{where}.load")
        buses.append(Bus(str(entry.get("name", f"bus{k}")),
                         _number(entry.get("capacitance", 0.05), f"{where}.capacitance", positive=True),
                         None if load is None else _number(load.get("r", 0.0), f"{where}.load.r", nonnegative=True),
                         0.0 if load is None else _number(load.get("x", 0.0), f"{where}.load.x", nonnegative=True)))
    lines = []
    for k, entry in enumerate(_entries(config, "lines", source)):
        where = f"{source}: lines[{k}]"
        _unknown(entry, _LINE_KEYS, where)
        if "from" not in entry or "to" not in entry:
            raise MicrogridError(f"{where}: needs 'from' and 'to' (bus names, or {GRID!r} for 'to')")
        lines.append(Line(str(entry["from"]), str(entry["to"]),
                          _number(entry.get("r", 0.01), f"{where}.r", nonnegative=True),
                          _number(entry.get("x", 0.05), f"{where}.x", positive=True)))
    units = []
    for k, entry in enumerate(_entries(config, "units", source)):
        where = f"{source}: units[{k}]"
        _unknown(entry, _UNIT_KEYS, where)
        if ("model" in entry) == ("plant" in entry):
            raise MicrogridError(f"{where}: give exactly one of 'model' (an explicit model JSON) or 'plant' "
                                 f"(the virtual HIL's inverter with these parameters)")
        if "bus" not in entry:
            raise MicrogridError(f"{where}: needs 'bus'")
        if "model" in entry:
            path = str(Path(base_dir) / str(entry["model"]))
            system = loaded.get(path) if loaded is not None else None
            if system is None:
                system = ExplicitModel.load(path)
                if loaded is not None:
                    loaded[path] = system
        else:
            from ..plant import InverterPlant, PlantParameters

            params = entry["plant"] or {}
            if not isinstance(params, dict):
                raise MicrogridError(f"{where}.plant: a mapping of plant parameters, got {params!r}")
            try:
                system = InverterPlant(PlantParameters().replace(**params))
            except (TypeError, ValueError) as err:
                raise MicrogridError(f"{where}.plant: {err}") from None
        current = entry.get("current", ("ig_d", "ig_q"))
        if not isinstance(current, (list, tuple)) or len(current) != 2:
            raise MicrogridError(f"{where}.current: two state names (d, q), got {current!r}")
        units.append(Unit(str(entry.get("name", f"unit{k}")), system, str(entry["bus"]),
                          angle=str(entry.get("angle", "delta")), current=tuple(map(str, current)),
                          rating=_number(entry.get("rating", 1.0), f"{where}.rating", positive=True)))
    base_hz = _number(config.get("base_hz", DEFAULT_BASE_HZ), f"{source}: base_hz", positive=True)
    try:
        return Microgrid(units, buses, lines, base_hz=base_hz), inputs
    except MicrogridError as err:
        raise MicrogridError(f"{source}: {err}") from None


def with_setting(config: dict, path: str, value) -> dict:
    """A copy of ``config`` with the entry at the dotted ``path`` set to ``value``: list entries by
    index or by their ``name`` (``units.aux.plant.KpV``, ``lines.3.x``, ``grid.ug``)."""
    import copy

    out = copy.deepcopy(config)
    keys = path.split(".")
    node = out
    for depth, key in enumerate(keys):
        last = depth == len(keys) - 1
        if isinstance(node, list):
            named = [k for k, entry in enumerate(node) if isinstance(entry, dict) and str(entry.get("name")) == key]
            if named:
                index = named[0]
            elif key.lstrip("-").isdigit() and -len(node) <= int(key) < len(node):
                index = int(key)
            else:
                where = '.'.join(keys[:depth]) or 'the configuration'
                raise MicrogridError(f"--vary {path}: no entry {key!r} in {where}")
            if last:
                node[index] = value
            node = node[index]
        elif isinstance(node, dict):
            if last:
                node[key] = value
            else:
                node = node.setdefault(key, {})
        else:
            raise MicrogridError(f"--vary {path}: {'.'.join(keys[:depth])} is a value, not a mapping or list")
    return out


def with_unit_model(config: dict, unit: str, model, base_dir=".", loaded: dict | None = None) -> tuple:
    """A copy of ``config`` whose unit ``unit`` (its name) takes its equations from ``model``, a
    system in memory (an identified model just received, say), and the ``loaded`` dict that
    :func:`microgrid_from_config` then finds it in. Returns ``(config, loaded)``."""
    units = config.get("units") if isinstance(config, dict) else None
    names = [str(entry.get("name")) for entry in units or [] if isinstance(entry, dict)]
    if unit not in names:
        raise MicrogridError(f"unit {unit!r} is not among the configuration's units {names}")
    index = names.index(unit)
    key = f"in-memory-model-of-{unit}"
    entry = {k: v for k, v in units[index].items() if k not in ("plant", "model")}
    loaded = dict(loaded or {})
    loaded[str(Path(base_dir) / key)] = model
    return with_setting(config, f"units.{index}", dict(entry, model=key)), loaded


def parameter_sweep(config: dict, path: str, values, base_dir=".", loaded: dict | None = None,
                    source: str = "microgrid") -> dict:
    """The microgrid's modes as one setting (dotted ``path``, :func:`with_setting`) takes
    ``values``, and the stability boundaries between them (Brent's method on the largest real
    part's sign change, :func:`~pisml_ros.analysis.margins.stability_boundaries`).

    Returns
    -------
    dict
        ``{"parameter", "points": [{"value", "max_real", "eigenvalues"} (the root locus), or
        {"value", "max_real": None, "error"} where there is no operating point], "boundaries"}``
    """
    from .margins import stability_boundaries

    loaded = {} if loaded is None else loaded
    spectra = {}

    def max_real(value):
        grid, inputs = microgrid_from_config(with_setting(config, path, value), base_dir, source=source, loaded=loaded)
        spectra[value] = np.linalg.eigvals(grid.jacobian(grid.equilibrium(*inputs), inputs))
        return float(np.max(spectra[value].real))

    points = []
    for value in values:
        try:
            points.append({"value": float(value), "max_real": max_real(value),
                           "eigenvalues": [[float(z.real), float(z.imag)] for z in spectra[value]]})
        except EquilibriumNotFound as err:
            points.append({"value": float(value), "max_real": None, "error": str(err)})
    boundaries = stability_boundaries(max_real, sorted(values), xtol=1e-6)
    return {"parameter": path, "points": points, "boundaries": boundaries}


def unit_other_equilibria(microgrid: Microgrid, x, k: int) -> list | None:
    """Unit ``k``'s other equilibria with the voltage of its bus held where it is at the microgrid
    state ``x`` (:func:`~.operating_point.other_equilibria`, in the frame of its bus voltage),
    nearest first; None where the unit cannot say (no stored rest states: a plant) or where ``x`` is
    no equilibrium of the unit alone (islanded at a frequency other than the grid's, which an
    identified unit's angle equation was fitted against).

    An identified model can have a second equilibrium near a fold of its own (stop 52: protocol
    recording 7 at 40 dB, 0.066 away at ug 1.2, unstable). The microgrid's own equilibria are not
    searched: an assembled microgrid has no rest states to start from, and a unit held at its bus
    voltage is the stiff-bus view of the same question.
    """
    from ..equilibrium import residual_below
    from .operating_point import other_equilibria

    system = microgrid.units[k].system
    if not callable(getattr(system, "other_equilibria", None)):
        return None
    local, inputs = microgrid._local(x, k)
    own = root(system.vector_field, system.jacobian, inputs, local,
               residual_below(system.vector_field, 1e-9, system.residual_scale()))
    if own is None or np.linalg.norm(own - local) > 1e-6 * (1.0 + np.linalg.norm(local)):
        return None
    return other_equilibria(system, inputs, own, microgrid.units[k].state_names)


def unit_other_equilibria_note(entry: dict) -> list:
    """Lines on a unit entry's ``other_equilibria`` (:func:`microgrid_report`), one per equilibrium."""
    from .operating_point import other_equilibria_note

    return other_equilibria_note(entry, "held at the voltage of its bus, the unit has another equilibrium",
                                 "the microgrid's operating point is the one found from its initial guess, and "
                                 "which one the unit sits at")


def microgrid_report(microgrid: Microgrid, ug: float = 1.0, theta_g: float = 0.0, modes: int = 3) -> dict:
    """The microgrid's operating point and modes
    (:func:`~pisml_ros.analysis.operating_point.operating_point_report`), plus per unit the bus
    voltage it sees and whether an identified unit was fitted on such voltages, the ``modes``
    least-damped modes with each unit's share in them, and where identified units carry their
    coefficients' covariance, how far their data pin the microgrid's verdict (``uncertainty``, as
    ``pisml analyse`` has it for one model; :meth:`Microgrid.max_real_std`), and an identified
    unit's other equilibria at its bus voltage (``other_equilibria``, :func:`unit_other_equilibria`).
    JSON-ready."""
    from .operating_point import analyse_operating_point, bandwidth_note, coverage_note, data_coverage

    report, x, summary = analyse_operating_point(microgrid, ug, theta_g)
    units = []
    currents = microgrid.injected_currents(x)
    for k, unit in enumerate(microgrid.units):
        seen = microgrid._unit_inputs(x, unit)
        current = currents[k]
        o = microgrid.v_offset[unit.bus]
        v = x[o:o + 2]
        entry = {"name": unit.name, "bus": unit.bus, "ug": float(seen[0]), "theta_g": float(seen[1]),
                 # the power the unit delivers into its bus (network frame, p.u.)
                 "p": float(v @ current), "q": float(v[1] * current[0] - v[0] * current[1]),
                 "kind": type(unit.system).__name__}
        coverage = data_coverage(unit.system, seen)
        if coverage is not None:
            entry["data_coverage"] = coverage
            note = coverage_note(coverage)
            if note:
                entry["note"] = note
        others = unit_other_equilibria(microgrid, x, k)
        if others:
            entry["other_equilibria"] = others
        units.append(entry)
    report["units"] = units
    report["islanded"] = microgrid.islanded
    report["frequency_pu"] = microgrid.frequency(x, (ug, theta_g))
    report["weakest_modes"] = []
    for k in range(min(modes, len(summary.eigenvalues))):
        shares = microgrid.unit_shares(summary.participation[k])
        mode = {"eigenvalue": [float(summary.eigenvalues[k].real), float(summary.eigenvalues[k].imag)],
                "damping": float(summary.damping[k]), "frequency_hz": float(summary.frequencies_hz[k]),
                "unit_shares": shares, "dominant_states": summary.dominant_states(k)}
        # an identified unit with a real share in a mode faster than its records pin (a network resonance)
        notes = [bandwidth_note(unit.system, mode["frequency_hz"], unit.name) for unit in microgrid.units
                 if shares.get(unit.name, 0.0) >= MODE_SHARE_NOTED]
        if any(notes):
            mode["note"] = "; ".join(n for n in notes if n)
        report["weakest_modes"].append(mode)
    return report


def simulate_stages(stages, x0, inputs, dt: float = 1e-4, rtol: float = 1e-8, atol: float = 1e-10):
    """Time response of a microgrid whose network changes at given instants (a load step, a line
    switched): ``stages``, a list of (:class:`Microgrid`, duration in s) sharing one state layout,
    run one after the other from ``x0`` with the grid source at ``inputs`` (ug, theta_g).

    scipy's BDF with the exact Jacobian: the network's shunt capacitors and lines put modes at
    10⁴-10⁵ rad/s beside the droop's 1 rad/s, a stiffness an explicit step cannot afford.

    Returns
    -------
    t : ndarray, shape (n,)
        Sample times from 0, every ``dt``, and each stage's end.
    x : ndarray, shape (n, n_states)
    """
    import scipy.integrate

    u = np.asarray(inputs, dtype=float)
    names = stages[0][0].state_names
    for grid, duration in stages:
        if grid.state_names != names:
            raise MicrogridError("the stages of a microgrid simulation must share their states (a load that turns "
                                 "resistive or a line removed changes them)")
        if not duration > 0:
            raise MicrogridError(f"a stage's duration must be > 0 s, got {duration}")
    times, states = [np.array([0.0])], [np.asarray(x0, dtype=float)[None]]
    start, x = 0.0, np.asarray(x0, dtype=float)
    for grid, duration in stages:
        end = start + duration
        samples = np.arange(start, end, dt)[1:]
        t_eval = np.append(samples[samples < end - 1e-12], end)
        sol = scipy.integrate.solve_ivp(lambda _t, z, g=grid: g.vector_field(z, u), (start, end), x, method="BDF",
                                        t_eval=t_eval, jac=lambda _t, z, g=grid: g.jacobian(z, u), rtol=rtol,
                                        atol=atol)
        if not sol.success:
            raise MicrogridError(f"microgrid simulation failed at t = {sol.t[-1] if sol.t.size else start:.6g} s: "
                                 f"{sol.message}")
        times.append(sol.t)
        states.append(sol.y.T)
        start, x = end, sol.y[:, -1]
    return np.concatenate(times), np.concatenate(states)
