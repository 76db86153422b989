"""Coefficient refinement on trajectories (multiple shooting) and small-signal responses.

Given a fixed structure (terms and a support mask), the coefficients are fitted by
Levenberg-Marquardt least squares over these residual kinds:

- trajectory residuals: windows of ``window`` samples start at fitted start states
  (full multiple shooting) and are integrated with RK4 (``substeps`` per sample);
  residuals are noise-weighted per state;
- small-signal (Jacobian-consistency) residuals: around the pre-step steady state
  of each small-signal record, the model's linearisation (A = ∂f/∂x, B = ∂f/∂u)
  must reproduce the measured deviation Δx(t) over the whole record (exact
  zero-order-hold discretisation by matrix exponential). This is what pins the
  slow droop/power modes that 40 ms trajectories cannot;
- optionally a stability prior: at the rest states of the small-signal records (or of any
  records given), eigenvalues of the model's Jacobian right of ``-margin`` cost
  ``(Re λ + margin)²`` (first-order eigenvalue perturbation for their slopes);
- optionally an equilibrium prior: at the same rest states the model's f(x, u), in units of what
  the noise left in the rest mean makes of it, costs ``(f / σ)²`` (a record that starts at rest
  starts at an equilibrium).

The Gauss-Newton normal equations come from forward sensitivities integrated beside
the states, with the window start states eliminated per window (Schur complement):
every step is exact, at any problem size. The fit also returns the Gauss-Newton
Hessian of its cost (window starts profiled out), from which
:func:`backward_elimination` derives sparser models without integrating again.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import scipy.linalg

from ..data import Dataset
from ..data.dataset import steady_start_mean
from ..model.expressions import TermSet
from .derivatives import rest_window_starts, trajectory_windows

# |uᴴv| of unit left/right eigenvectors below which the stability prior treats an eigenvalue as
# defective (no derivative): its first-order perturbation 1/|uᴴv| would exceed 1e6
DEFECTIVE_OVERLAP = 1e-6

# the most parts the refinement shares its shooting windows out in (TrajectoryFitter's threads): each
# part launches many small torch operations and holds the GIL between them, so more parts contend
# for it. Measured with bench/threads_bench.py (40 dB protocol data, windows of 25, seconds per cost
# evaluation): 2 cores 0.76 / 0.58 / 0.69 / 0.84 s in 1 / 2 / 3 / 4 parts; 16 cores (a lent H200
# machine) 0.85 / 0.76 / 0.82 / 1.33 / 2.28 / 2.89 / 6.07 s in 1 / 2 / 3 / 4 / 6 / 8 / 16 parts. There,
# torch's default of a part per core made a 40 dB identification take over 420 s (71 s in 2 parts).
# Stop 83 (scratch, 2 cores, windows of 25, 219 coefficients, a tangent pass with torch and the BLAS on
# one thread): 0.59 s in 1 part, 0.48 s in 2 threads, 0.34-0.48 s (mean 0.41) in 2 spawned processes
# with a half each, their Hessians to the bit the threads' sum. A process pool would save ~15 % of the
# tangent passes (~5 % of a fit) and add its start-up, data shipping and failure modes: not taken.
SHOOTING_PARTS_MAX = 2


def blas_threads(limit: int | None, user_api: str | None = None):
    """A context with at most ``limit`` threads in the BLAS pools (threadpoolctl; without it, or
    with ``limit`` None, the pools keep their size); ``user_api`` "blas" leaves the OpenMP pools
    alone (threadpoolctl sets those for the calling thread only)."""
    import contextlib

    if not limit:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=limit, user_api=user_api)


def _gram_adder(single: bool = False):
    """``add(a, c)``: c += aᵀ·a in c's upper triangle, a (k, n) C-ordered, c (n, n) F-ordered,
    both float64 (``single``: both float32): BLAS dsyrk (ssyrk; half the work of a product).

    Called through ctypes on the function pointer scipy exports for Cython
    (``scipy.linalg.cython_blas``), because ctypes releases the GIL for the call and the f2py
    wrapper ``scipy.linalg.blas.dsyrk`` does not: the refinement's window parts run on threads,
    and measured with two threads the wrapper's products ran one after the other (0.54 s for two
    against 0.58 s alone), these side by side (0.24 s against 0.46 s). Same BLAS, same results;
    the wrapper is the fallback where the pointer cannot be had.
    """
    import ctypes

    try:
        from scipy.linalg import cython_blas

        capsule = cython_blas.__pyx_capi__["ssyrk" if single else "dsyrk"]
        get_name = ctypes.PYFUNCTYPE(ctypes.c_char_p, ctypes.py_object)(("PyCapsule_GetName", ctypes.pythonapi))
        get_pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
            ("PyCapsule_GetPointer", ctypes.pythonapi))
        scalar = ctypes.c_float if single else ctypes.c_double
        int_p, scalar_p = ctypes.POINTER(ctypes.c_int), ctypes.POINTER(scalar)
        syrk = ctypes.CFUNCTYPE(None, ctypes.c_char_p, ctypes.c_char_p, int_p, int_p, scalar_p, ctypes.c_void_p,
                                int_p, scalar_p, ctypes.c_void_p, int_p)(get_pointer(capsule, get_name(capsule)))
    except (ImportError, AttributeError, KeyError, TypeError, ValueError, OSError):
        from scipy.linalg.blas import dsyrk, ssyrk

        wrapped = ssyrk if single else dsyrk

        def add(a, c):
            wrapped(1.0, a.T, beta=1.0, c=c, trans=0, lower=0, overwrite_c=1)

        return add

    one = scalar(1.0)
    dtype = np.float32 if single else np.float64

    def add(a, c):
        assert a.flags.c_contiguous and c.flags.f_contiguous and a.dtype == c.dtype == dtype
        k, n = a.shape
        if k == 0 or n == 0:
            return
        # column-major: aᵀ is n × k with leading dimension n, so c += aᵀ·(aᵀ)ᵀ is "N"
        size, depth = ctypes.c_int(n), ctypes.c_int(k)
        syrk(b"U", b"N", ctypes.byref(size), ctypes.byref(depth), ctypes.byref(one), a.ctypes.data,
              ctypes.byref(size), ctypes.byref(one), c.ctypes.data, ctypes.byref(size))

    return add


_add_gram = _gram_adder()
_add_gram_single = _gram_adder(single=True)


# the Levenberg-Marquardt damping a fit starts from (relative to the normal equations' diagonal): a
# light start and a fall of up to 10x per good step (Nielsen: 3x); measured at 60 dB, 1e-3 with 3x
# reached cost 425 in 10 evaluations, this 397 (scipy's trust region before: 398); at 40 dB on the
# exact structure it made the difference between stalling and converging
START_DAMPING = 1e-5


@dataclasses.dataclass
class FitResult:
    coefficients: np.ndarray
    cost: float
    nfev: int
    seconds: float
    abandoned: bool = False  # stopped early because ``keep_going`` said the fit was not improving
    # steps taken: each costs a Gauss-Newton pass (the normal equations, ~10x a cost evaluation),
    # a rejected trial step only its cost evaluation
    accepted: int = 0
    # Gauss-Newton Hessian of the cost in the support coefficients (``support``: flat indices into the
    # coefficient matrix), the window start states profiled out; for pruning (:func:`backward_elimination`)
    hessian: np.ndarray | None = None
    support: np.ndarray | None = None
    window: int | None = None  # samples per shooting window of the fit
    windows: int | None = None  # shooting windows of the fit
    # :attr:`hessian` without the priors' curvature (stability, equilibrium, ridge): what the data pin
    data_hessian: np.ndarray | None = None

    def covariance(self) -> np.ndarray | None:
        """Covariance of the support coefficients for the measurement noise alone (not the model's
        own error, nor the priors): each residual is a sample's misfit in noise units over
        sqrt(window + 1), so the data's information is (window + 1) times :attr:`data_hessian`.
        Measured (stop 35, the ten 40 dB benchmark recordings' chosen models): with the priors'
        curvature counted as data (the stability prior holds the slow modes), the plant's largest
        real part lay within two standard deviations of the model's at 13 of 68 grid points. None
        without a Hessian."""
        if self.data_hessian is None or self.window is None:
            return None
        return np.linalg.pinv(self.data_hessian, rcond=1e-12, hermitian=True) / (self.window + 1)


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
    max_windows : int, optional
        Use at most this many windows, evenly spread (:func:`~.derivatives.trajectory_windows`).
    threads : int
        The windows are integrated in this many parts side by side, one thread each (torch and
        the BLAS on one thread per part while the fit runs).
    single_precision : bool
        Carry the coefficient tangents (the Gauss-Newton Jacobian's coefficient columns: its
        forcing, recursion, Hessian and coupling to the start states) in float32. The states,
        residuals and every cost the Levenberg-Marquardt loop compares stay float64, so a step is
        taken only where it lowers the exact cost; the steps themselves come from a Jacobian good
        to ~1e-7 instead of ~1e-16. The normal equations at the point the fit ends are computed
        again in float64: the Hessian it returns (:attr:`FitResult.hessian`, which prunes and
        gives the covariance) has a condition number of ~1e10, beyond float32's reach.
    held_levels : bool
        Where the training records' inputs were held at their stretch means (noisy measured inputs:
        their metadata's ``inputs_denoised``), fit each held level's error beside the coefficients
        (errors in variables, prior N(0, σ²/n); :func:`held_window_levels`).
    rest_starts : float
        Hold the start states of the windows inside a record's steady start (the plant at rest) at
        the rest's mean state: a prior of precision ``rest_starts`` times the rest's samples, in the
        noise's units and the windows' scale (:func:`~.derivatives.rest_window_starts`); 0: free
        starts there too.
    """

    def __init__(self, terms: TermSet, n_states: int, dt: float, window: int = 50, substeps: int = 2,
                 weights=None, max_windows: int | None = None, threads: int = 1, single_precision: bool = False,
                 held_levels: bool = False, rest_starts: float = 0.0):
        self.terms = terms
        self.n_states = n_states
        self.dt = dt
        self.window = window
        self.substeps = substeps
        self.weights = np.ones(n_states) if weights is None else np.asarray(weights, dtype=float)
        self.max_windows = max_windows
        self.threads = max(1, int(threads))
        self.single_precision = bool(single_precision)
        self.held_levels = bool(held_levels)
        self.rest_starts = float(rest_starts)

    def fit(self, coef0: np.ndarray, mask: np.ndarray, train: Dataset, smallsignal: Dataset | None = None,
            lambda_jac: float = 1.0, max_nfev: int = 20, ss_stride: int = 5,
            on_evaluation=None, keep_going=None, fit_starts_first: bool = False,
            lambda_stab: float = 0.0, stability_margin: float = 0.1, stability_records=None,
            lambda_eq: float = 0.0, ftol: float = 1e-8, equilibrium_space: str = "rates",
            lambda_ridge: float = 0.0, damping: float = START_DAMPING) -> FitResult:
        """Refine ``coef0`` on the entries where ``mask`` is true.

        Parameters
        ----------
        train : Dataset
            Trajectories for the multiple-shooting residuals.
        smallsignal : Dataset, optional
            Records that start in steady state and then see a small input step.
        lambda_jac : float
            Weight of the small-signal residuals (0 switches them off).
        lambda_stab : float
            Weight of the stability prior (0 switches it off): at the pre-step steady state of each
            small-signal record, every eigenvalue of the model's Jacobian with a real part above
            ``-stability_margin`` (1/s) adds a residual ``sqrt(lambda_stab) * (Re λ + margin)``.
        stability_records : iterable of trajectories, optional
            The records whose rest states (steady starts, grouped by input) anchor the stability
            and equilibrium priors instead of the small-signal records.
        lambda_eq : float
            Weight of the equilibrium prior (0 switches it off): at each anchoring rest state x_r,
            each equation's ``sqrt(lambda_eq) * f_j(x_r, u_r) / σ_j``, σ_j the spread of f_j that
            the noise left in the rest mean makes (the start model's Jacobian, the residual weights'
            noise levels, the number of samples averaged).
        equilibrium_space : {"rates", "states"}
            Where the equilibrium prior measures the misfit: "rates" as above; "states" the distance
            from each rest state to the model's equilibrium next to it (one Newton step,
            ``J(x_r)⁻¹ f(x_r)``, the current model's Jacobian) in units of the noise left in the
            rest mean, ``sqrt(lambda_eq) * (J⁻¹f)_k * sqrt(samples) / noise_k``. Multiple shooting
            fits every window's start state, so a slow state's equilibrium can sit far from where
            the records rested at no trajectory cost; in rates, a small slow-row rate is a large
            state offset (J⁻¹ is large along the slow modes), which this unit sees.
        lambda_ridge : float
            Weight of the ridge prior (0 switches it off): each coefficient's share of its equation,
            ``sqrt(lambda_ridge) * c_ij * rms(θ_i) / rms(f_j)`` (the term's and the start model's
            equation's root mean square over the windows' samples). It pins the directions the data
            hardly see — pairs of nearly collinear terms that cancel with large coefficients (at
            40 dB, ``delta`` and ``sin(delta)`` at ∓1.6e4 in a power-filter row) — and hardly moves
            the coefficients the data determine.
        max_nfev : int
            Cost evaluations (the start and every trial step).
        damping : float
            The Levenberg-Marquardt damping to start from (relative to the normal equations'
            diagonal; > 0).
        ftol : float
            The fit ends when an accepted step lowers the cost by at most this fraction.
        on_evaluation : callable, optional
            ``on_evaluation(nfev, cost)`` after every cost evaluation.
        fit_starts_first : bool
            First fit the window start states alone (coefficients fixed; independent 13-dimensional
            problems). On noisy data a start at the measured sample excites the fast modes for the
            whole window; the joint fit then begins where the windows already follow the model.
        keep_going : callable, optional
            ``keep_going(coefficients) -> bool``, asked at every accepted point after the start;
            False stops the fit there (``FitResult.abandoned``). The multiple-shooting cost always
            decreases, but on noisy data the free-run error of the model can grow meanwhile: this
            lets a caller stop paying for such a fit.
        """
        import torch

        threads = torch.get_num_threads()
        if self.threads > 1:
            # a part per thread: torch inside each on one thread, and the BLAS (the Hessian's syrk)
            # too; OpenBLAS threads spinning beside torch's doubled the time (measured)
            torch.set_num_threads(1)
        problem = None
        try:
            with blas_threads(1 if self.threads > 1 else None):
                problem = _ShootingProblem(self, coef0, mask, train, smallsignal, lambda_jac, ss_stride,
                                           lambda_stab, stability_margin, stability_records, lambda_eq,
                                           equilibrium_space, lambda_ridge)
                return self._solve(torch, problem, coef0, max_nfev, on_evaluation, keep_going, fit_starts_first,
                                   ftol, damping)
        finally:
            if problem is not None:
                problem.close()
            torch.set_num_threads(threads)

    def _solve(self, torch, problem, coef0, max_nfev, on_evaluation, keep_going, fit_starts_first,
               ftol, damping) -> FitResult:
        started = time.monotonic()
        theta = problem.parameters(coef0)
        z = torch.zeros((problem.n_windows, self.n_states))
        if fit_starts_first:
            z = problem.fit_starts(theta, z)
        nfev = accepted = 0

        def evaluate(th, zz):
            nonlocal nfev
            nfev += 1
            value = problem.cost(th, zz)
            if on_evaluation is not None:
                on_evaluation(nfev, value)
            return value

        cost = evaluate(theta, z)
        normal = problem.normal_equations(theta, z)
        mu, nu = damping, 2.0
        # windows that blow up can leave the normal equations without finite values: the fit then
        # ends where it is (a step from there is undefined), without a Hessian for pruning
        while nfev < max_nfev and _finite(normal):
            step_theta, step_z, predicted = problem.damped_step(normal, mu)
            trial = evaluate(theta + step_theta, z + step_z)
            if trial < cost:
                # Nielsen's update of the damping from the gain ratio (floor 0.1, see START_DAMPING)
                gain = (cost - trial) / max(predicted, 1e-300)
                mu *= max(0.1, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3)
                nu = 2.0
                theta, z, fall, cost = theta + step_theta, z + step_z, cost - trial, trial
                accepted += 1
                if keep_going is not None and not keep_going(problem.coefficients(theta)):
                    return FitResult(problem.coefficients(theta), cost, nfev, time.monotonic() - started,
                                     abandoned=True, accepted=accepted)
                normal = problem.normal_equations(theta, z)
                if fall <= ftol * cost:
                    break
            else:
                mu *= nu
                nu *= 2.0
                if mu > 1e10:
                    break
        if problem.single_precision and _finite(normal):
            # the Hessian returned prunes and gives the covariance: float64, at the point the fit ends
            problem.single_precision = False
            normal = problem.normal_equations(theta, z)
        hessian = problem.profiled_hessian(normal) if _finite(normal) else None
        # the priors' curvature is a plain sum in the normal equations: the data's is the rest
        data = hessian - problem.prior_hessian(normal) if hessian is not None else None
        return FitResult(problem.coefficients(theta), cost, nfev, time.monotonic() - started, accepted=accepted,
                         hessian=hessian if hessian is not None and np.all(np.isfinite(hessian)) else None,
                         support=problem.idx, window=problem.window, windows=problem.n_windows,
                         data_hessian=data if data is not None and np.all(np.isfinite(data)) else None)


def _expm_row_derivatives(m, rows, vectors, tau: float):
    """exp(M·τ) and its derivatives in the directions that move one row of M each.

    Parameters
    ----------
    m : tensor, shape (R, S, S)
        A batch of matrices.
    rows : tensor of int, shape (C,)
        Direction c moves row ``rows[c]`` of M ...
    vectors : tensor, shape (R, C, S)
        ... by ``vectors[:, c]`` (so dM_c = e_row · vectorᵀ).
    tau : float

    Returns
    -------
    exp(M·τ), shape (R, S, S), and the derivatives L[r, a, c, b] = ∂exp(M·τ)[a, b] / ∂(direction c),
    shape (R, S, C, S).

    Why written here: torch's matrix_exp gives the derivatives only as blocks of exp([[M, dM],
    [0, M]]·τ), one 2S × 2S exponential per direction (~0.14 s of every Gauss-Newton pass at the
    benchmark's 4 records × 300 coefficients), and scipy's expm_frechet takes one direction per
    call. Here the Taylor series of degree 18 with scaling and squaring (‖M·τ‖₁ ≤ 1 after
    scaling; truncation below 1e-17) and its derivative run for all directions at once: each
    Horner and squaring step is one matrix product against the directions side by side, and a
    direction's own term E·Q is a rank-one update (E moves one row).
    """
    import torch

    n_batch, size, _ = m.shape
    n_dir = rows.numel()
    x = m * tau
    norm = float(x.abs().sum(dim=1).max()) if x.numel() else 0.0
    squarings = min(64, max(0, math.ceil(math.log2(norm)))) if math.isfinite(norm) and norm > 1.0 else 0
    x = x / 2.0 ** squarings
    e = vectors * (tau / 2.0 ** squarings)
    cols = torch.arange(n_dir)
    eye = torch.eye(size, dtype=m.dtype)
    degree = 18
    # Horner: Q_degree = I + X/degree, Q_i = I + X·Q_(i+1)/i, exp(X) ≈ Q_1; dQ_i = (E·Q_(i+1) + X·dQ_(i+1))/i
    q = eye + x / degree
    dq = torch.zeros((n_batch, size, n_dir, size), dtype=m.dtype)
    dq[:, rows, cols] = e / degree
    for i in range(degree - 1, 0, -1):
        step = torch.bmm(x, dq.view(n_batch, size, n_dir * size)).view(n_batch, size, n_dir, size)
        step[:, rows, cols] += torch.bmm(e, q)
        dq = step.div_(i)
        q = eye + torch.bmm(x, q) / i
    for _ in range(squarings):
        # (T, L) -> (T·T, T·L + L·T)
        dq = (torch.bmm(q, dq.view(n_batch, size, n_dir * size)).view(n_batch, size, n_dir, size)
              + torch.bmm(dq.view(n_batch, size * n_dir, size), q).view(n_batch, size, n_dir, size))
        q = torch.bmm(q, q)
    return q, dq


def _rk4_tangent_map(a1, a2, a3, a4, h, forced: bool = True):
    """One RK4 step of a linear tangent equation S' = A(t)·S + B(t), the four stages' Jacobians
    A_i given, as matrices: the step maps S to P·S + G_1·B_1 + ... + G_4·B_4 (B_i at stage i).

    Returns [P | G_1 | G_2 | G_3 | G_4], shape (batch, n, 5n), or P alone (``forced`` false: B = 0).
    These are the classical RK4 stages applied to the block tangent [S, B_1, ..., B_4] (start
    [I, 0, ...]; stage i adds the identity in B_i's block), written out block by block: stage i
    has only its first i + 1 blocks, and some of those are multiples of A_i, so three products of
    (n × n)·(n × n, 2n, 3n) do it.
    """
    import torch

    n = a1.shape[-1]
    eye = torch.eye(n, dtype=a1.dtype)
    k2_0 = torch.bmm(a2, eye + (0.5 * h) * a1)
    if not forced:
        k3_0 = torch.bmm(a3, eye + (0.5 * h) * k2_0)
        k4_0 = torch.bmm(a4, eye + h * k3_0)
        return eye + (h / 6.0) * (a1 + 2.0 * k2_0 + 2.0 * k3_0 + k4_0)
    k2_1 = (0.5 * h) * a2
    k3 = torch.bmm(a3, torch.cat([eye + (0.5 * h) * k2_0, (0.5 * h) * k2_1], dim=2))  # [K3_0 | K3_1]
    k3_2 = (0.5 * h) * a3
    k4 = torch.bmm(a4, torch.cat([eye + h * k3[..., :n], h * k3[..., n:], h * k3_2], dim=2))  # K4_0..2
    third = (h / 6.0)
    return torch.cat([
        eye + third * (a1 + 2.0 * k2_0 + 2.0 * k3[..., :n] + k4[..., :n]),
        third * (eye + 2.0 * k2_1 + 2.0 * k3[..., n:] + k4[..., n:2 * n]),
        third * (2.0 * eye + 2.0 * k3_2 + k4[..., 2 * n:]),
        third * (2.0 * eye + h * a4),
        (third * eye).expand_as(a4),
    ], dim=2)


def held_input_sigma(dataset: Dataset) -> np.ndarray | None:
    """The noise standard deviation of each input that :func:`~.noise.piecewise_constant_inputs`
    held at its stretch means in ``dataset`` (its metadata's ``inputs_denoised``; 0 for an input
    taken as given), or None where none was held."""
    denoised = dataset.metadata.get("inputs_denoised") if dataset is not None else None
    if not denoised:
        return None
    sigma = np.array([float(denoised.get(name, 0.0)) for name in dataset.input_names])
    return sigma if np.any(sigma > 0) else None


def held_level_counts(records, sigma: np.ndarray) -> list:
    """For each input: how many samples of ``records`` sit at each of its values. A held level's
    count is the samples its mean was taken over, pooled stretches' together
    (:func:`~.noise.piecewise_constant_inputs` gives them one common value); empty for an input
    taken as exact (``sigma`` 0)."""
    out = []
    for j, s in enumerate(sigma):
        if not s > 0:
            out.append({})
            continue
        values, counts = np.unique(np.concatenate([tr.u[:, j] for tr in records]), return_counts=True)
        out.append(dict(zip(values.tolist(), counts.tolist())))
    return out


def held_level_basis(u: np.ndarray, sigma: np.ndarray, samples: np.ndarray, counts: list, min_samples: int = 8):
    """How the errors of a record's held input levels enter its small-signal deviations.

    A held level is the mean of its noisy samples, off by ε ~ N(0, σ²/n) (n from ``counts``,
    :func:`held_level_counts`). The small-signal residuals use Δu = u(t) − u(0), so a stretch's
    error moves Δu by ε where t is in it, and the first stretch's by −ε_0 where t is not. At 40 dB
    the 50 samples before a 0.01 p.u. step of ug hold it to ~1e-3 p.u., ~10 % of the step.

    Parameters
    ----------
    u : ndarray, shape (n_samples, n_inputs)
        The record's inputs, held.
    sigma : ndarray, shape (n_inputs,)
        Noise of each input (0: taken as exact, no level error).
    samples : ndarray of int
        The samples the small-signal residuals use.
    counts : list of dict
        :func:`held_level_counts` of the records the levels were held over.

    Returns
    -------
    basis : ndarray, shape (len(samples), n_inputs, n_levels)
        ∂Δu/∂ε for each held stretch's level error.
    precision : ndarray, shape (n_levels,)
        1 / the prior standard deviation of each, √n / σ.
    """
    columns, precision = [], []
    for j in np.flatnonzero(sigma > 0):
        edges = np.concatenate([[0], np.flatnonzero(np.diff(u[:, j]) != 0) + 1, [len(u)]])
        held = [counts[j].get(float(u[a, j]), 1) >= min_samples for a in edges[:-1]]
        if not held[0]:
            continue  # the reference sample is not on a held stretch: its error is not a level's
        for index, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
            if not held[index]:
                continue  # left as measured (a ramp, an oscillation): no level to be off
            column = np.zeros((len(samples), len(sigma)))
            inside = (samples >= a) & (samples < b)
            column[:, j] = -(~inside).astype(float) if index == 0 else inside
            columns.append(column)
            precision.append(np.sqrt(counts[j][float(u[a, j])]) / sigma[j])
    if not columns:
        return np.zeros((len(samples), len(sigma), 0)), np.zeros(0)
    return np.stack(columns, axis=-1).astype(float), np.array(precision)


def held_level_variance(u: np.ndarray, sigma: np.ndarray, counts: list) -> np.ndarray:
    """The variance of each held input's level at a record's start, σ²/n (n from ``counts``,
    :func:`held_level_counts`; σ² for an input as measured there)."""
    variance = np.zeros(len(sigma))
    for j in np.flatnonzero(sigma > 0):
        variance[j] = sigma[j] ** 2 / counts[j].get(float(u[0, j]), 1)
    return variance


def held_window_levels(u: np.ndarray, sigma: np.ndarray, counts: list, min_samples: int = 8):
    """Which held level each shooting window's input sits on, sample by sample, and each level's
    standard deviation.

    A held level is the mean of its noisy samples, off by ε ~ N(0, σ²/n) (n from ``counts``,
    :func:`held_level_counts`); a level is identified by its input and value, so pooled stretches
    (one common mean) share one error wherever they occur.

    Parameters
    ----------
    u : ndarray, shape (n_windows, window + 1, n_inputs)
        The windows' inputs, held (:func:`~.derivatives.trajectory_windows`).
    sigma : ndarray, shape (n_inputs,)
        Noise of each input (0: taken as exact).
    counts : list of dict
        :func:`held_level_counts` of the records the levels were held over.

    Returns
    -------
    index : ndarray of int, shape (n_windows, window + 1, n_inputs)
        The level of each sample's input (-1: not a held level, taken as exact).
    unit : ndarray, shape (n_levels,)
        σ/√n of each level.
    """
    index = np.full(u.shape, -1, dtype=np.int64)
    unit = []
    for j in np.flatnonzero(sigma > 0):
        values, inverse = np.unique(u[..., j], return_inverse=True)
        level_of = np.full(values.size, -1, dtype=np.int64)  # each distinct value's level, if held
        for v, value in enumerate(values.tolist()):
            count = counts[j].get(value, 1)
            if count >= min_samples:
                level_of[v] = len(unit)
                unit.append(sigma[j] / np.sqrt(count))
        index[..., j] = level_of[inverse.reshape(u.shape[:-1])]
    return index, np.array(unit, dtype=float)


def _stack_offsets(offsets: list, length: int, n_inputs: int):
    """The level-error bases and precisions of records stepping together, padded to the most levels
    (a padded level has no basis and unit precision: it stays at 0)."""
    import torch

    size = max(o[1].numel() for o in offsets if o is not None)
    basis = torch.zeros((len(offsets), length, n_inputs, size))
    precision = torch.ones((len(offsets), size))
    for r, o in enumerate(offsets):
        if o is not None:
            basis[r, :, :, :o[1].numel()] = o[0]
            precision[r, :o[1].numel()] = o[1]
    return basis, precision


def _profile_level_errors(ad, bd, dx, du, w, basis, precision):
    """The held levels' errors that best explain each small-signal record, given the model's
    discretisation (closed form: the response is linear in Δu), and Δu corrected by them.

    ``ad`` (R, n, n), ``bd`` (R, n, m), ``dx`` (R, S, n), ``du`` (R, S, m), ``w`` (R, n) the
    residual weights, ``basis`` (R, S, m, E), ``precision`` (R, E). Returns the errors (R, E), the
    corrected Δu (R, S, m) and the responses to the levels' unit errors (R, S, n, E).
    """
    import torch

    drive = torch.cat([du[..., None], basis], dim=-1)  # (R, S, m, 1 + E)
    y = torch.zeros((dx.shape[0], dx.shape[2], drive.shape[-1]), dtype=dx.dtype)
    out = [y]
    for k in range(dx.shape[1] - 1):
        y = ad @ y + bd @ drive[:, k]
        out.append(y)
    out = torch.stack(out, 1)  # (R, S, n, 1 + E)
    responses = out[..., 1:]
    weighted = responses * w[:, None, :, None]
    normal = torch.einsum("rsne,rsnf->ref", weighted, weighted) + torch.diag_embed(precision ** 2)
    rhs = torch.einsum("rsne,rsn->re", weighted, (out[..., 0] - dx) * w[:, None, :])
    levels = torch.zeros_like(precision)
    try:
        if bool(torch.isfinite(normal).all()) and bool(torch.isfinite(rhs).all()):
            levels = -torch.linalg.solve(normal, rhs[..., None])[..., 0]
    except torch.linalg.LinAlgError:
        pass  # a trial step that blew the response up: the levels stay as held (its cost is huge anyway)
    return levels, du + torch.einsum("rsme,re->rsm", basis, levels), responses


def _project_levels(record, profiled, slot, scale, unit, size):
    """One record's small-signal residuals and θ-Jacobian with its level errors profiled out
    (variable projection): the levels' prior rows appended, the Jacobian projected off the
    directions the levels take up (J − J_ε (J_εᵀJ_ε)⁻¹ J_εᵀJ)."""
    import torch

    res, jac = record
    levels, responses, precision = (v[slot, ..., :size] for v in profiled)
    j_data = (responses * scale[None, :, None]).reshape(-1, size)  # (S·n, E)
    prior = unit * precision
    normal = j_data.T @ j_data + torch.diag(prior ** 2)
    try:
        move = torch.linalg.solve(normal, j_data.T @ jac)  # (E, n_c)
    except torch.linalg.LinAlgError:  # a blown-up response (see _profile_level_errors): not projected
        move = torch.zeros((size, jac.shape[1]), dtype=jac.dtype)
    return (torch.cat([res, prior * levels]),
            torch.cat([jac - j_data @ move, -prior[:, None] * move]))


def _finite(blocks: dict) -> bool:
    return all(bool(value.isfinite().all()) for value in blocks.values())


class _ShootingProblem:
    """The multiple-shooting least-squares problem of one :meth:`TrajectoryFitter.fit` call.

    Parameters are the scaled support coefficients θ (coefficient / ``scale``) and each window's
    start-state offset z (in noise units). The Gauss-Newton normal equations come from forward
    sensitivities of the RK4 steps (f is linear in the coefficients, so ∂f/∂c is a term value;
    :meth:`_tangent_blocks`); the start states are eliminated window by window (Schur complement, as in bundle
    adjustment), so every step is exact at any problem size. Hand-written because neither scipy
    nor torch solves least squares with this block structure: ``scipy.optimize.least_squares`` on
    the full sparse Jacobian needed thousands of LSMR products per step at the benchmark's sizes.
    """

    def __init__(self, fitter: TrajectoryFitter, coef0, mask, train, smallsignal, lambda_jac, ss_stride,
                 lambda_stab=0.0, stability_margin=0.1, stability_records=None, lambda_eq=0.0,
                 equilibrium_space="rates", lambda_ridge=0.0):
        import torch

        torch.set_default_dtype(torch.float64)
        self.torch = torch
        self.terms = fitter.terms
        self.n = n = fitter.n_states
        self.window = fitter.window
        self.substeps = fitter.substeps
        self.h = fitter.dt / fitter.substeps
        xw, uw = trajectory_windows(train, fitter.window, max_windows=fitter.max_windows)
        # the starts of the windows inside a record's steady start: the plant sat at its rest state,
        # whose mean is known to noise/√samples, so a prior holds them there (z is in noise units; its
        # precision scaled as the windows' residuals are) and a model that drifts off that rest pays
        # for the whole window instead of moving its start to meet the drift
        self.rest_starts = None
        if fitter.rest_starts > 0:
            targets, samples = rest_window_starts(train, fitter.window, max_windows=fitter.max_windows)
            inside = samples > 0
            if inside.any():
                offsets = np.where(inside[:, None], (np.nan_to_num(targets) - xw[:, 0]) * fitter.weights, 0.0)
                precision = fitter.rest_starts * samples / (fitter.window + 1)
                self.rest_starts = (torch.tensor(offsets), torch.tensor(precision)[:, None])
        self.X = torch.tensor(xw)
        self.U = torch.tensor(uw)
        self.n_windows = self.X.shape[0]
        # torch.func's forward-mode autodiff (TermSet.thread_safe_gradient) must stay on one thread
        self.threads = fitter.threads if fitter.terms.thread_safe_gradient() else 1
        self.single_precision = fitter.single_precision
        self._pool = None
        self._kept = None  # the last cost pass: (θ, z, states, residuals, RK4 stage points)
        self.shape = coef0.shape
        self.idx = np.flatnonzero(mask.ravel())
        scale = np.abs(coef0.ravel()[self.idx])
        self.scale = np.where(scale > 0, scale, 1.0) + 1e-3 * np.abs(coef0).max()
        # which term and which state equation each support coefficient belongs to
        self.term_of = torch.tensor(self.idx // self.shape[1])
        self.row_of = torch.tensor(self.idx % self.shape[1])
        self.scale_t = torch.tensor(self.scale)
        self.idx_t = torch.tensor(self.idx)
        # residuals are (x - x_measured) * weight / sqrt(window + 1); z is in units of 1 / weight
        self.res_weight = torch.tensor(fitter.weights) / np.sqrt(fitter.window + 1)
        self.x_unit = torch.tensor(1.0 / fitter.weights)
        self.ss = []
        # noisy measured inputs held at their stretch means (ident.noise.piecewise_constant_inputs):
        # their noise per input, for the levels' errors the small-signal residuals profile out
        train_sigma = held_input_sigma(train)
        held_sigma = held_input_sigma(smallsignal) if smallsignal is not None else None
        if held_sigma is None:
            held_sigma = train_sigma
        # (the counts of every input held in either record set: each user reads its own inputs' only)
        either = held_sigma if train_sigma is None else np.maximum(held_sigma, train_sigma)
        counts = held_level_counts([*train, *(smallsignal if smallsignal is not None else [])], either) \
            if held_sigma is not None else None
        # the training records' held levels: each level's error is a parameter after the coefficients
        # (errors in variables, in units of its σ/√n with a unit normal prior), shared by every window
        # on it; their forcing per window sample and input comes from a one-hot table of the levels
        self.n_c = self.idx.size
        self.n_levels = 0
        if train_sigma is not None and fitter.held_levels:
            index, unit = held_window_levels(uw, train_sigma, counts)
            if unit.size:
                self.n_levels = unit.size
                index = np.where(index < 0, unit.size, index)  # "no level": a last slot, of zero error
                self.level_index = torch.tensor(index)
                self.level_unit = torch.tensor(unit)
                one_hot = np.zeros((*index.shape, unit.size + 1))
                np.put_along_axis(one_hot, index[..., None], 1.0, axis=-1)
                self.level_table = torch.tensor(one_hot[..., :unit.size] * unit)  # ∂u/∂θ_level
        self.n_params = self.n_c + self.n_levels
        if smallsignal is not None and lambda_jac > 0:
            for tr in smallsignal:
                k0, x_eq = steady_start_mean(tr)
                if x_eq is None:
                    continue
                dx = tr.x[k0 - 1::ss_stride] - x_eq
                du = tr.u[k0 - 1::ss_stride] - tr.u[0]
                grad = self.terms.gradient(np.concatenate([x_eq, tr.u[0]]))  # (n_terms, n_signals)
                # the linearisation itself is only good to ~1 % of the deviation for 1 % steps
                w_ss = 1.0 / np.sqrt((1.0 / fitter.weights) ** 2 + (0.01 * dx.std(axis=0)) ** 2 + 1e-30)
                offsets = None
                if held_sigma is not None:
                    basis, precision = held_level_basis(tr.u, held_sigma, np.arange(k0 - 1, len(tr), ss_stride), counts)
                    if precision.size:
                        offsets = (torch.tensor(basis), torch.tensor(precision))
                self.ss.append((torch.tensor(grad), torch.tensor(dx), torch.tensor(du), torch.tensor(w_ss), offsets))
        self.ss_dt = fitter.dt * ss_stride
        # stability prior: state-gradients of the terms at each anchoring operating point (the
        # records of one point share their rest state: the mean of their steady starts)
        self.rest_gradients = []
        self.rest_values = []  # equilibrium prior: (term values, 1 / σ of f there, θ-slopes) per rest state
        if equilibrium_space not in ("rates", "states"):
            raise ValueError(f"equilibrium_space must be rates or states, got {equilibrium_space!r}")
        self.equilibrium_space = equilibrium_space
        self.rest_states = []  # equilibrium prior in states: (term gradients, sqrt(samples) / noise) per rest state
        anchors = smallsignal if stability_records is None else stability_records
        if anchors is not None and (lambda_stab > 0 or lambda_eq > 0):
            rests: dict = {}
            for tr in anchors:
                length, rest = steady_start_mean(tr)
                if rest is not None:
                    rests.setdefault(tuple(np.round(tr.u[0], 9)), []).append((length, rest, tr.u))
            noise = 1.0 / np.asarray(fitter.weights, dtype=float)
            for u0, group in rests.items():
                samples = sum(length for length, _, _ in group)
                point = np.concatenate([np.mean([r for _, r, _ in group], axis=0), u0])
                full_grad = self.terms.gradient(point)
                grad = full_grad[:, :n]
                if lambda_stab > 0:
                    self.rest_gradients.append(grad)
                if lambda_eq > 0:
                    if equilibrium_space == "states":
                        sigma = np.ones(n)  # the slopes below are then plain ∂f/∂θ
                        self.rest_states.append((grad, np.sqrt(samples) / noise))
                    else:
                        # f at a measured rest state is zero up to the noise left in its mean, carried
                        # through the start model's Jacobian: the prior's unit for each equation
                        jac = coef0.T @ grad
                        variance = (jac ** 2) @ (noise ** 2) / samples
                        if held_sigma is not None:
                            # a held input's level is off by its noise over its stretch(es), and f
                            # with it (stop 91, recording 242, held ug in the small-signal records:
                            # with this prior off the refinement fit the training records, with it
                            # on in the state noise's unit alone it failed; README, stop 91)
                            variance = variance + (coef0.T @ full_grad[:, n:]) ** 2 @ held_level_variance(
                                group[0][2], held_sigma, counts)
                        sigma = np.sqrt(variance)
                        sigma = np.maximum(sigma, 1e-9 * (1.0 + np.abs(jac).max()))
                    values = self.terms.evaluate(point[None])[0]
                    # f is linear in θ: the prior's θ-derivatives are fixed, built once here
                    slopes = np.zeros((n, self.idx.size))
                    slopes[self.idx % self.shape[1], np.arange(self.idx.size)] = (
                        self.scale * values[self.idx // self.shape[1]] / sigma[self.idx % self.shape[1]])
                    self.rest_values.append((values, 1.0 / sigma, slopes))
        self.ridge_unit = np.zeros(self.idx.size)  # ridge prior: ∂residual/∂θ per support coefficient
        if lambda_ridge > 0 and self.idx.size:
            points = np.concatenate([xw, uw], axis=-1).reshape(-1, xw.shape[-1] + uw.shape[-1])
            values = self.terms.evaluate(points)
            term_rms = np.sqrt(np.mean(values ** 2, axis=0))
            rate_rms = np.sqrt(np.mean((values @ coef0) ** 2, axis=0))
            rate_rms = np.maximum(rate_rms, 1e-9 * (1.0 + rate_rms.max()))
            self.ridge_unit = np.sqrt(lambda_ridge) * self.scale * (
                term_rms[self.idx // self.shape[1]] / rate_rms[self.idx % self.shape[1]])
        # the held levels' prior N(0, 1) in their units: a ridge of unit weight on their entries
        self.ridge_unit = np.concatenate([self.ridge_unit, np.ones(self.n_levels)])
        self.sqrt_ls = float(np.sqrt(lambda_stab))
        self.sqrt_le = float(np.sqrt(lambda_eq))
        self.stability_margin = float(stability_margin)
        self.sqrt_lj = float(np.sqrt(lambda_jac))

    def parameters(self, coefficients):
        """θ of a coefficient matrix of the problem's shape: its support entries over ``scale``, and every
        held level's error at zero."""
        return self.torch.tensor(np.concatenate([np.asarray(coefficients).ravel()[self.idx] / self.scale,
                                                 np.zeros(self.n_levels)]))

    def coefficients(self, theta) -> np.ndarray:
        out = np.zeros(int(np.prod(self.shape)))
        out[self.idx] = np.asarray(theta)[:self.n_c] * self.scale
        return out.reshape(self.shape)

    def _matrix(self, theta):
        torch = self.torch
        flat = torch.zeros(int(np.prod(self.shape)), dtype=theta.dtype)
        return flat.index_put((self.idx_t,), theta[:self.n_c] * self.scale_t).reshape(self.shape)

    def _shoot(self, theta, z, tangents: str = "", beside=None, keep: bool = False):
        """Integrate every window from its start; residuals, and the Gauss-Newton blocks when
        ``tangents`` names them ("z": start states only; "zc": also the coefficients).

        ``keep`` keeps this pass's states (a cost evaluation: the Levenberg-Marquardt loop asks for
        the normal equations at the point it has just evaluated when it takes the step); a pass with
        tangents at the kept θ and z starts from them instead of integrating again.

        With ``threads`` > 1 the windows are shared out in contiguous parts, one thread each (the
        windows are independent; torch releases the GIL in its kernels, and one part per thread keeps
        the two cores busy where one intra-op pool over these small batched products did not:
        measured on a 40 dB benchmark refinement, torch on 2 threads took as long as on 1).

        Only the passes with tangents are shared out: one without is too light (measured: it took
        longer in two parts). A pass with start-state tangents alone ("z", :meth:`fit_starts`) gains
        (measured, 480 windows of 10 at 40 dB: 0.075 s in two parts against 0.10 s in one, the same
        blocks to the bit).
        ``beside()``, if given, runs on the calling thread meanwhile.

        Returns (cost of the trajectory residuals, blocks or None, what ``beside`` returned).
        """
        torch = self.torch
        parts = min(self.threads, self.n_windows) if tangents else 1
        kept = self._kept if tangents and self._kept is not None and torch.equal(self._kept[0], theta) \
            and torch.equal(self._kept[1], z) else None
        if parts <= 1:
            return (*self._shoot_part(theta, z, slice(None), tangents, keep, kept), beside() if beside else None)
        bounds = np.linspace(0, self.n_windows, parts + 1).round().astype(int)
        slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self.terms.values_and_jacobian_torch(torch.cat([self.X[:1, 0], self.U[:1, 0]], dim=-1),
                                                 self._matrix(theta), self.n)  # compiled once, as is
            if self.n_levels:  # the held levels' forcing
                self.terms.input_jacobian_torch(torch.cat([self.X[:1, 0], self.U[:1, 0]], dim=-1), self._matrix(theta),
                                                self.n)
            self.terms.evaluate_split_torch(self.X[:1, 0], self.U[:1, 0])  # the state pass's evaluation
            self._pool = ThreadPoolExecutor(parts, "pisml-shoot")
        futures = [self._pool.submit(self._shoot_part, theta, z[part], part, tangents, False, kept) for part in slices]
        extra = beside() if beside else None
        results = [future.result() for future in futures]
        cost = sum(c for c, _ in results)
        blocks = {}
        for key in results[0][1]:
            values = [b[key] for _, b in results]
            # per-window blocks side by side, sums (gradient, Hessian) added
            blocks[key] = torch.cat(values) if key in ("A", "bz", "E") else sum(values[1:], values[0])
        return cost, blocks, extra

    def close(self):
        """Release the threads of the window parts (if any)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def _shoot_part(self, theta, z, rows: slice, tangents: str = "", keep: bool = False, kept=None):
        """:meth:`_shoot` over the windows ``rows`` (``z``: their start offsets); ``keep`` and
        ``kept`` as there.

        The states go sample by sample (RK4 is sequential). With ``tangents`` the RK4 stage points
        are kept, and a chunk of samples at a time the model's Jacobians there, each sample's
        tangent map (:func:`_rk4_tangent_map`) and the coefficients' forcing come from batched
        operations; only the tangents' linear recursion S_(k+1) = P_k·S_k + Q_k goes sample by
        sample. The passes are launch-bound (small batches, many samples per window), so fewer
        and larger operations are most of the speed.
        """
        torch = self.torch
        c = self._matrix(theta)
        X, u_all = self.X[rows], self.U[rows]
        if self.n_levels:  # the held levels moved by their errors
            errors = torch.cat([theta[self.n_c:] * self.level_unit, torch.zeros(1, dtype=theta.dtype)])
            u_all = u_all + errors[self.level_index[rows]]
        if kept is not None:
            states, residuals, points = ([value[rows] for value in values] for values in kept[2:])
            cost = 0.5 * float(torch.stack(residuals).square().sum())
            return cost, self._tangent_blocks(c, X, u_all, states, residuals, points, "c" in tangents, rows)
        h = self.h
        x = X[:, 0] + z * self.x_unit
        w = self.res_weight

        def residual(x, k):
            return torch.nan_to_num((x - X[:, k]) * w, nan=1e6, posinf=1e6, neginf=-1e6).clamp(-1e6, 1e6)

        def rate(y, u):
            return self.terms.evaluate_split_torch(y, u) @ c

        cost = 0.0
        r = residual(x, 0)
        cost += 0.5 * float((r * r).sum())
        # with tangents or keep: per sample the state, its residuals and the RK4 stage points (n_win, 4·substeps, n)
        states, residuals, points = [x], [r], []
        for k in range(self.window):
            u = u_all[:, k]
            stage_points = []
            for _ in range(self.substeps):
                k1 = rate(x, u)
                x2 = x + 0.5 * h * k1
                k2 = rate(x2, u)
                x3 = x + 0.5 * h * k2
                k3 = rate(x3, u)
                x4 = x + h * k3
                k4 = rate(x4, u)
                stage_points += [x, x2, x3, x4]
                x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
            r = residual(x, k + 1)
            cost += 0.5 * float((r * r).sum())
            if tangents or keep:
                states.append(x)
                residuals.append(r)
                points.append(torch.stack(stage_points, dim=1))
        if keep:
            self._kept = (theta.clone(), z.clone(), states, residuals, points)
        if not tangents:
            return cost, None
        return cost, self._tangent_blocks(c, X, u_all, states, residuals, points, "c" in tangents, rows)

    def _tangent_blocks(self, c, X, u_all, states, residuals, points, coefficients: bool, rows=slice(None)):
        """The Gauss-Newton blocks of one part's windows (``rows``) from its states and RK4 stage points
        (:meth:`_shoot_part`): "A", "bz" (start states) and, with ``coefficients``, "H", "g", "E" (in
        all parameters: the coefficients, then the held levels' errors)."""
        torch = self.torch
        n, n_win, n_c = self.n, X.shape[0], self.n_params
        n_stages, n_terms, n_inputs = 4 * self.substeps, len(self.terms), u_all.shape[-1]
        w = self.res_weight
        # the coefficient tangents' type (TrajectoryFitter.single_precision); the rest stays float64
        single = self.single_precision and coefficients
        tangent_type = torch.float32 if single else torch.float64
        add_gram = _add_gram_single if single else _add_gram
        blocks = {"A": torch.zeros((n_win, n, n)), "bz": torch.zeros((n_win, n))}
        if coefficients:
            blocks.update(g=torch.zeros(n_c), E=torch.zeros((n_win, n, n_c), dtype=tangent_type))
            # JᵀJ of the coefficients by BLAS syrk (half the work of a product; upper triangle)
            hessian = np.zeros((n_c, n_c), order="F", dtype=np.float32 if single else np.float64)
        # where each support coefficient sits in a (states × terms) table flattened row by row
        state_term = self.row_of * n_terms + self.term_of
        level_table = self.level_table[rows].to(tangent_type) if self.n_levels and coefficients else None
        # the coefficient tangents are carried in residual units (state k's row times its residual
        # weight w_k): the Gauss-Newton blocks then read them as they are
        forcing_scale = (w[:, None] * self.scale_t[None, :]).to(tangent_type)
        rescale = w[:, None] / w[None, :]

        def accumulate(jz, jc, r, alive):
            """Add samples' rows: jz (m, n_win, n, n) start-state tangents, jc (m, n_win, n, n_c)
            coefficient tangents (residual units) or None, r (m, n_win, n), alive (m, n_win)."""
            # a window that has blown up (residuals at the clip) has no useful slope: it adds none
            mask = alive.to(r.dtype)[..., None, None]
            jz = torch.nan_to_num(jz * w[:, None], nan=0.0, posinf=0.0, neginf=0.0) * mask
            jz_t = jz.transpose(-1, -2).contiguous()  # (a transposed view takes a slow batched product)
            for i in range(jz.shape[0]):
                blocks["A"].baddbmm_(jz_t[i], jz[i])
                blocks["bz"] += (jz_t[i] @ r[i][..., None])[..., 0]
            if jc is None:
                return
            # a non-finite entry makes its column's gradient entry non-finite, so the copy that
            # clears them is made only then
            flat = jc.reshape(-1, n_c)
            r = r.to(tangent_type)
            gradient = flat.T @ r.reshape(-1)
            if not (bool(alive.all()) and bool(torch.isfinite(gradient).all())):
                jc = torch.nan_to_num(jc, nan=0.0, posinf=0.0, neginf=0.0) * mask.to(tangent_type)
                flat = jc.reshape(-1, n_c)
                gradient = flat.T @ r.reshape(-1)
            if n_c:
                add_gram(np.ascontiguousarray(flat.numpy()), hessian)
            blocks["g"] += gradient
            jz_t = jz_t.to(tangent_type)
            for i in range(jc.shape[0]):
                blocks["E"].baddbmm_(jz_t[i], jc[i])

        def rows_at(k0, k1):
            """Residuals and aliveness of samples k0..k1-1, sample-major."""
            xs = torch.stack(states[k0:k1])
            r = torch.stack(residuals[k0:k1])
            alive = (r.abs() < 1e6).all(dim=-1) & torch.isfinite(xs).all(dim=-1)
            return r, alive

        s_z = torch.diag(self.x_unit).expand(n_win, n, n).clone()  # d x / d z (each window's own start)
        s_c = torch.zeros((n_win, n, n_c), dtype=tangent_type) if coefficients else None  # d x / d θ, residual units
        r, alive = rows_at(0, 1)
        accumulate(s_z[None], None, r, alive)  # the start: no coefficient enters yet
        # samples per chunk: ~256 window-samples (the chunk's tangents ~8 MB at 300 coefficients; stop 67,
        # windows of 10 and 25 at 40 dB: 1024 and 4096 took longer per pass, with one thread and two)
        chunk = max(1, 256 // max(n_win, 1))
        for k0 in range(0, self.window, chunk):
            k1 = min(self.window, k0 + chunk)
            m = k1 - k0
            pts = torch.stack(points[k0:k1])  # (m, n_win, n_stages, n), sample-major
            inputs = u_all[:, k0:k1].transpose(0, 1)[:, :, None, :].expand(m, n_win, n_stages, n_inputs)
            signals = torch.cat([pts, inputs], dim=-1).reshape(-1, n + n_inputs)
            values, jx = self.terms.values_and_jacobian_torch(signals, c, n)
            jx = jx.reshape(m * n_win, self.substeps, 4, n, n)
            maps = _rk4_tangent_map(*(jx[:, :, i].reshape(-1, n, n) for i in range(4)), self.h,
                                    forced=coefficients).view(m * n_win, self.substeps, n, -1)
            # the RK4 steps of a sample composed: [P | D_1 ... D_(n_stages)] (:func:`_rk4_tangent_map`)
            sample = maps[:, 0]
            for i in range(1, self.substeps):
                step = maps[:, i]
                sample = torch.cat([step[..., :n] @ sample, step[..., n:]], dim=2)
            propagators = sample[..., :n].reshape(m, n_win, n, n)
            tangents_z = torch.empty((m, n_win, n, n))
            if coefficients:
                # B_i of coefficient (term t, equation j) is the term's value in row j, so
                # (D_i·B_i)[:, (t, j)] = D_i[:, j]·value_t: every pair from one small product of
                # the D's and the stages' term values, then the support's entries picked
                d = sample[..., n:].reshape(m * n_win, n, n_stages, n).transpose(2, 3).reshape(m * n_win, n * n, n_stages)
                table = torch.bmm(d.to(tangent_type), values.view(m * n_win, n_stages, n_terms).to(tangent_type)
                                  ).view(m * n_win * n, n * n_terms)
                # (2-D index_select: ~5x the speed of the same pick along a 3-D tensor's last axis);
                # each sample's slot then takes its tangents in place (S = P·S + forcing)
                tangents_c = torch.index_select(table, 1, state_term).view(m, n_win, n, self.n_c).mul_(forcing_scale)
                if level_table is not None:
                    # a level error δ moves every stage's rate by ∂f/∂u·δ, which the steps' D_i carry
                    ju = self.terms.input_jacobian_torch(signals, c, n)
                    ju = ju.reshape(m * n_win, n_stages, n, n_inputs).to(tangent_type)
                    # (.., out state, stage, state)
                    gains = d.view(m * n_win, n, n, n_stages).transpose(2, 3).to(tangent_type)
                    per_input = torch.einsum("brsk,bskj->brj", gains, ju).view(m, n_win, n, n_inputs)
                    levels = torch.einsum("mwrj,wmjl->mwrl", per_input, level_table[:, k0:k1])
                    tangents_c = torch.cat([tangents_c, levels * w[None, None, :, None].to(tangent_type)], dim=-1)
                weighted = (propagators * rescale).to(tangent_type)
            for i in range(m):
                s_z = torch.bmm(propagators[i], s_z, out=tangents_z[i])
                if coefficients:
                    s_c = tangents_c[i].baddbmm_(weighted[i], s_c)
            r, alive = rows_at(k0 + 1, k1 + 1)
            accumulate(tangents_z, tangents_c if coefficients else None, r, alive)
        if coefficients:
            upper = torch.from_numpy(np.triu(hessian).astype(np.float64))
            blocks["H"] = upper + upper.T - torch.diag(torch.diagonal(upper))
            blocks["E"] = blocks["E"].to(torch.float64)
        return blocks

    def _smallsignal_residuals(self, theta):
        """Around the pre-step steady state of each small-signal record, the model's linearisation
        (exact zero-order-hold discretisation) must reproduce the measured deviation."""
        torch = self.torch
        c = self._matrix(theta)
        n = self.n
        res = []
        for grad, dx, du, w_ss, offsets in self.ss:
            jac = c.T @ grad  # (n_states, n_signals)
            m = torch.cat([jac, torch.zeros((du.shape[1], n + du.shape[1]), dtype=c.dtype)], dim=0)
            disc = torch.linalg.matrix_exp(m * self.ss_dt)
            ad, bd = disc[:n, :n], disc[:n, n:]
            if offsets is not None:
                levels, du, _ = _profile_level_errors(ad[None], bd[None], dx[None], du[None], w_ss[None],
                                                      offsets[0][None], offsets[1][None])
                du = du[0]
                res.append(self.sqrt_lj / np.sqrt(dx.shape[0]) * offsets[1] * levels[0])  # their prior
            # the record is in steady state before the step: a start at the first (noisy) deviation
            # sample would ring the fast modes through the whole record
            y = torch.zeros_like(dx[0])
            preds = [y]
            for k in range(dx.shape[0] - 1):
                y = ad @ y + bd @ du[k]
                preds.append(y)
            res.append(self.sqrt_lj * ((torch.stack(preds) - dx) * w_ss).reshape(-1) / np.sqrt(dx.shape[0]))
        return torch.cat(res) if res else torch.zeros(0)

    def _stability_residuals(self, theta):
        """Stability prior: residuals ``sqrt(λ_s)·(Re λ + margin)`` of the eigenvalues of the model's
        Jacobian at the anchoring records' rest states whose real part exceeds ``-margin``, and their
        derivatives in θ (first-order eigenvalue perturbation: dλ = uᴴ dA v / uᴴv)."""
        c = self.coefficients(np.asarray(theta))
        res, rows = [], []
        for grad in self.rest_gradients:
            a = c.T @ grad  # (n_states, n_states): row j is equation j
            if not np.all(np.isfinite(a)):
                continue
            lam, left, right = scipy.linalg.eig(a, left=True, right=True)
            for i in np.flatnonzero(lam.real > -self.stability_margin):
                res.append(self.sqrt_ls * (lam[i].real + self.stability_margin))
                u, v = left[:, i], right[:, i]
                overlap = u.conj() @ v  # scipy's eigenvectors have unit norm: |uᴴv| = 1 / condition
                if abs(overlap) < DEFECTIVE_OVERLAP:
                    # a defective eigenvalue (a Jordan block: a state whose equation lost its terms
                    # gives a repeated 0) has no derivative; the residual still counts in the cost,
                    # but an inf/NaN row would end the whole Gauss-Newton loop (_finite)
                    rows.append(np.zeros(self.idx.size))
                    continue
                d_re = np.real(np.outer(u.conj(), v) / overlap)  # ∂Re λ / ∂A
                # A[j, k] = Σ_t c[t, j]·grad[t, k]: ∂A[row, k] / ∂θ = scale·grad[term, k]
                rows.append(self.sqrt_ls * self.scale * np.einsum("ik,ik->i", d_re[self.row_of.numpy()],
                                                                  grad[self.term_of.numpy()]))
        if not res:
            return np.zeros(0), np.zeros((0, self.idx.size))
        return np.array(res), np.array(rows)

    def _equilibrium_residuals(self, theta):
        """Equilibrium prior: ``sqrt(λ_e)·f_j(x_r, u_r)/σ_j`` at each anchoring rest state (a record
        that starts at rest starts at an equilibrium), and their θ-derivatives (f is linear in θ)."""
        if not self.rest_values:
            return np.zeros(0), np.zeros((0, self.idx.size))
        c = self.coefficients(np.asarray(theta))
        if self.equilibrium_space == "states":
            res, rows = [], []
            for (values, _, slopes), (grad, unit) in zip(self.rest_values, self.rest_states):
                # the Newton step to the model's equilibrium; its θ-derivative with J held (the term
                # J⁻¹·dJ·J⁻¹f is second order where the step is small)
                jac = c.T @ grad
                rhs = np.column_stack([values @ c, slopes])
                try:
                    solved = scipy.linalg.solve(jac, rhs, check_finite=False)
                except (np.linalg.LinAlgError, ValueError):
                    solved = np.linalg.lstsq(jac, rhs, rcond=None)[0]
                res.append(self.sqrt_le * unit * solved[:, 0])
                rows.append(self.sqrt_le * unit[:, None] * solved[:, 1:])
            return np.concatenate(res), np.concatenate(rows)
        res = [self.sqrt_le * (values @ c) * inv_sigma for values, inv_sigma, _ in self.rest_values]
        return np.concatenate(res), self.sqrt_le * np.concatenate([slopes for _, _, slopes in self.rest_values])

    def _smallsignal_jacobian(self, theta):
        """:meth:`_smallsignal_residuals` and their θ-derivatives, by tangents carried through the
        recursion; the derivatives of the discretisation exp(M·dt) in each coefficient's direction
        from :func:`_expm_row_derivatives`. Records of equal length step together."""
        torch = self.torch
        c = self._matrix(theta)
        n, n_c = self.n, self.idx.size
        out = [None] * len(self.ss)
        lengths = sorted({rec[1].shape[0] for rec in self.ss})
        for length in lengths:
            members = [i for i, rec in enumerate(self.ss) if rec[1].shape[0] == length]
            grad, dx, du, w_ss = (torch.stack([self.ss[i][k] for i in members]) for k in range(4))
            n_rec, size = grad.shape[0], grad.shape[2]  # states + inputs: the inputs held constant
            m = torch.zeros((n_rec, size, size), dtype=c.dtype)
            m[:, :n] = torch.einsum("tj,rts->rjs", c, grad)
            # a coefficient (term t, equation j) moves row j of M by its term's gradient
            disc, d_disc = _expm_row_derivatives(m, self.row_of, grad[:, self.term_of] * self.scale_t[None, :, None],
                                                 self.ss_dt)
            ad, bd = disc[:, :n, :n], disc[:, :n, n:]
            profiled = None
            if any(self.ss[i][4] is not None for i in members):
                basis, precision = _stack_offsets([self.ss[i][4] for i in members], length, du.shape[2])
                levels, du, responses = _profile_level_errors(ad, bd, dx, du, w_ss, basis, precision)
                profiled = (levels, responses, precision)
            # the response itself is the same for every coefficient: first all of it
            y = torch.zeros((n_rec, n), dtype=c.dtype)
            preds = [y]
            for k in range(length - 1):
                y = (ad @ y[..., None] + bd @ du[:, k, :, None])[..., 0]
                preds.append(y)
            preds = torch.stack(preds, 1)  # (records, samples, n)
            # then the tangents (transposed: states × coefficients, as the shooting pass's):
            # dy_(k+1) = ad·dy_k + d_ad·y_k + d_bd·du_k, the last two for every k in one product
            drive = torch.cat([preds[:, :-1], du[:, :length - 1]], dim=2)  # (records, samples - 1, size)
            forcing = torch.einsum("rics,rks->kric", d_disc[:, :n], drive)
            tangents = torch.zeros((length, n_rec, n, n_c), dtype=c.dtype)
            for k in range(length - 1):
                torch.baddbmm(forcing[k], ad, tangents[k], out=tangents[k + 1])
            scale = self.sqrt_lj * w_ss / np.sqrt(length)  # (records, n)
            res = (preds - dx) * scale[:, None]  # (records, samples, n)
            jac = tangents.mul_(scale[None, :, :, None])
            for slot, i in enumerate(members):
                out[i] = (res[slot].reshape(-1), jac[:, slot].reshape(-1, n_c))
                if profiled is not None and self.ss[i][4] is not None:
                    out[i] = _project_levels(out[i], profiled, slot, scale[slot], self.sqrt_lj / np.sqrt(length),
                                             self.ss[i][4][1].numel())
        return torch.cat([r for r, _ in out]), torch.cat([j for _, j in out])

    def cost(self, theta, z) -> float:
        with self.torch.no_grad():
            traj, _, _ = self._shoot(theta, z, keep=True)
            ss = self._smallsignal_residuals(theta)
        stab, _ = self._stability_residuals(theta)
        eq, _ = self._equilibrium_residuals(theta)
        ridge = self.ridge_unit * np.asarray(theta)
        value = (traj + 0.5 * float((ss * ss).sum()) + 0.5 * float(stab @ stab) + 0.5 * float(eq @ eq)
                 + 0.5 * float(ridge @ ridge) + self._rest_start_cost(z))
        return value if np.isfinite(value) else np.inf

    def _rest_start_cost(self, z) -> float:
        """The rest-start prior's cost (0 without it)."""
        if self.rest_starts is None:
            return 0.0
        offsets, precision = self.rest_starts
        return 0.5 * float((precision * (z - offsets).square()).sum())

    def _add_rest_starts(self, blocks, z):
        """The rest-start prior's curvature and gradient in the start-state blocks "A" and "bz"."""
        if self.rest_starts is None:
            return
        offsets, precision = self.rest_starts
        blocks["A"] += self.torch.diag_embed(precision.expand(-1, self.n))
        blocks["bz"] += precision * (z - offsets)

    def normal_equations(self, theta, z) -> dict:
        torch = self.torch
        def smallsignal():
            """The small-signal residuals' JᵀJ and Jᵀr, on the calling thread while the window parts
            run (measured, 40 dB, 480 windows of 10, 278 coefficients: the pass took 0.321 s median
            here against 0.348 s with the products after the parts, the same blocks to the bit)."""
            if not (self.ss and self.idx.size):
                return None
            with torch.no_grad():
                r, j = self._smallsignal_jacobian(theta)
                j = torch.nan_to_num(j)
                return j.T @ j, j.T @ torch.nan_to_num(r)

        with torch.no_grad():
            _, blocks, ss = self._shoot(theta, z, "zc", beside=smallsignal)
        self._add_rest_starts(blocks, z)
        k = self.n_c  # the coefficients' entries; the held levels' after them
        if ss is not None:
            blocks["H"][:k, :k] += ss[0]
            blocks["g"][:k] += ss[1]
        # the priors' curvature, kept apart too: the data's alone give the coefficients' covariance
        blocks["H_prior"] = torch.zeros_like(blocks["H"])
        for res, jac in (self._stability_residuals(theta), self._equilibrium_residuals(theta)):
            if res.size:
                blocks["H_prior"][:k, :k] += torch.tensor(jac.T @ jac)
                blocks["g"][:k] += torch.tensor(jac.T @ res)
        if self.ridge_unit.any():  # residuals unit·θ: a diagonal JᵀJ
            unit2 = torch.tensor(self.ridge_unit ** 2)
            blocks["H_prior"] += torch.diag(unit2)
            blocks["g"] += unit2 * torch.as_tensor(theta, dtype=unit2.dtype)
        blocks["H"] += blocks["H_prior"]
        return blocks

    def damped_step(self, blocks, mu):
        """The Levenberg-Marquardt step (Marquardt's diagonal scaling) with the start states
        eliminated; returns (Δθ, Δz, predicted cost reduction)."""
        torch = self.torch
        d_c = torch.diagonal(blocks["H"]).clamp_min(1e-12)
        d_z = torch.diagonal(blocks["A"], dim1=1, dim2=2).clamp_min(1e-12)
        a = blocks["A"] + torch.diag_embed(mu * d_z)
        a_e = torch.linalg.solve(a, blocks["E"])
        a_b = torch.linalg.solve(a, blocks["bz"][..., None])[..., 0]
        reduced = blocks["H"] + torch.diag(mu * d_c) - torch.einsum("wkc,wkd->cd", blocks["E"], a_e)
        g = blocks["g"] - torch.einsum("wkc,wk->c", blocks["E"], a_b)
        # LAPACK gelsy through scipy: torch's CPU lstsq (the same driver) gave a different step on
        # every call for the same matrix (benchmark recording, condition number 4e10), so that the
        # same data gave different models from run to run
        step_c = -torch.from_numpy(scipy.linalg.lstsq(
            reduced.numpy(), g.numpy(), cond=np.finfo(float).eps * g.numel(), lapack_driver="gelsy",
            check_finite=False)[0]) if g.numel() else g
        step_z = -(a_b + torch.einsum("wkc,c->wk", a_e, step_c))
        # model reduction -(g·δ + ½ δᵀJᵀJδ) = ½ δᵀ(μD)δ - ½ gᵀδ for the exact damped step
        predicted = 0.5 * float(mu * (d_c * step_c ** 2).sum() + mu * (d_z * step_z ** 2).sum()
                                - (blocks["g"] * step_c).sum() - (blocks["bz"] * step_z).sum())
        return step_c, step_z, predicted

    def fit_starts(self, theta, z, iterations: int = 3):
        """Gauss-Newton on the window start states alone (independent per window)."""
        torch = self.torch
        cost = self.cost(theta, z)
        for _ in range(iterations):
            with torch.no_grad():
                _, blocks, _ = self._shoot(theta, z, "z")
            self._add_rest_starts(blocks, z)
            a = blocks["A"] + 1e-9 * torch.diag_embed(torch.diagonal(blocks["A"], dim1=1, dim2=2))
            trial = z - torch.linalg.solve(a, blocks["bz"][..., None])[..., 0]
            trial_cost = self.cost(theta, trial)
            if not trial_cost < cost:
                break
            z, cost = trial, trial_cost
        return z

    def profiled_hessian(self, blocks) -> np.ndarray:
        """JᵀJ of the coefficients with the window start states minimised out (Schur complement):
        the curvature of the cost when the starts re-adjust to a coefficient change, in
        coefficient units (for :func:`backward_elimination`)."""
        torch = self.torch
        a = blocks["A"] + 1e-12 * torch.diag_embed(torch.diagonal(blocks["A"], dim1=1, dim2=2))
        h = blocks["H"] - torch.einsum("wkc,wkd->cd", blocks["E"], torch.linalg.solve(a, blocks["E"]))
        if self.n_levels:  # the held levels' errors minimised out too
            k = self.n_c
            h = h[:k, :k] - h[:k, k:] @ torch.linalg.solve(h[k:, k:], h[k:, :k])
        return h.numpy() / np.outer(self.scale, self.scale)

    def prior_hessian(self, blocks) -> np.ndarray:
        """The priors' (stability, equilibrium, ridge) part of :meth:`profiled_hessian`, in
        coefficient units (they do not involve the window start states)."""
        return blocks["H_prior"][:self.n_c, :self.n_c].numpy() / np.outer(self.scale, self.scale)


class _ZeroModes:
    """:func:`backward_elimination`'s check for a mode of modulus below ``threshold`` (1/s) in the
    model's Jacobians at the operating points of ``state_gradients`` (see there); it only judges
    points where the starting ``coefficients`` have none (the check is off with no gradients or a
    threshold of 0)."""

    def __init__(self, coefficients, support, scale, state_gradients, threshold: float):
        self.shape, self.support, self.scale = coefficients.shape, support, scale
        self.threshold = threshold
        gradients = list(state_gradients or []) if threshold > 0 else []
        flat = coefficients.ravel()[support].astype(float) * scale
        self.gradients = [g for g in gradients if self._smallest(flat, g) >= threshold]

    def _smallest(self, beta, gradient) -> float:
        flat = np.zeros(int(np.prod(self.shape)))
        flat[self.support] = beta / self.scale
        jac = flat.reshape(self.shape).T @ gradient
        if not np.all(np.isfinite(jac)):
            return np.inf
        return float(np.min(np.abs(np.linalg.eigvals(jac))))

    def leaves_zero_mode(self, beta) -> bool:
        """Whether the coefficients ``beta`` (support, scaled) have such a mode at every one of the
        points: a state the model no longer pulls back lacks it at all of them, where a slow mode
        crossing from stable to unstable as terms go passes near zero at one (protocol recording 8
        at 40 dB, asked at any point: the first prune round went another way and its third round
        came out spurious at ug 0.2)."""
        return bool(self.gradients) and all(self._smallest(beta, g) < self.threshold for g in self.gradients)


def backward_elimination(coefficients: np.ndarray, hessian: np.ndarray, support: np.ndarray,
                         budgets, order_weights=None, groups=None, state_gradients=None,
                         zero_mode: float = 0.0) -> list[tuple[float, np.ndarray]]:
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
    order_weights : ndarray, shape (n_support,), optional
        Positive weights on the rises that rank the removals (the smallest weighted rise goes
        first); the budgets still count the unweighted rises. A weight below 1 makes a
        coefficient go sooner than another that costs as little to lose. None: all 1.
    groups : ndarray of int, shape (n_support,), optional
        A label per support coefficient (its equation, say): the last one left of a group is
        never dropped. None: no groups.
    state_gradients : sequence of ndarray, shape (n_terms, n_states), optional
        The terms' gradients in the states at some operating points (the records' rest states), so
        that the model's Jacobian there is ``coefficients.T @ gradient``. With ``zero_mode`` > 0, a
        drop that leaves that Jacobian an eigenvalue of modulus below ``zero_mode`` (1/s) at every
        one of them where the starting model had none is not made (that coefficient stays): such
        a mode is a state the model no longer pulls back, an equilibrium the smallest offset moves
        far, which the cost of 40 ms windows hardly sees.
    zero_mode : float
        See ``state_gradients``; 0: no such check.

    Returns
    -------
    list of (predicted rise, coefficients)
        One model per budget (the sparsest that stays within it), in the order of ``budgets``.
    """
    # in Jacobi-scaled units (coefficients span many decades); the elimination is invariant to it
    d = np.sqrt(np.clip(np.diag(hessian), 1e-300, None))
    beta = coefficients.ravel()[support].astype(float) * d
    # on one BLAS thread: the eigendecomposition's rounding depends on the threads, and a prune
    # round's polish then ends a little apart (stop 86: up to 2e-3 in a coefficient); so the same
    # everywhere, whether the family runs alone (two threads) or beside another (one)
    with blas_threads(1, user_api="blas"):
        h_inv = np.linalg.pinv(hessian / np.outer(d, d), rcond=1e-12, hermitian=True)
    order_weights = np.ones(beta.size) if order_weights is None else np.asarray(order_weights, dtype=float)
    groups = None if groups is None else np.asarray(groups)
    alive = np.ones(beta.size, dtype=bool)
    kept = np.zeros(beta.size, dtype=bool)  # drops refused for the mode they would leave
    modes = _ZeroModes(coefficients, support, d, state_gradients, zero_mode)
    rise = 0.0
    path = [(0.0, beta.copy(), alive.copy())]
    while alive.sum() > 1:
        live = np.flatnonzero(alive)
        diag = np.diag(h_inv)[live]
        with np.errstate(over="ignore", divide="ignore"):  # a pinned coefficient: infinite cost, never dropped
            cost_up = np.where(diag > 0, 0.5 * beta[live] ** 2 / np.maximum(diag, 1e-300), np.inf)
        if groups is not None:  # a group's last member stays
            labels, counts = np.unique(groups[live], return_counts=True)
            cost_up = np.where(np.isin(groups[live], labels[counts == 1]), np.inf, cost_up)
        cost_up = np.where(kept[live], np.inf, cost_up)
        k = int(np.argmin(cost_up * order_weights[live]))
        j = live[k]
        if not np.isfinite(cost_up[k]):
            break
        # drop j: the constrained minimum of the quadratic model, and H⁻¹ restricted to the rest
        dropped = beta - h_inv[:, j] * (beta[j] / h_inv[j, j])
        dropped[j] = 0.0
        if modes.leaves_zero_mode(dropped):
            kept[j] = True
            continue
        rise += float(cost_up[k])
        beta = dropped
        h_inv = h_inv - np.outer(h_inv[:, j], h_inv[j, :]) / h_inv[j, j]
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


def window_costs(models: dict, train: Dataset, window: int, weights=None, substeps: int = 2) -> dict:
    """Each model's multiple-shooting cost on ``train`` over windows of ``window`` samples, its
    coefficients as they are and each window's start state fitted (:meth:`_ShootingProblem.fit_starts`):
    how well it follows the records over short spans, where the fast modes (the LCL resonances) show,
    in the units of :meth:`TrajectoryFitter.fit`'s cost (half the squared misfit in noise units over
    ``window + 1``: ``2 (window + 1)`` times a difference of two such costs is a chi-square).

    Parameters
    ----------
    models : dict
        Name -> :class:`~pisml_ros.model.ExplicitModel`, over the records' states and inputs.
    train : Dataset
    window : int
        Samples per shooting window.
    weights : ndarray, shape (n_states,), optional
        Residual weight per state (1/noise std); :func:`.noise.residual_weights` of ``train`` if None.

    Returns
    -------
    dict
        Name -> cost (inf where a window's run blows up).
    """
    import torch

    from ..model.expressions import term_set
    from .noise import residual_weights

    weights = residual_weights(train) if weights is None else weights
    costs = {}
    for name, model in models.items():
        coefficients = np.asarray(model.coefficients, dtype=float)
        fitter = TrajectoryFitter(term_set(model.terms, tuple(model.state_names) + tuple(model.input_names)),
                                  model.n_states, train.dt, window=window, substeps=substeps, weights=weights)
        problem = _ShootingProblem(fitter, coefficients, coefficients != 0.0, train, None, 0.0, 5)
        try:
            theta = problem.parameters(coefficients)
            starts = problem.fit_starts(theta, torch.zeros((problem.n_windows, model.n_states)))
            costs[name] = float(problem.cost(theta, starts))
        finally:
            problem.close()
    return costs
