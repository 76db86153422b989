"""Saturation-type candidates found in the records: the limit of a dq reference.

A grid-forming inverter's cascaded control limits the reference its inner loop tracks, the
current reference il* = ℓ(x), in one of two ways (DESIGN.md's effects):

- a magnitude limit (``current_limit``): ℓ scaled down to magnitude m where |ℓ| > m,
  S = ℓ · min(1, m / |ℓ|);
- a per-axis clamp (``current_clamp``): each axis clipped on its own, S_d = clip(ℓ_d, −m_d, m_d),
  S_q = clip(ℓ_q, −m_q, m_q).

With the limit active, every equation the reference enters (the inner integrator's, the inductor
current's through the PI's proportional part, the outer integrator's anti-windup) holds S(x),
ℓ = (ℓ_d, ℓ_q) affine in the states, which no fixed library has: ℓ and the limits are the
plant's, unknown. This module fits them to the records so that S_d and S_q become two terms of the
library (sympy strings with ``Min``, ``Max`` and ``sqrt``, so a model that uses them is still data:
``ExplicitModel`` JSON, rebuilt by anyone).

How ℓ and the limits are found (:func:`fit_reference_limit`). A PI integrator I integrates its error,
dI/dt = S − c for the measured signal c the loop controls; for each pair of integrators and each
current pair of the roles that is a constraint, in integral form over windows of ``span`` samples
(noise averaged, as the backbone): I(t+T) − I(t) + ∫c = ∫S. Those rows fix ℓ where the limit is
inactive (most samples). The current rows add what the limit does when it acts: each is Θ(x, u)
(the physics library) plus a free combination of S_d, S_q, the linear part profiled out
(variable projection). scipy's ``least_squares`` fits ℓ's coefficients and the limits from a few
starts (at high percentiles of |ℓ|, or of |ℓ_d| and |ℓ_q|, from the integrators' linear fit); the
kind and pairing that explain the records best are kept, and only where the limit removes a clear
share of their misfit and acts on enough samples. ℓ leaves out the angle (the equations of a dq
controller do not depend on the grid's phase but through the grid terms) and the integrator pair
itself (a cascade's reference comes from the outer loop).

Measured (stop 54, the benchmark's saturation plant, ``current_limit`` imax 2.2, scratch
/tmp/sat): clean records (recording 0), m = 2.2000, the limited reference's error on the test
records 0.002 (rms, p.u., against its rms 1.13); 40 dB, recordings 0 / 1 / 2, m = 2.2065 / 2.2105
/ 2.1943, error 0.037 / 0.091 / 0.079. Windows of 20 samples: on recording 0 before ℓ's small
parts were dropped, 0.24 with windows of 10, 0.045 with 20, 0.084 with 30, 0.085 with 40.
"""
from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from ..data import Dataset
from ..model.expressions import parse_term, term_set
from .derivatives import cumulative_integral, integral_form
from .library import is_limited, physics_library
from .roles import SignalRoles
from .trajfit import blas_threads


KINDS = ("magnitude", "clamp")


@dataclasses.dataclass
class ReferenceLimit:
    """A fitted limit of a dq reference (see the module's docstring).

    Attributes
    ----------
    kind : str
        ``"magnitude"`` (one limit on |ℓ|) or ``"clamp"`` (one limit per axis).
    integrators : (str, str)
        The integrator pair whose input is the limited reference.
    measured : (str, str)
        The current pair that integrator pair's loop controls (dI/dt = S − measured).
    argument : dict
        ``{"d": {signal: coefficient}, "q": {...}}`` of ℓ (``"1"`` for the constant).
    limit : tuple of float
        ``(m,)``, the largest magnitude of the reference, or ``(m_d, m_q)``, the largest magnitude
        of each axis (units of the measured pair).
    saturated_fraction : float
        Share of the records' samples where the limit acts (|ℓ| > m, or an axis beyond its own).
    misfit_reduction : float
        Share of the whitened integral-form misfit (integrator and current rows) the limit removes.
    """

    kind: str
    integrators: tuple
    measured: tuple
    argument: dict
    limit: tuple
    saturated_fraction: float
    misfit_reduction: float

    def terms(self) -> list[str]:
        """The terms S_d, S_q as sympy-parsable strings over the signals."""
        return limiter_terms(self.argument["d"], self.argument["q"], self.limit, self.kind)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "integrators": list(self.integrators), "measured": list(self.measured),
                "argument": {axis: dict(v) for axis, v in self.argument.items()}, "limit": list(self.limit),
                "saturated_fraction": self.saturated_fraction, "misfit_reduction": self.misfit_reduction,
                "terms": self.terms()}


def _number(value: float) -> str:
    """A fitted number as a decimal literal, "2.0" and not "2" (``ExplicitModel.n_parameters`` counts
    the decimals written in the terms)."""
    text = f"{value:.7g}"
    return text if any(c in text for c in ".en") else text + ".0"


def _affine_text(coefficients: dict) -> str:
    parts = [_number(value) if name == "1" else f"{_number(value)}*{name}" for name, value in coefficients.items()
             if value != 0]
    return "(" + (" + ".join(parts).replace("+ -", "- ") if parts else "0") + ")"


def _checked_kind(kind: str) -> str:
    if kind not in KINDS:
        raise ValueError(f"limiter kind {kind!r}: expected one of {KINDS}")
    return kind


def limiter_terms(argument_d: dict, argument_q: dict, limit, kind: str = "magnitude") -> list[str]:
    """``[S_d, S_q]``: the affine references ``argument_*`` ({signal: coefficient}, ``"1"`` the
    constant) limited by ``limit``: for ``kind`` "magnitude" (``limit`` m or ``(m,)``) scaled down
    to magnitude m where they exceed it, for "clamp" (``limit`` ``(m_d, m_q)``) each clipped to
    ±its own."""
    return _limited(_affine_text(argument_d), _affine_text(argument_q), limit, kind)


def _limited(ld: str, lq: str, limit, kind: str) -> list[str]:
    """``[S_d, S_q]`` of the references written ``ld``, ``lq`` (:func:`limiter_terms`)."""
    limit = np.atleast_1d(np.asarray(limit, dtype=float))
    if kind == "magnitude":
        scale = f"Min(1, {_number(limit[0])}/sqrt({ld}**2 + {lq}**2))"
        return [f"{ld}*{scale}", f"{lq}*{scale}"]
    if _checked_kind(kind) == "clamp":
        return [f"Max({_number(-m)}, Min({_number(m)}, {text}))" for text, m in zip((ld, lq), limit)]


def readable_equations(model, digits: int = 5) -> list[str]:
    """The equations of ``model`` (an ``ExplicitModel``) for a reader: each term with a ``Min`` or
    ``Max`` it uses written as a name, defined after the equations in lines ``where NAME = ...``.

    The limit the engine found (``model.metadata["limiter"]``) reads as the controller's: the
    reference as ``l_d``, ``l_q`` (its numbers as the terms hold them) and the limited reference as
    ``S_d``, ``S_q`` of them; any other such term as ``S1``, ``S2``, …. A name already taken by a
    signal gets a trailing ``_``. Without such terms these are :meth:`ExplicitModel.equations`.
    """
    signals = [*model.state_names, *model.input_names]
    used = [term for term, row in zip(model.terms, model.coefficients) if np.any(row != 0)]
    limited = [term for term in used if is_limiter_term(term, signals)]
    taken = set(signals)

    def fresh(name: str) -> str:
        while name in taken:
            name += "_"
        taken.add(name)
        return name

    names, definitions = {}, []
    found = ((getattr(model, "metadata", None) or {}).get("limiter") or {}).get("limit") or {}
    try:
        kind = found.get("kind", "magnitude")
        # the record's terms rebuilt from its numbers: names only where they say the same thing
        ours = limiter_terms(found["argument"]["d"], found["argument"]["q"], found["limit"], kind) \
            if found.get("terms") and set(found["terms"]) & set(limited) else None
    except (KeyError, TypeError, ValueError):
        ours = None
    if ours is not None and ours == list(found["terms"]):
        reference = {axis: fresh(f"l_{axis}") for axis in "dq"}
        definitions += [f"{reference[axis]} = {_affine_text(found['argument'][axis])[1:-1]}" for axis in "dq"]
        for axis, term, text in zip("dq", ours, _limited(reference["d"], reference["q"], found["limit"], kind)):
            if term in limited:
                names[term] = fresh(f"S_{axis}")
                definitions.append(f"{names[term]} = {text}")
    for k, term in enumerate([term for term in limited if term not in names]):
        names[term] = fresh(f"S{k + 1}")
        definitions.append(f"{names[term]} = {term}")
    return model.equations(digits=digits, names=names) + [f"where {line}" for line in definitions]


def is_limiter_term(text: str, signals) -> bool:
    """Whether a term is a limiter's (it has a ``Min`` or ``Max``)."""
    return is_limited(parse_term(text, signals))


def _pairs(names) -> list[tuple]:
    return [tuple(names[k:k + 2]) for k in range(0, len(names) - 1, 2)]


class _WindowIntegrals:
    """The windows of :func:`~.derivatives.integral_form` over ``span`` samples, every ``span // 2``
    (trapezoid rule): Θ's integrals and the states' increments over them, and the integrals of any
    per-sample values stacked over the records."""

    def __init__(self, dataset: Dataset, theta, span: int):
        stride = max(1, span // 2)
        self.theta, self._increments = integral_form(dataset, theta, span=span, stride=stride)
        self.pieces = [(tr.t, np.arange(0, len(tr) - span, stride)) for tr in dataset]
        self.span = span
        # records on one time grid (the usual case) are integrated as one array: the search calls
        # this thousands of times, and the loop over records was 40 % of it (stop 86: 2.1 of 5.1 s,
        # 12 records). The same sums in the same order (cumsum along the samples), so the same values
        t0 = self.pieces[0][0] if self.pieces else None
        same = bool(self.pieces) and all(t.shape == t0.shape and np.array_equal(t, t0) for t, _ in self.pieces)
        self._grid = (np.diff(t0)[None, :, None], self.pieces[0][1]) if same else None

    def __call__(self, values: np.ndarray) -> np.ndarray:
        if self._grid is not None:
            steps, starts = self._grid
            stacked = values.reshape(len(self.pieces), steps.shape[1] + 1, values.shape[1])
            cumulative = np.concatenate([np.zeros((len(self.pieces), 1, values.shape[1])),
                                         np.cumsum(0.5 * (stacked[:, 1:] + stacked[:, :-1]) * steps, 1)], axis=1)
            return (cumulative[:, starts + self.span] - cumulative[:, starts]).reshape(-1, values.shape[1])
        out, offset = [], 0
        for t, starts in self.pieces:
            cumulative = cumulative_integral(values[offset:offset + len(t)], t)
            offset += len(t)
            out.append(cumulative[starts + self.span] - cumulative[starts])
        return np.concatenate(out)

    def increments(self, columns) -> np.ndarray:
        return self._increments[:, columns]


def fit_reference_limit(dataset: Dataset, roles: SignalRoles | None = None, span: int = 20,
                        kinds=KINDS, min_reduction: float = 0.15, min_saturated: int = 10,
                        percentiles=(90.0, 99.0), max_nfev: int = 40, sparse_threshold: float = 0.01,
                        sparse_loss: float = 0.02) -> ReferenceLimit | None:
    """Fit the limit of a dq reference to the records (module docstring), or None where no kind
    and pairing of the roles' integrators and currents shows one.

    Parameters
    ----------
    dataset : Dataset
        Training records (states and inputs as the roles name them).
    roles : SignalRoles, optional
        Which states are the integrators (taken in d/q pairs) and the current pairs.
    span : int
        Samples per integral-form window.
    kinds : sequence of str
        The kinds of limit tried (:data:`KINDS`); the one that removes the most misfit is kept.
    min_reduction : float
        Least share of the whitened misfit the limit must remove. Measured (stop 56): on records with
        a limit, 0.21–0.37 at 40 dB (the benchmark's magnitude limit and clamp, recordings 0–3) and
        0.9999 clean, but 0.047–0.085 at 30 dB and 0.02–0.025 at 20 dB; on 41 record sets without
        one (protocol recordings 0–9 at 40 dB, clean, 20 and 30 dB, the other inverters, the
        scenarios at 40 dB) at most 0.074 (5 kHz, recording 0), the only one above 0.05.
    min_saturated : int
        Least number of samples where it must act.
    sparse_threshold : float
        ℓ's terms whose share of its spread is below this are dropped and the rest re-fitted, where
        that raises the misfit left by at most the fraction ``sparse_loss`` (0: ℓ keeps every state).

    Returns
    -------
    ReferenceLimit or None
    """
    kinds = [_checked_kind(kind) for kind in kinds]
    # the problems are small (~2k rows): OpenBLAS's threads spinning on each of their ~9000 lstsq
    # calls and SVDs made a search take 28 s on 2 cores against 5.9 s on one thread, the same limit
    # (stop 56, the saturation plant's 40 dB recording 0)
    with blas_threads(1):
        return _fit_reference_limit(dataset, roles or SignalRoles(), span, kinds, min_reduction, min_saturated,
                                    percentiles, max_nfev, sparse_threshold, sparse_loss)


def _fit_reference_limit(dataset, roles, span, kinds, min_reduction, min_saturated, percentiles, max_nfev,
                         sparse_threshold, sparse_loss) -> ReferenceLimit | None:
    names = list(dataset.state_names)
    signals = names + list(dataset.input_names)
    currents = [pair for pair in (tuple(roles.current), *map(tuple, roles.other_currents))
                if all(s in names for s in pair)]
    integrator_pairs = _pairs([s for s in roles.integrators if s in names])
    if not currents or not integrator_pairs or len(dataset) == 0:
        return None
    if min(len(tr) for tr in dataset) <= span:
        return None
    x = np.concatenate([tr.x for tr in dataset])
    theta = term_set(physics_library(roles, names, coupling=True), signals)
    windows = _WindowIntegrals(dataset, theta, span)

    best = None
    for pair in integrator_pairs:
        keep = [k for k, s in enumerate(names) if s not in pair and s != roles.angle]
        a = np.column_stack([np.ones(len(x)), x[:, keep]])
        for measured, kind in itertools.product(currents, kinds):
            problem = _LimitProblem(dataset, windows, a, names, pair, measured, kind)
            for k, q in enumerate(percentiles):
                fitted = problem.fit(problem.start(q), max_nfev=max_nfev)
                if fitted is not None and fitted[2] >= min_saturated and fitted[1] >= min_reduction and \
                        (best is None or fitted[1] > best[0][1]):
                    best = (fitted, problem, keep)
                if k == 0 and fitted is not None and fitted[1] < min_reduction / 3:
                    # no sign of a limit from the first start: the others are not tried (stop 56: the
                    # first start removed at most 0.02 on limit-free records, 0.17-1.0 on the pairing
                    # that wins on limited ones, and no later start won where the first was below 0.05)
                    break
    if best is None:
        return None
    (p, reduction, saturated), problem, keep = best
    if sparse_threshold > 0:
        # the reference's small parts out (each axis' terms below sparse_threshold of its spread), re-fitted
        coef = p[:-problem.n_limits].reshape(-1, 2)
        share = np.abs(coef) * problem.a.std(axis=0)[:, None] / np.maximum((problem.a @ coef).std(axis=0), 1e-300)
        free = share >= sparse_threshold
        free[0] = True  # the constant
        sparse = problem.fit(np.r_[np.where(free, coef, 0.0).ravel(), p[-problem.n_limits:]], max_nfev=max_nfev,
                             free=free.ravel())
        if sparse is not None and sparse[2] >= min_saturated and \
                1.0 - sparse[1] <= (1.0 + sparse_loss) * (1.0 - reduction):
            p, reduction, saturated = sparse
    coef = p[:-problem.n_limits].reshape(-1, 2)
    argument = {axis: {name: float(value) for name, value in zip(["1", *[names[k] for k in keep]], coef[:, j])
                       if value != 0}
                for j, axis in enumerate("dq")}
    return ReferenceLimit(problem.kind, problem.pair, problem.measured, argument,
                          tuple(float(m) for m in p[-problem.n_limits:]), saturated / len(x), float(reduction))


class _LimitProblem:
    """The least-squares problem of one kind of limit and one pairing (integrator pair, the current
    pair its loop controls): parameters ℓ's coefficients over ``a``'s columns (constant, states) for d
    and q, then the limits (m, or m_d and m_q)."""

    def __init__(self, dataset, windows, a, names, pair, measured, kind="magnitude"):
        self.kind, self.n_limits = _checked_kind(kind), (1 if kind == "magnitude" else 2)
        self.pair, self.measured = tuple(pair), tuple(measured)
        self.a, self.windows, self.theta_int = a, windows, windows.theta
        self.y_int = windows.increments([names.index(s) for s in pair]) + \
            windows(np.concatenate([tr.x[:, [names.index(s) for s in measured]] for tr in dataset]))
        # the loop's own current rows see the limit through the PI's proportional part
        self.y_free = windows.increments([names.index(s) for s in measured])
        linear, *_ = np.linalg.lstsq(self.theta_int, self.y_free, rcond=None)
        self.w_free = 1.0 / np.maximum((self.y_free - self.theta_int @ linear).std(axis=0), 1e-300)
        self.a_int = windows(a)
        self.w0, *_ = np.linalg.lstsq(self.a_int, self.y_int, rcond=None)
        self.w_int = 1.0 / np.maximum((self.y_int - self.a_int @ self.w0).std(axis=0), 1e-300)
        self.without = float(np.sum(self.residuals(np.r_[self.w0.ravel(), [np.inf] * self.n_limits]) ** 2))

    def limited(self, p):
        """The limited reference S per sample, and where the limit acts."""
        ref = self.a @ p[:-self.n_limits].reshape(-1, 2)
        limits = p[-self.n_limits:]
        if self.kind == "clamp":
            return np.clip(ref, -limits, limits), np.any(np.abs(ref) > limits, axis=1)
        magnitude = np.hypot(ref[:, 0], ref[:, 1])
        return ref * np.minimum(1.0, limits[0] / np.maximum(magnitude, 1e-300))[:, None], magnitude > limits[0]

    def residuals(self, p):
        s_int = self.windows(self.limited(p)[0])
        features = np.column_stack([self.theta_int, s_int])
        c, *_ = np.linalg.lstsq(features, self.y_free, rcond=None)
        return np.concatenate([((self.y_int - s_int) * self.w_int).ravel(),
                               ((self.y_free - features @ c) * self.w_free).ravel()])

    def start(self, percentile: float) -> np.ndarray:
        """ℓ from the integrator rows' linear fit, the limits at a percentile of its magnitude (of
        each axis' for a clamp)."""
        ref = self.a @ self.w0
        size = np.abs(ref) if self.kind == "clamp" else np.hypot(ref[:, 0], ref[:, 1])
        return np.r_[self.w0.ravel(), np.percentile(size, percentile, axis=0)]

    def fit(self, p0, max_nfev: int, free=None):
        """(parameters, share of the misfit removed, samples where the limit acts), or None where the
        fit fails; ``free`` (bool over ℓ's coefficients) holds the others at ``p0``'s values."""
        import scipy.optimize

        free = np.r_[np.ones(len(p0) - self.n_limits, dtype=bool) if free is None else free,
                     np.ones(self.n_limits, dtype=bool)]

        def residuals(v):
            p = p0.copy()
            p[free] = v
            return self.residuals(p)

        try:
            sol = scipy.optimize.least_squares(residuals, p0[free], method="trf", x_scale="jac", max_nfev=max_nfev)
        except (ValueError, np.linalg.LinAlgError):
            return None
        p = p0.copy()
        p[free] = sol.x
        if not (np.all(np.isfinite(p)) and np.all(p[-self.n_limits:] > 0)):
            return None
        return p, 1.0 - 2.0 * sol.cost / self.without, int(np.sum(self.limited(p)[1]))


def _found_limit(model) -> dict | None:
    record = (getattr(model, "metadata", None) or {}).get("limiter") or {}
    return record["limit"] if record.get("found") else None


def limit_in_use(model) -> bool | None:
    """Whether ``model`` uses the limit the engine found in its records (a term of it with a nonzero
    coefficient), or None where none was searched for or found."""
    found = _found_limit(model)
    if found is None:
        return None
    return any(term in model.terms and bool(np.any(model.coefficients[model.terms.index(term)] != 0))
               for term in found["terms"])


def limit_note(model) -> str | None:
    """The limit the engine found in the records (``model.metadata["limiter"]``, from ``PISML``), in
    words for a user, or None where none was searched for or found."""
    found = _found_limit(model)
    if found is None:
        return None
    used = limit_in_use(model)
    limits = np.atleast_1d(found["limit"])
    if found.get("kind", "magnitude") == "clamp":
        what, how = "a per-axis clamp", f"clamped to ±{limits[0]:.4g} (d) and ±{limits[-1]:.4g} (q)"
    else:
        what, how = "a magnitude limit", f"limited to {limits[0]:.4g}"
    return (f"{what} found in the records: {'/'.join(found['integrators'])} integrate a reference {how} "
            f"minus {'/'.join(found['measured'])}, the limit acting on "
            f"{100 * found['saturated_fraction']:.1f} % of the samples; "
            + ("the model uses it" if used else "the model chosen does not use it, so where the limit acts harder "
               "than in these records (deeper sags, faults) expect the model's response to differ from the inverter's"))
