"""Coefficient refinement on trajectories (multiple shooting) and small-signal responses.

Given a fixed structure (terms and a support mask), the coefficients are fitted
by Levenberg-Marquardt-type least squares (scipy ``least_squares``, trust
region) with Jacobians from torch forward-mode autodiff (``torch.func.jacfwd``):

- trajectory residuals: windows of ``window`` samples start at measured states
  and are integrated with RK4 (``substeps`` per sample); residuals are
  noise-weighted per state;
- small-signal (Jacobian-consistency) residuals: around the pre-step steady state
  of each small-signal record, the model's linearisation (A = ∂f/∂x, B = ∂f/∂u)
  must reproduce the measured deviation Δx(t) over the whole record (exact
  zero-order-hold discretisation by matrix exponential). This is what pins the
  slow droop/power modes that 40 ms trajectories cannot.

The fit also returns the Gauss-Newton Hessian of its cost (window starts profiled out), from
which :func:`backward_elimination` derives sparser models without integrating again.
Hand-written because no library fits ODE coefficients through an integrator
with these two residual kinds; scipy provides the solver, torch the derivatives.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.optimize
import scipy.sparse

from ..data import Dataset
from ..data.dataset import steady_start_length
from ..model.expressions import TermSet
from .derivatives import trajectory_windows


@dataclasses.dataclass
class FitResult:
    coefficients: np.ndarray
    cost: float
    nfev: int
    seconds: float
    abandoned: bool = False  # stopped early because ``keep_going`` said the fit was not improving
    # Gauss-Newton Hessian of the cost in the support coefficients (``support``: flat indices into the
    # coefficient matrix), the window start states profiled out; for pruning (:func:`backward_elimination`)
    hessian: np.ndarray | None = None
    support: np.ndarray | None = None


class _Abandon(Exception):
    def __init__(self, params):
        super().__init__("refinement abandoned")
        self.params = params


def _steady_start(tr, min_samples=5):
    end = steady_start_length(tr)
    return end if min_samples <= end < len(tr) else 0


class TrajectoryFitter:
    """Least-squares refinement of the coefficients of ``terms`` on a support.

    Parameters
    ----------
    terms : TermSet
        Over ``state_names + input_names``.
    n_states : int
    window : int
        Samples per shooting window.
    substeps : int
        RK4 steps per sample.
    weights : ndarray, shape (n_states,)
        Residual weight per state (1/noise std).
    exact_range : (int, int)
        Dense Jacobian sizes (rows × parameters) whose trust-region steps are solved exactly (SVD);
        others use LSMR.
    """

    # Below ~2e6 entries LSMR is cheap and its regularised inexact steps converge at least as fast
    # on collinear coefficients; above it LSMR needed thousands of products per step (~7 s at the
    # benchmark's 2e7) where the exact step takes well under a second; above 4e7 memory decides.
    exact_range = (2_000_000, 40_000_000)

    def __init__(self, terms: TermSet, n_states: int, dt: float, window: int = 50, substeps: int = 2,
                 weights=None, max_windows: int | None = None):
        self.terms = terms
        self.n_states = n_states
        self.dt = dt
        self.window = window
        self.substeps = substeps
        self.weights = np.ones(n_states) if weights is None else np.asarray(weights, dtype=float)
        self.max_windows = max_windows

    def fit(self, coef0: np.ndarray, mask: np.ndarray, train: Dataset, smallsignal: Dataset | None = None,
            lambda_jac: float = 1.0, max_nfev: int = 20, ss_stride: int = 5,
            on_evaluation=None, keep_going=None, fit_starts_first: bool = False) -> FitResult:
        """Refine ``coef0`` on the entries where ``mask`` is true.

        Parameters
        ----------
        train : Dataset
            Trajectories for the multiple-shooting residuals.
        smallsignal : Dataset, optional
            Records that start in steady state and then see a small input step.
        lambda_jac : float
            Weight of the small-signal residuals (0 switches them off).
        fit_starts_first : bool
            First fit the window start states alone (coefficients fixed; a cheap, sparse problem).
            On noisy data a start at the measured sample excites the fast modes for the whole
            window; the joint fit then begins where the windows already follow the model.
        keep_going : callable, optional
            ``keep_going(coefficients) -> bool``, asked at every accepted point (Jacobian
            evaluation) after the start; False stops the fit there (``FitResult.abandoned``). The
            multiple-shooting cost always decreases, but on noisy data the free-run error of the
            model can grow meanwhile: this lets a caller stop paying for such a fit.
        """
        import torch
        from torch.func import jacfwd

        torch.set_default_dtype(torch.float64)
        n = self.n_states
        xw, uw = trajectory_windows(train, self.window, max_windows=self.max_windows)
        X = torch.tensor(xw)
        U = torch.tensor(uw)
        w = torch.tensor(self.weights)
        idx = np.flatnonzero(mask.ravel())
        idx_t = torch.tensor(idx)
        scale = np.abs(coef0.ravel()[idx])
        scale = np.where(scale > 0, scale, 1.0) + 1e-3 * np.abs(coef0).max()
        scale_t = torch.tensor(scale)
        h = self.dt / self.substeps
        terms = self.terms

        ss = []
        if smallsignal is not None and lambda_jac > 0:
            for tr in smallsignal:
                k0 = _steady_start(tr)
                if k0 == 0:
                    continue
                x_eq = tr.x[:k0].mean(axis=0)
                u_eq = tr.u[0]
                dx = tr.x[k0 - 1::ss_stride] - x_eq
                du = tr.u[k0 - 1::ss_stride] - u_eq
                z = np.concatenate([x_eq, u_eq])
                grad = terms.gradient(z)  # (n_terms, n_signals)
                # the linearisation itself is only good to ~1 % of the deviation for 1 % steps
                w_ss = 1.0 / np.sqrt((1.0 / self.weights) ** 2 + (0.01 * dx.std(axis=0)) ** 2 + 1e-30)
                ss.append((torch.tensor(grad), torch.tensor(dx), torch.tensor(du), torch.tensor(w_ss)))
        ss_dt = self.dt * ss_stride
        sqrt_lj = float(np.sqrt(lambda_jac))

        def coefficients(theta):
            flat = torch.zeros(coef0.size, dtype=theta.dtype)
            flat = flat.index_put((idx_t,), theta * scale_t)
            return flat.reshape(coef0.shape)

        n_win = X.shape[0]
        x_scale = torch.tensor(1.0 / self.weights)

        def trajectory_residuals(theta, x_start):
            """Residuals of all windows; the window start states are parameters too
            (full multiple shooting: noisy measured starts would bias the coefficients)."""
            c = coefficients(theta)
            x = x_start
            out = [((x - X[:, 0]) * w).reshape(-1)]
            for k in range(self.window):
                u = U[:, k]
                for _ in range(self.substeps):
                    f = lambda y: terms.evaluate_torch(torch.cat([y, u], dim=-1)) @ c  # noqa: E731
                    k1 = f(x)
                    k2 = f(x + 0.5 * h * k1)
                    k3 = f(x + 0.5 * h * k2)
                    k4 = f(x + h * k3)
                    x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
                out.append(((x - X[:, k + 1]) * w).reshape(-1))
            return torch.stack(out).reshape(-1) / np.sqrt(len(out))

        def smallsignal_residuals(theta):
            c = coefficients(theta)
            res = []
            for grad, dx, du, w_ss in ss:
                jac = c.T @ grad  # (n_states, n_signals)
                m = torch.cat([torch.cat([jac[:, :n], jac[:, n:]], dim=1),
                               torch.zeros((du.shape[1], n + du.shape[1]), dtype=c.dtype)], dim=0)
                disc = torch.linalg.matrix_exp(m * ss_dt)
                ad, bd = disc[:n, :n], disc[:n, n:]
                # the record is in steady state before the step: a start at the first (noisy)
                # deviation sample would ring the fast modes through the whole record
                y = torch.zeros_like(dx[0])
                preds = [y]
                for k in range(dx.shape[0] - 1):
                    y = ad @ y + bd @ du[k]
                    preds.append(y)
                pred = torch.stack(preds)
                res.append(sqrt_lj * ((pred - dx) * w_ss).reshape(-1) / np.sqrt(dx.shape[0]))
            return torch.cat(res) if res else torch.zeros(0)

        n_c = idx.size
        n_x = n_win * n
        x0_meas = X[:, 0]

        def split(params):
            theta = params[:n_c]
            x_start = x0_meas + params[n_c:].reshape(n_win, n) * x_scale
            return theta, x_start

        def all_residuals(params):
            theta, x_start = split(params)
            return torch.cat([trajectory_residuals(theta, x_start), smallsignal_residuals(theta)])

        jac_theta = jacfwd(lambda th, xs: torch.cat([trajectory_residuals(th, xs), smallsignal_residuals(th)]))
        started = time.monotonic()

        calls = [0]

        def residual_vector(params):
            with torch.no_grad():
                r = all_residuals(torch.tensor(params)).numpy()
            # a trial step that makes a window blow up is just a bad step (large, finite residuals)
            return np.clip(np.where(np.isfinite(r), r, 1e6), -1e6, 1e6)

        def fun(params):
            r = residual_vector(params)
            calls[0] += 1
            if on_evaluation is not None:
                on_evaluation(calls[0], float(0.5 * r @ r))
            return r

        jac_calls = [0]

        def start_jacobian(theta, x_start, n_rows, offset):
            # windows are independent: one forward tangent per state component covers all windows,
            # the n tangents in one batched (vmap) pass
            directions = torch.zeros((n,) + tuple(x_start.shape), dtype=x_start.dtype)
            directions[torch.arange(n), :, torch.arange(n)] = x_scale[:, None]
            tangents = torch.func.vmap(lambda d: torch.func.jvp(lambda xs: trajectory_residuals(theta, xs),
                                                                (x_start,), (d,))[1])(directions)
            return _start_state_block(tangents.numpy(), n_win, n_rows, offset)

        def jac(params):
            jac_calls[0] += 1
            if keep_going is not None and jac_calls[0] > 1:
                if not keep_going(to_coefficients(params)):
                    raise _Abandon(params)
            theta, x_start = split(torch.tensor(params))
            dense = jac_theta(theta, x_start).numpy()  # (n_res, n_c)
            sparse = start_jacobian(theta, x_start, dense.shape[0], n_c)
            dense_full = scipy.sparse.csr_matrix(np.hstack([np.where(np.isfinite(dense), dense, 0.0),
                                                            np.zeros((dense.shape[0], n_x))]))
            full = dense_full + sparse
            return full.toarray() if exact else full

        def to_coefficients(params):
            out = np.zeros(coef0.size)
            out[idx] = np.asarray(params)[:n_c] * scale
            return out.reshape(coef0.shape)

        theta0 = np.concatenate([coef0.ravel()[idx] / scale, np.zeros(n_x)])
        with torch.no_grad():
            n_rows = int(all_residuals(torch.tensor(theta0)).numel())
        if fit_starts_first:
            # the start states alone, coefficients fixed: independent windows, a sparse, cheap problem
            fixed = theta0[:n_c]
            theta0[n_c:] = scipy.optimize.least_squares(
                lambda p: residual_vector(np.concatenate([fixed, p])), theta0[n_c:],
                jac=lambda p: start_jacobian(*split(torch.tensor(np.concatenate([fixed, p]))), n_rows, 0),
                method="trf", tr_solver="lsmr", max_nfev=10, x_scale="jac").x
        exact = self.exact_range[0] <= n_rows * (n_c + n_x) <= self.exact_range[1]
        try:
            result = scipy.optimize.least_squares(fun, theta0, jac=jac, method="trf", x_scale="jac",
                                                  max_nfev=max_nfev, tr_solver="exact" if exact else "lsmr")
        except _Abandon as stop:
            r = residual_vector(stop.params)
            return FitResult(to_coefficients(stop.params), float(0.5 * r @ r), calls[0], time.monotonic() - started,
                             abandoned=True)
        coef = to_coefficients(result.x).ravel()
        hessian = _profiled_hessian(result.jac, n_c) / np.outer(scale, scale)
        return FitResult(coef.reshape(coef0.shape), float(result.cost), int(result.nfev),
                         time.monotonic() - started, hessian=hessian, support=idx)


def _start_state_block(tangents: np.ndarray, n_win: int, n_rows: int, offset: int) -> "scipy.sparse.csr_matrix":
    """The sparse Jacobian block of the window start states from the ``n`` batched tangents
    (tangent k: every window's start component k moved by its scale), in columns ``offset`` on.

    Residual layout (steps, windows, states): entry (step, win, s) depends on the starts of
    window ``win`` only. Rows past the trajectory residuals (small-signal ones) stay empty.
    """
    n = tangents.shape[0]
    steps = tangents[0].size // (n_win * n)
    r_index = np.arange(steps * n_win * n).reshape(steps, n_win, n)
    rows = np.concatenate([r_index.ravel()] * n)
    cols = np.concatenate([(offset + np.arange(n_win)[None, :, None] * n + k + 0 * r_index).ravel()
                           for k in range(n)])
    vals = np.concatenate([np.where(np.isfinite(t), t, 0.0).ravel() for t in tangents])
    return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(n_rows, offset + n_win * n))


def _profiled_hessian(jac, n_c: int) -> np.ndarray:
    """JᵀJ of the first ``n_c`` parameters with the others (window start states) minimised out
    (Schur complement): the curvature of the cost when the starts re-adjust to a coefficient change."""
    if scipy.sparse.issparse(jac):
        # the fit used LSMR (a large problem): keep the start-state block sparse, no dense copy
        jac = jac.tocsc()
        jc, jx = jac[:, :n_c].toarray(), jac[:, n_c:]
        h_xc, h_xx = np.asarray(jx.T @ jc), (jx.T @ jx).toarray()
    else:
        jc, jx = jac[:, :n_c], jac[:, n_c:]
        h_xc, h_xx = jx.T @ jc, jx.T @ jx
    h_cc = jc.T @ jc
    if h_xx.size == 0:
        return h_cc
    return h_cc - h_xc.T @ np.linalg.lstsq(h_xx, h_xc, rcond=1e-12)[0]


def backward_elimination(coefficients: np.ndarray, hessian: np.ndarray, support: np.ndarray,
                         budgets) -> list[tuple[float, np.ndarray]]:
    """Sparser models from a fitted one by greedy backward elimination on its quadratic cost model.

    Repeatedly drops the support coefficient whose removal (the others re-fitted through the
    Hessian, no new integration) raises the cost least, while the total predicted rise stays
    within each budget. Near-collinear groups (common in these libraries) lose their spurious
    members one at a time, which a one-shot |t| threshold cannot do.

    Parameters
    ----------
    coefficients : ndarray
        The fitted coefficient matrix (a cost minimum).
    hessian : ndarray, shape (n_support, n_support)
        Gauss-Newton Hessian of the cost in the support coefficients (:attr:`FitResult.hessian`).
    support : ndarray of int
        Flat indices of the support coefficients.
    budgets : sequence of float
        Allowed predicted cost rises (absolute, in cost units).

    Returns
    -------
    list of (predicted rise, coefficients)
        One model per budget (the sparsest that stays within it), in the order of ``budgets``.
    """
    # in Jacobi-scaled units (coefficients span many decades); the elimination is invariant to it
    d = np.sqrt(np.clip(np.diag(hessian), 1e-300, None))
    beta = coefficients.ravel()[support].astype(float) * d
    h_inv = np.linalg.pinv(hessian / np.outer(d, d), rcond=1e-12, hermitian=True)
    alive = np.ones(beta.size, dtype=bool)
    rise = 0.0
    path = [(0.0, beta.copy(), alive.copy())]
    while alive.sum() > 1:
        live = np.flatnonzero(alive)
        diag = np.diag(h_inv)[live]
        with np.errstate(over="ignore", divide="ignore"):  # a pinned coefficient: infinite cost, never dropped
            cost_up = np.where(diag > 0, 0.5 * beta[live] ** 2 / np.maximum(diag, 1e-300), np.inf)
        k = int(np.argmin(cost_up))
        j = live[k]
        if not np.isfinite(cost_up[k]):
            break
        rise += float(cost_up[k])
        # drop j: the constrained minimum of the quadratic model, and H⁻¹ restricted to the rest
        beta = beta - h_inv[:, j] * (beta[j] / h_inv[j, j])
        h_inv = h_inv - np.outer(h_inv[:, j], h_inv[j, :]) / h_inv[j, j]
        beta[j] = 0.0
        h_inv[j, :] = 0.0
        h_inv[:, j] = 0.0
        alive[j] = False
        path.append((rise, beta.copy(), alive.copy()))
    out = []
    for budget in budgets:
        best = max((p for p in path if p[0] <= budget), key=lambda p: (-p[2].sum(), -p[0]))
        flat = np.zeros(coefficients.size)
        flat[support] = np.where(best[2], best[1] / d, 0.0)
        out.append((best[0], flat.reshape(coefficients.shape)))
    return out
