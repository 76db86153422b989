"""The default grid-forming inverter: vector field, Jacobian, equilibrium, eigenvalues.

Droop-controlled grid-forming inverter (Pogaku et al. 2007) with an LCL filter,
a series damping resistor and cascaded voltage/current PI loops, on a stiff
grid; conventions in DESIGN.md ("Plant conventions"). Complex dq quantities are
written as ``x_d + j·x_q``.

The vector field is written with plain numpy arithmetic on arrays whose last
axis is the state, so that one call evaluates many trajectories at once and so
that it accepts complex numbers: the Jacobian is taken by complex-step
differentiation, exact to machine precision (non-smooth effects use the branch
selected by the real part).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.interpolate
import scipy.signal

from .effects import resolve_effects
from .parameters import OMEGA_BASE, PlantParameters

from ..equilibrium import continuation, residual_below, root
from ..signals import INPUT_NAMES, STATE_NAMES

N_MEASURED = len(STATE_NAMES)

_COMPLEX_STEP = 1e-30


class EquilibriumError(RuntimeError):
    """No equilibrium could be found at the requested operating point."""


def _real(a):
    return np.real(a) if np.iscomplexobj(a) else a


def _limit_magnitude(x_d, x_q, limit):
    """Scale (x_d, x_q) down to magnitude ``limit`` where it is larger."""
    mag = np.sqrt(x_d * x_d + x_q * x_q)
    scale = np.where(_real(mag) > limit, limit / np.where(_real(mag) > 0, mag, 1.0), 1.0)
    return x_d * scale, x_q * scale


def _clip(x, low, high):
    return np.where(_real(x) > high, high, np.where(_real(x) < low, low, x))


def _pade_state_space(td: float, order: int):
    """State-space (A, B, C, D) of the Padé approximation of exp(-s·td)."""
    taylor = [(-td) ** k / math.factorial(k) for k in range(2 * order + 1)]
    num, den = scipy.interpolate.pade(taylor, order)
    # pade returns poly1d in s with highest power first
    return scipy.signal.tf2ss(num.coeffs, den.coeffs)


class InverterPlant:
    """Virtual HIL model of the default grid-forming inverter.

    Parameters
    ----------
    params : PlantParameters, optional
        Nameplate parameters (used by the controller, and by the circuit unless
        ``param_drift`` says otherwise).
    effects : mapping, optional
        ``{effect_name: {param: value}}``; see :mod:`pisml_ros.plant.effects`.

    Attributes
    ----------
    n_states : int
        Measured plus hidden states.
    hidden_state_names : tuple of str
        Names of the hidden states some effects add (after the 13 measured).
    """

    state_names = STATE_NAMES
    input_names = INPUT_NAMES

    def __init__(self, params: PlantParameters | None = None, effects=None):
        self.params = params or PlantParameters()
        self.effects = resolve_effects(effects)
        circuit = {key: getattr(self.params, key) for key in ("Lf", "Rf", "Cf", "Rd", "Lg", "Rg")}
        circuit.update(self.effects.get("param_drift", {}))
        self.circuit = circuit
        # the controller's gains: nameplate unless `gain_mismatch` says it runs with others
        self.control = self.params.replace(**self.effects.get("gain_mismatch", {}))
        hidden = []
        self._delay = None
        if "delay" in self.effects:
            order = int(self.effects["delay"]["order"])
            a, b, c, d = _pade_state_space(self.effects["delay"]["td"], order)
            self._delay = (np.asarray(a), np.asarray(b)[:, 0], np.asarray(c)[0], float(np.asarray(d)[0, 0]))
            hidden += [f"delay_d{k}" for k in range(order)] + [f"delay_q{k}" for k in range(order)]
        self.hidden_state_names = tuple(hidden)
        self.n_states = N_MEASURED + len(hidden)

    # ------------------------------------------------------------------ vector field
    def vector_field(self, x, u):
        """Time derivative of the full state (see :meth:`evaluate`)."""
        return self.evaluate(x, u)[0]

    def internal_signals(self, x, u) -> dict:
        """Controller and circuit signals the measurements don't show directly.

        Returns
        -------
        dict of ndarray
            ``w`` (droop frequency), ``p``, ``q`` (instantaneous powers), ``vo_d/q``
            (output voltage), ``ilref_d/q`` (current reference after limiting),
            ``ilref_unlimited_d/q``, ``vi_d/q`` (inverter voltage applied to the
            filter), ``vref_d/q`` (voltage reference after virtual impedance).
        """
        return self.evaluate(x, u)[1]

    def evaluate(self, x, u):
        """Time derivative of the full state, and the internal signals.

        Parameters
        ----------
        x : array_like, shape (..., n_states)
            Measured states followed by hidden states; real or complex.
        u : array_like, shape (..., 2)
            Grid voltage magnitude ``ug`` (p.u.) and phase ``theta_g`` (rad).

        Returns
        -------
        dxdt : ndarray, shape (..., n_states)
            dx/dt in 1/s.
        signals : dict of ndarray
            See :meth:`internal_signals`.
        """
        p, c, eff = self.control, self.circuit, self.effects
        x = np.asarray(x)
        u = np.asarray(u)
        (delta, Pf, Qf, phi_d, phi_q, gam_d, gam_q,
         il_d, il_q, vc_d, vc_q, ig_d, ig_q) = (x[..., k] for k in range(N_MEASURED))
        ug, theta_g = u[..., 0], u[..., 1]
        wb = OMEGA_BASE

        # droop frequency and angle
        w = p.wset + p.mp * (p.Pset - Pf)
        if "frequency_limit" in eff:
            dw = eff["frequency_limit"]["dw_max"]
            w = _clip(w, p.wset - dw, p.wset + dw)
        d_delta = wb * (w - p.wg)

        # grid voltage in the inverter frame, output voltage behind the damping resistor
        vg_d = ug * np.cos(theta_g - delta)
        vg_q = ug * np.sin(theta_g - delta)
        vo_d = vc_d + c["Rd"] * (il_d - ig_d)
        vo_q = vc_q + c["Rd"] * (il_q - ig_q)
        p_inst = vo_d * ig_d + vo_q * ig_q
        q_inst = vo_q * ig_d - vo_d * ig_q
        d_Pf = p.wc * (p_inst - Pf)
        d_Qf = p.wc * (q_inst - Qf)

        # voltage reference (reactive droop on the d axis), optional virtual impedance
        vref_d = p.Vset + p.mq * (p.Qset - Qf) + 0.0 * delta
        vref_q = 0.0 * delta
        if "virtual_impedance" in eff:
            vi_cfg = eff["virtual_impedance"]
            ig_mag = np.sqrt(ig_d * ig_d + ig_q * ig_q)
            excess = np.where(_real(ig_mag) > vi_cfg["i_th"], ig_mag - vi_cfg["i_th"], 0.0 * ig_mag)
            r_v = vi_cfg["r"] + vi_cfg["k_r"] * excess
            x_v = vi_cfg["x"] + vi_cfg["xr"] * vi_cfg["k_r"] * excess
            vref_d = vref_d - (r_v * ig_d - x_v * ig_q)
            vref_q = vref_q - (r_v * ig_q + x_v * ig_d)

        # voltage PI on the output voltage vo (w·Cf decoupling, F·ig feed-forward) -> current reference
        ev_d, ev_q = vref_d - vo_d, vref_q - vo_q
        ilr_d = p.F * ig_d - w * p.Cf * vo_q + p.KpV * ev_d + p.KiV * phi_d
        ilr_q = p.F * ig_q + w * p.Cf * vo_d + p.KpV * ev_q + p.KiV * phi_q
        d_phi_d, d_phi_q = ev_d, ev_q
        ilr_free_d, ilr_free_q = ilr_d, ilr_q
        if "current_limit" in eff:
            cl = eff["current_limit"]
            sat_d, sat_q = _limit_magnitude(ilr_d, ilr_q, cl["imax"])
            d_phi_d = d_phi_d + cl["kaw"] * (sat_d - ilr_d)
            d_phi_q = d_phi_q + cl["kaw"] * (sat_q - ilr_q)
            ilr_d, ilr_q = sat_d, sat_q
        if "current_clamp" in eff:
            cc = eff["current_clamp"]
            ilr_d = _clip(ilr_d, -cc["imax_d"], cc["imax_d"])
            ilr_q = _clip(ilr_q, -cc["imax_q"], cc["imax_q"])

        # current PI (w·Lf decoupling, no voltage feed-forward) -> inverter voltage
        ei_d, ei_q = ilr_d - il_d, ilr_q - il_q
        vi_d = -w * p.Lf * il_q + p.KpC * ei_d + p.KiC * gam_d
        vi_q = w * p.Lf * il_d + p.KpC * ei_q + p.KiC * gam_q
        d_gam_d, d_gam_q = ei_d, ei_q
        if "voltage_limit" in eff:
            vl = eff["voltage_limit"]
            sat_d, sat_q = _limit_magnitude(vi_d, vi_q, vl["vmax"])
            d_gam_d = d_gam_d + vl["kaw"] * (sat_d - vi_d)
            d_gam_q = d_gam_q + vl["kaw"] * (sat_q - vi_q)
            vi_d, vi_q = sat_d, sat_q

        vi_cmd_d, vi_cmd_q = vi_d, vi_q
        extra = []
        if self._delay is not None:
            a, b, cc_, dd = self._delay
            order = b.shape[-1]
            z_d = x[..., N_MEASURED:N_MEASURED + order]
            z_q = x[..., N_MEASURED + order:N_MEASURED + 2 * order]
            if a.ndim == 2:
                dz_d = z_d @ a.T + vi_d[..., None] * b
                dz_q = z_q @ a.T + vi_q[..., None] * b
                vi_d = z_d @ cc_ + dd * vi_d
                vi_q = z_q @ cc_ + dd * vi_q
            else:  # a stack of plants (plant.stack): one delay per row of the batch
                dz_d = np.einsum("...ij,...j->...i", a, z_d) + vi_d[..., None] * b
                dz_q = np.einsum("...ij,...j->...i", a, z_q) + vi_q[..., None] * b
                vi_d = np.einsum("...j,...j->...", z_d, cc_) + dd * vi_d
                vi_q = np.einsum("...j,...j->...", z_q, cc_) + dd * vi_q
            extra = [dz_d[..., k] for k in range(order)] + [dz_q[..., k] for k in range(order)]

        # LCL filter in the frame rotating at w: (L/wb) di/dt = v - R i - j w L i
        d_il_d = wb / c["Lf"] * (vi_d - c["Rf"] * il_d - vo_d) + wb * w * il_q
        d_il_q = wb / c["Lf"] * (vi_q - c["Rf"] * il_q - vo_q) - wb * w * il_d
        d_vc_d = wb / c["Cf"] * (il_d - ig_d) + wb * w * vc_q
        d_vc_q = wb / c["Cf"] * (il_q - ig_q) - wb * w * vc_d
        d_ig_d = wb / c["Lg"] * (vo_d - vg_d - c["Rg"] * ig_d) + wb * w * ig_q
        d_ig_q = wb / c["Lg"] * (vo_q - vg_q - c["Rg"] * ig_q) - wb * w * ig_d

        dxdt = np.stack(
            [d_delta, d_Pf, d_Qf, d_phi_d, d_phi_q, d_gam_d, d_gam_q,
             d_il_d, d_il_q, d_vc_d, d_vc_q, d_ig_d, d_ig_q, *extra],
            axis=-1,
        )
        signals = {"w": w, "p": p_inst, "q": q_inst, "vo_d": vo_d, "vo_q": vo_q, "vref_d": vref_d,
                   "vref_q": vref_q, "ilref_d": ilr_d, "ilref_q": ilr_q, "ilref_unlimited_d": ilr_free_d,
                   "ilref_unlimited_q": ilr_free_q, "vi_d": vi_d, "vi_q": vi_q,
                   "vi_cmd_d": vi_cmd_d, "vi_cmd_q": vi_cmd_q}
        return dxdt, signals

    # ------------------------------------------------------------------ linearisation
    def jacobian(self, x, u, wrt: str = "x") -> np.ndarray:
        """Exact Jacobian of the vector field by complex-step differentiation.

        Parameters
        ----------
        x : array_like, shape (n_states,)
        u : array_like, shape (2,)
        wrt : {"x", "u"}
            Differentiate with respect to the state (A matrix) or the input (B).

        Returns
        -------
        ndarray, shape (n_states, n_states) or (n_states, 2)
        """
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        base = x if wrt == "x" else u
        n = base.shape[-1]
        probe = np.repeat(base[None, :].astype(complex), n, axis=0)
        probe[np.arange(n), np.arange(n)] += 1j * _COMPLEX_STEP
        if wrt == "x":
            out = self.vector_field(probe, np.broadcast_to(u, (n, u.shape[-1])))
        elif wrt == "u":
            out = self.vector_field(np.broadcast_to(x, (n, x.shape[-1])), probe)
        else:
            raise ValueError(f"wrt must be 'x' or 'u', got {wrt!r}")
        return np.imag(out).T / _COMPLEX_STEP

    # ------------------------------------------------------------------ equilibrium
    def initial_guess(self, ug: float, theta_g: float = 0.0) -> np.ndarray:
        """A rough operating point from a phasor power-flow estimate (for the root finder)."""
        p = self.params
        x = np.zeros(self.n_states)
        x_line = self.circuit["Lg"]
        # angle for the scheduled power over the grid-side reactance
        delta = theta_g + math.asin(max(-0.9, min(0.9, p.Pset * x_line / max(ug, 1e-3))))
        vc = complex(p.Vset, 0.0)
        vg = ug * complex(math.cos(theta_g - delta), math.sin(theta_g - delta))
        ig = (vc - vg) / complex(self.circuit["Rg"], x_line)
        il = ig + 1j * self.circuit["Cf"] * vc
        x[:N_MEASURED] = [delta, p.Pset, (vc * ig.conjugate()).imag, 0, 0, 0, 0,
                          il.real, il.imag, vc.real, vc.imag, ig.real, ig.imag]
        return x

    def equilibrium(self, ug: float, theta_g: float = 0.0, x0=None, tol: float = 1e-11) -> np.ndarray:
        """Operating point f(x, u) = 0 at grid voltage ``ug`` and phase ``theta_g``.

        Solved with scipy's hybrid Powell method and the exact Jacobian; where a
        direct solve fails, by continuation in ``ug`` from 1.0 p.u.

        Returns
        -------
        ndarray, shape (n_states,)

        Raises
        ------
        EquilibriumError
            If no equilibrium with a residual below ``tol`` is found.
        """
        u = np.array([ug, theta_g], dtype=float)
        starts = [x0] if x0 is not None else []
        if self.effects:
            # limiters can trap Newton far from the solution: start from the ideal plant's equilibrium
            try:
                ideal = InverterPlant(self.params).equilibrium(ug, theta_g, tol=tol)
                starts.append(np.concatenate([ideal, np.zeros(self.n_states - N_MEASURED)]))
            except EquilibriumError:
                pass
        starts.append(self.initial_guess(ug, theta_g))
        for start in starts:
            x = self._solve(u, np.asarray(start, dtype=float), tol)
            if x is not None:
                return x
        # continuation from nominal voltage
        u_nominal = np.array([1.0, theta_g])
        x = self._solve(u_nominal, self.initial_guess(1.0, theta_g), tol)
        if x is not None:
            x = continuation(self.vector_field, self.jacobian, u_nominal, x, u, 24, self._accept(tol))
            if x is not None:
                return self._wrap_angle(x, u)
        raise EquilibriumError(f"no equilibrium found at ug={ug}, theta_g={theta_g}")

    def _accept(self, tol):
        # (a NaN or infinite residual fails the comparison)
        return residual_below(self.vector_field, tol * 1e3, self._residual_scale())

    @staticmethod
    def _wrap_angle(x, u):
        # angles are defined modulo 2π: keep delta - theta_g in (-π, π]
        x = x.copy()
        x[0] = u[1] + (x[0] - u[1] + math.pi) % (2 * math.pi) - math.pi
        return x

    def _solve(self, u, start, tol):
        x = root(self.vector_field, self.jacobian, u, start, self._accept(tol))
        return None if x is None else self._wrap_angle(x, u)

    def _residual_scale(self):
        # the filter equations are scaled by wb/L ~ 1e4; compare residuals on a per-unit footing
        scale = np.ones(self.n_states)
        scale[7:13] = OMEGA_BASE / min(self.circuit["Lf"], self.circuit["Cf"], self.circuit["Lg"])
        scale[0] = OMEGA_BASE
        return scale

    def full_state(self, x_measured, u) -> np.ndarray:
        """Extend measured states (..., 13) with hidden states in steady state for the inputs u.

        The delay's Padé states are set so that the delayed voltage equals the
        command (the state a delay settles to when the command is constant).
        """
        x_measured = np.asarray(x_measured, dtype=float)
        if self.n_states == N_MEASURED:
            return x_measured
        hidden = np.zeros(x_measured.shape[:-1] + (self.n_states - N_MEASURED,))
        full = np.concatenate([x_measured, hidden], axis=-1)
        if self._delay is not None:
            a, b, _, _ = self._delay
            sig = self.internal_signals(full, u)
            z_per_volt = -np.linalg.solve(a, b)  # steady state of z' = A z + B v for v = 1
            order = len(b)
            full[..., N_MEASURED:N_MEASURED + order] = sig["vi_cmd_d"][..., None] * z_per_volt
            full[..., N_MEASURED + order:N_MEASURED + 2 * order] = sig["vi_cmd_q"][..., None] * z_per_volt
        return full

    def eigenvalues(self, ug: float, theta_g: float = 0.0) -> np.ndarray:
        """Eigenvalues (1/s) of the linearisation at the equilibrium for (ug, theta_g)."""
        x = self.equilibrium(ug, theta_g)
        return np.linalg.eigvals(self.jacobian(x, [ug, theta_g]))
