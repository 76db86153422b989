"""The `unnamed` effect: when no catalogue effect explains the gap, learn the missing dynamics.

The residual vector field r(x, u) = f_true − f_ref is fitted by sparse regression
(pysindy STLSQ) over the extended library Θ_ext in integral form:
x(t+T) − x(t) − ∫ f_ref dt = ∫ Θ_ext dt · C. The discovered terms become an
explicit model added to the reference, and the gap is shown before and after.
(The PISML neural residual is not used here yet: this is the distillation step
applied to the measured residual directly.)
"""
from __future__ import annotations

import numpy as np

from ..ident.library import extended_library
from ..ident.roles import RoleError, SignalRoles
from ..model import ExplicitModel
from ..model.expressions import term_set


def learn_unnamed_effect(flow, ref, data, span: int = 10, threshold: float = 0.05) -> dict | None:
    """Fit the residual dynamics; return {"reference", "terms", "evidence"} or None if nothing helps."""
    import pysindy as ps

    from .workflow import gap_percent

    try:
        roles = SignalRoles()
        roles.check(data.state_names, data.input_names)
    except RoleError:
        return None
    terms = extended_library(roles, data.state_names)
    ts = term_set(terms, data.state_names + data.input_names)
    rows_a, rows_b = [], []
    for tr in data:
        z = np.concatenate([tr.x, tr.u], axis=1)
        theta = ts.evaluate(z)
        full = ref.plant.full_state(tr.x, tr.u) if hasattr(ref, "plant") else tr.x
        f_ref = ref.vector_field(full, tr.u)[:, :tr.x.shape[1]]
        dt = np.diff(tr.t)[:, None]
        cum_t = np.concatenate([np.zeros((1, theta.shape[1])), np.cumsum(0.5 * (theta[1:] + theta[:-1]) * dt, 0)])
        cum_f = np.concatenate([np.zeros((1, f_ref.shape[1])), np.cumsum(0.5 * (f_ref[1:] + f_ref[:-1]) * dt, 0)])
        k = np.arange(0, len(tr) - span)
        rows_a.append(cum_t[k + span] - cum_t[k])
        rows_b.append(tr.x[k + span] - tr.x[k] - (cum_f[k + span] - cum_f[k]))
    a, b = np.concatenate(rows_a), np.concatenate(rows_b)
    # only the states that disagree get residual terms; each with a threshold relative to its own
    # largest (column-normalised) ridge coefficient, since residuals differ in scale by orders
    flagged = {name for w in flow.windows for name in w["states"][:4]} if getattr(flow, "windows", None) else set()
    norms = np.linalg.norm(a, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    coef = np.zeros((len(terms), b.shape[1]))
    for j, name in enumerate(data.state_names):
        if flagged and name not in flagged:
            continue
        ridge = np.linalg.lstsq(np.vstack([a / norms, 1e-6 * np.eye(a.shape[1])]),
                                np.concatenate([b[:, j], np.zeros(a.shape[1])]), rcond=None)[0]
        if not np.any(ridge):
            continue
        opt = ps.STLSQ(threshold=threshold * float(np.max(np.abs(ridge))), alpha=1e-6, max_iter=30)
        opt.fit(a / norms, b[:, j:j + 1])
        coef[:, j] = np.asarray(opt.coef_)[0] / norms
    keep = np.flatnonzero(np.any(coef != 0, axis=1))
    if keep.size == 0:
        return None
    residual = ExplicitModel(data.state_names, data.input_names, [terms[k] for k in keep], coef[keep],
                             {"method": "pysindy STLSQ over Θ_ext, integral form", "threshold": threshold})
    augmented = ref.with_residual(residual)
    before = gap_percent(data, flow.corrected(flow._simulate(ref)))
    after = gap_percent(data, flow.corrected(flow._simulate(augmented)))
    if not np.isfinite(after) or after >= before:
        return None
    listed = [{"state": data.state_names[j], "term": terms[k], "coefficient": float(coef[k, j])}
              for k in keep for j in range(coef.shape[1]) if coef[k, j] != 0]
    return {"reference": augmented, "terms": listed,
            "evidence": {"gap_before": before, "gap_after": after, "n_terms": len(listed),
                         "method": residual.metadata["method"]}}
