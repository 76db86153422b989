"""Saturation-type candidates found in the records: the magnitude limit of a dq reference.

A grid-forming inverter's cascaded control limits the reference its inner loop tracks: the
current reference il* = ℓ(x) is scaled down to a magnitude m where |ℓ| > m (DESIGN.md's
``current_limit``; a voltage command limited the same way is the modulation's saturation). With
the limit active, every equation the reference enters (the inner integrator's, the inductor
current's through the PI's proportional part, the outer integrator's anti-windup) holds

    S(x) = ℓ(x) · min(1, m / |ℓ(x)|),        ℓ = (ℓ_d, ℓ_q) affine in the states,

which no fixed library has: ℓ and m are the plant's, unknown. This module fits them to the
records so that S_d and S_q become two terms of the library (sympy strings with ``Min`` and
``sqrt``, so a model that uses them is still data: ``ExplicitModel`` JSON, rebuilt by anyone).

How ℓ and m are found (:func:`fit_magnitude_limit`). A PI integrator I integrates its error,
dI/dt = S − c for the measured signal c the loop controls; for each pair of integrators and each
current pair of the roles that is a constraint, in integral form over windows of ``span`` samples
(noise averaged, as the backbone): I(t+T) − I(t) + ∫c = ∫S. Those rows fix ℓ where the limit is
inactive (most samples). The current rows add what the limit does when it acts: each is Θ(x, u)
(the physics library) plus a free combination of S_d, S_q, the linear part profiled out
(variable projection). scipy's ``least_squares`` fits ℓ's coefficients and m from a few starts (m
at high percentiles of |ℓ| from the integrators' linear fit); the pairing that explains the
records best is kept, and only where the limit removes a clear share of their misfit and acts on
enough samples. ℓ leaves out the angle (the equations of a dq controller do not depend on the
grid's phase but through the grid terms) and the integrator pair itself (a cascade's reference
comes from the outer loop).

Measured (stop 54, the benchmark's saturation plant, ``current_limit`` imax 2.2, recording 0,
scratch /tmp/sat): clean records, m = 2.2000, the reference's error on the test records 0.002
(rms, p.u.); 40 dB, m = 2.198, error of the limited reference 0.045 against its rms 1.13 with
windows of 20 samples (0.24 with windows of 10, 0.085 with 40).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..data import Dataset
from ..model.expressions import parse_term, term_set
from .library import physics_library
from .roles import SignalRoles


@dataclasses.dataclass
class MagnitudeLimit:
    """A fitted magnitude limit of a dq reference (see the module's docstring).

    Attributes
    ----------
    integrators : (str, str)
        The integrator pair whose input is the limited reference.
    measured : (str, str)
        The current pair that integrator pair's loop controls (dI/dt = S − measured).
    argument : dict
        ``{"d": {signal: coefficient}, "q": {...}}`` of ℓ (``"1"`` for the constant).
    limit : float
        m, the largest magnitude of the reference (units of the measured pair).
    saturated_fraction : float
        Share of the records' samples where |ℓ| > m.
    misfit_reduction : float
        Share of the whitened integral-form misfit (integrator and current rows) the limit removes.
    """

    integrators: tuple
    measured: tuple
    argument: dict
    limit: float
    saturated_fraction: float
    misfit_reduction: float

    def terms(self) -> list[str]:
        """The terms S_d, S_q as sympy-parsable strings over the signals."""
        return limiter_terms(self.argument["d"], self.argument["q"], self.limit)

    def to_dict(self) -> dict:
        return {"integrators": list(self.integrators), "measured": list(self.measured),
                "argument": {axis: dict(v) for axis, v in self.argument.items()}, "limit": self.limit,
                "saturated_fraction": self.saturated_fraction, "misfit_reduction": self.misfit_reduction,
                "terms": self.terms()}


def _affine_text(coefficients: dict) -> str:
    parts = [f"{value:.7g}" if name == "1" else f"{value:.7g}*{name}" for name, value in coefficients.items()
             if value != 0]
    return "(" + (" + ".join(parts).replace("+ -", "- ") if parts else "0") + ")"


def limiter_terms(argument_d: dict, argument_q: dict, limit: float) -> list[str]:
    """``[S_d, S_q]``: the affine references ``argument_*`` ({signal: coefficient}, ``"1"`` the
    constant) scaled down to magnitude ``limit`` where they exceed it."""
    ld, lq = _affine_text(argument_d), _affine_text(argument_q)
    scale = f"Min(1, {limit:.7g}/sqrt({ld}**2 + {lq}**2))"
    return [f"{ld}*{scale}", f"{lq}*{scale}"]


def is_limiter_term(text: str, signals) -> bool:
    """Whether a term is a limiter's (it has a ``Min`` or ``Max``)."""
    import sympy

    return bool(parse_term(text, signals).has(sympy.Min, sympy.Max))


def _pairs(names) -> list[tuple]:
    return [tuple(names[k:k + 2]) for k in range(0, len(names) - 1, 2)]


class _WindowIntegrals:
    """∫ over windows of ``span`` samples (trapezoid rule, each record's own windows), of per-sample
    values stacked over the records: the integral form of :func:`~.derivatives.integral_form`."""

    def __init__(self, dataset: Dataset, span: int):
        self.pieces = []
        for tr in dataset:
            n = len(tr)
            starts = np.arange(0, max(n - span, 0), max(1, span // 2))
            self.pieces.append((np.diff(tr.t), starts, n))
        self.span = span

    def __call__(self, values: np.ndarray) -> np.ndarray:
        out, offset = [], 0
        for steps, starts, n in self.pieces:
            v = values[offset:offset + n]
            offset += n
            cumulative = np.concatenate([np.zeros((1, v.shape[1])),
                                         np.cumsum((v[1:] + v[:-1]) / 2 * steps[:, None], axis=0)])
            out.append(cumulative[starts + self.span] - cumulative[starts])
        return np.concatenate(out)

    def increments(self, dataset: Dataset, columns) -> np.ndarray:
        return np.concatenate([tr.x[starts + self.span][:, columns] - tr.x[starts][:, columns]
                               for tr, (_, starts, _) in zip(dataset, self.pieces)])


def fit_magnitude_limit(dataset: Dataset, roles: SignalRoles | None = None, span: int = 20,
                        min_reduction: float = 0.05, min_saturated: int = 10,
                        percentiles=(90.0, 95.0, 99.0), max_nfev: int = 60) -> MagnitudeLimit | None:
    """Fit the magnitude limit of a dq reference to the records (module docstring), or None where
    no pairing of the roles' integrators and currents shows one.

    Parameters
    ----------
    dataset : Dataset
        Training records (states and inputs as the roles name them).
    roles : SignalRoles, optional
        Which states are the integrators (taken in d/q pairs) and the current pairs.
    span : int
        Samples per integral-form window.
    min_reduction : float
        Least share of the whitened misfit the limit must remove.
    min_saturated : int
        Least number of samples where it must act.

    Returns
    -------
    MagnitudeLimit or None
    """
    import scipy.optimize

    roles = roles or SignalRoles()
    names = list(dataset.state_names)
    signals = names + list(dataset.input_names)
    currents = [pair for pair in (tuple(roles.current), *map(tuple, roles.other_currents))
                if all(s in names for s in pair)]
    integrator_pairs = [pair for pair in _pairs([s for s in roles.integrators if s in names])]
    if not currents or not integrator_pairs or len(dataset) == 0:
        return None
    if min(len(tr) for tr in dataset) <= span:
        return None
    x = np.concatenate([tr.x for tr in dataset])
    theta = term_set(physics_library(roles, names, coupling=True), signals)
    windows = _WindowIntegrals(dataset, span)
    theta_int = windows(np.concatenate([theta.evaluate(np.concatenate([tr.x, tr.u], axis=1)) for tr in dataset]))

    best = None
    for pair in integrator_pairs:
        keep = [k for k, s in enumerate(names) if s not in pair and s != roles.angle]
        a = np.column_stack([np.ones(len(x)), x[:, keep]])
        a_int = windows(a)
        for measured in currents:
            y_int = windows.increments(dataset, [names.index(s) for s in pair]) + \
                windows(x[:, [names.index(s) for s in measured]])
            # the loop's own current rows see the limit through the PI's proportional part
            y_free = windows.increments(dataset, [names.index(s) for s in measured])
            linear, *_ = np.linalg.lstsq(theta_int, y_free, rcond=None)
            w_free = 1.0 / np.maximum((y_free - theta_int @ linear).std(axis=0), 1e-300)
            w0, *_ = np.linalg.lstsq(a_int, y_int, rcond=None)
            w_int = 1.0 / np.maximum((y_int - a_int @ w0).std(axis=0), 1e-300)

            def limited(p):
                ref = a @ p[:-1].reshape(-1, 2)
                magnitude = np.hypot(ref[:, 0], ref[:, 1])
                return ref * np.minimum(1.0, p[-1] / np.maximum(magnitude, 1e-300))[:, None], magnitude

            def residuals(p):
                s_int = windows(limited(p)[0])
                features = np.column_stack([theta_int, s_int])
                c, *_ = np.linalg.lstsq(features, y_free, rcond=None)
                return np.concatenate([((y_int - s_int) * w_int).ravel(), ((y_free - features @ c) * w_free).ravel()])

            without = float(np.sum(residuals(np.r_[w0.ravel(), np.inf]) ** 2))
            magnitude0 = np.hypot(*(a @ w0).T)
            for q in percentiles:
                p0 = np.r_[w0.ravel(), np.percentile(magnitude0, q)]
                try:
                    sol = scipy.optimize.least_squares(residuals, p0, method="trf", x_scale="jac", max_nfev=max_nfev)
                except (ValueError, np.linalg.LinAlgError):
                    continue
                if not (np.all(np.isfinite(sol.x)) and sol.x[-1] > 0):
                    continue
                saturated = int(np.sum(limited(sol.x)[1] > sol.x[-1]))
                reduction = 1.0 - 2.0 * sol.cost / without
                if saturated >= min_saturated and reduction >= min_reduction and \
                        (best is None or reduction > best[0]):
                    best = (reduction, pair, measured, keep, sol.x, saturated)
    if best is None:
        return None
    reduction, pair, measured, keep, p, saturated = best
    coef = p[:-1].reshape(-1, 2)
    argument = {axis: {name: float(value) for name, value in zip(["1", *[names[k] for k in keep]], coef[:, j])}
                for j, axis in enumerate("dq")}
    return MagnitudeLimit(tuple(pair), tuple(measured), argument, float(p[-1]), saturated / len(x), float(reduction))
