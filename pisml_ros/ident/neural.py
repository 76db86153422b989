"""Neural residual vector field and the hybrid PISML field f = Θ(x, u)Ξ + N(x, u), trained
end-to-end through an ODE solver (torchdiffeq) on trajectory windows.

- :class:`ResidualMLP`: the paper's N(x, u), 15→128→128→13, tanh, LayerNorm, optional dropout;
  inputs standardised, outputs scaled per state (so one learning rate suits states whose
  derivatives differ by 10⁴).
- :class:`HybridField`: backbone (trainable Ξ over a term library) plus the residual; either
  part may be absent (Pure NODE has no backbone).
- :func:`train_hybrid`: multiple shooting over windows that start at measured states; inputs are
  a zero-order hold of their samples inside the ODE function (input steps sit on samples, the
  solver's fixed steps never straddle one). Loss = trajectory loss + λ_pert · Jacobian
  consistency on small-signal records + λ_sparse · ‖Ξ‖₁.
- :class:`NeuralModel`: numpy-facing wrapper (vector field, Jacobian by autodiff, equilibria,
  eigenvalues, simulation, parameter count) for analysis and scoring.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from ..data import Dataset
from ..data.dataset import steady_start_mean
from ..equilibrium import find_equilibrium
from ..model.replay import replay
from ..model.expressions import term_set
from .derivatives import trajectory_windows


def _torch():
    import torch

    torch.set_default_dtype(torch.float64)
    return torch


class StopRequested(Exception):
    """Raised inside training when the caller's should_stop() says so."""


def build_modules():
    """torch module classes (defined lazily so that importing this file does not import torch)."""
    torch = _torch()
    nn = torch.nn

    class ResidualMLP(nn.Module):
        def __init__(self, n_in, n_out, hidden=(128, 128), dropout=0.0, z_mean=None, z_std=None, out_scale=None):
            super().__init__()
            layers, width = [], n_in
            for h in hidden:
                layers += [nn.Linear(width, h), nn.LayerNorm(h), nn.Tanh()]
                if dropout > 0:
                    layers.append(nn.Dropout(dropout))
                width = h
            last = nn.Linear(width, n_out)
            nn.init.zeros_(last.weight)  # starts as "no residual": the backbone alone
            nn.init.zeros_(last.bias)
            layers.append(last)
            self.net = nn.Sequential(*layers)
            self.register_buffer("z_mean", torch.as_tensor(z_mean if z_mean is not None else np.zeros(n_in)))
            self.register_buffer("z_std", torch.as_tensor(z_std if z_std is not None else np.ones(n_in)))
            self.register_buffer("out_scale", torch.as_tensor(out_scale if out_scale is not None else np.ones(n_out)))

        def forward(self, z):
            return self.net((z - self.z_mean) / self.z_std) * self.out_scale

    class HybridField(nn.Module):
        def __init__(self, terms, signals, n_states, xi0=None, mlp=None, train_xi=True):
            super().__init__()
            self.n_states = n_states
            self.terms = term_set(list(terms), list(signals)) if terms else None
            self.mlp = mlp
            if self.terms is not None:
                xi = torch.as_tensor(np.zeros((len(terms), n_states)) if xi0 is None else xi0)
                self.xi = nn.Parameter(xi.clone(), requires_grad=train_xi)
                # the sparse backbone's support is its structure: training moves the values on it,
                # never re-opens the entries STLSQ set to zero
                self.register_buffer("xi_mask", (xi != 0).to(xi.dtype) if xi0 is not None else torch.ones_like(xi))
            else:
                self.xi = None
            self.u_seq = None  # (batch, n_samples, n_inputs) of the windows being integrated
            self.dt = 1.0

        def field(self, x, u):
            z = torch.cat([x, u], dim=-1)
            out = 0.0
            if self.terms is not None:
                out = self.terms.evaluate_torch(z) @ self.coefficients()
            if self.mlp is not None:
                out = out + self.mlp(z)
            return out

        def coefficients(self):
            """Ξ on its support (the backbone's nonzero pattern)."""
            return self.xi * self.xi_mask

        def forward(self, t, x):
            k = int(min(max(float(t) / self.dt + 1e-6, 0.0), self.u_seq.shape[1] - 2))
            return self.field(x, self.u_seq[:, k])

    return ResidualMLP, HybridField


@dataclasses.dataclass
class TrainingHistory:
    epochs: list = dataclasses.field(default_factory=list)
    trajectory_loss: list = dataclasses.field(default_factory=list)
    jacobian_loss: list = dataclasses.field(default_factory=list)
    sparse_loss: list = dataclasses.field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def smallsignal_pairs(smallsignal: Dataset | None, span: int = 10):
    """Per small-signal record: its pre-step steady state and integral-form deviation pairs.

    Returns a list of ``(x_eq, u_eq, dx_increment, int_dx, int_du, duration)`` (numpy); records
    without a steady start are skipped.
    """
    pairs = []
    if smallsignal is None:
        return pairs
    for tr in smallsignal:
        k0, x_eq = steady_start_mean(tr)
        if x_eq is None or k0 >= len(tr) - span:
            continue
        u_eq = tr.u[0].copy()
        dx, du = tr.x - x_eq, tr.u - u_eq
        steps = np.diff(tr.t)[:, None]
        # inputs are a zero-order hold: the left sample holds over each step
        cum_x = np.concatenate([np.zeros((1, dx.shape[1])), np.cumsum(0.5 * (dx[1:] + dx[:-1]) * steps, 0)])
        cum_u = np.concatenate([np.zeros((1, du.shape[1])), np.cumsum(du[:-1] * steps, 0)])
        starts = np.arange(max(k0 - span, 0), len(tr) - span)
        pairs.append((x_eq, u_eq, dx[starts + span] - dx[starts], cum_x[starts + span] - cum_x[starts],
                      cum_u[starts + span] - cum_u[starts], float(tr.t[starts[0] + span] - tr.t[starts[0]])))
    return pairs


def train_hybrid(field, train: Dataset, smallsignal: Dataset | None, *, epochs: int, window: int,
                 batch_windows: int, learning_rate: float, lambda_pert: float, lambda_sparse: float,
                 solver: str = "rk4", substeps: int = 2, adjoint: bool = False, seed: int = 0,
                 state_scale=None, callback: Callable | None = None,
                 should_stop: Callable[[], bool] | None = None, device: str = "cpu",
                 weight_decay: float = 0.0, lr_schedule: str = "cosine", full_passes: bool = False) -> TrainingHistory:
    """Train ``field`` (a HybridField) through torchdiffeq on windows of ``train``.

    Parameters
    ----------
    state_scale : ndarray, shape (n_states,)
        Per-state scale of the trajectory residuals (noise level or signal spread).
    callback : callable(epoch, losses: dict)
        Called after every epoch.
    should_stop : callable() -> bool
        Polled every epoch; raises :class:`StopRequested` when it returns True.
    device : str
        torch device to train on (``cpu``, ``cuda``, ``cuda:1``, ...); the field is back on the
        CPU when this returns (or raises).
    weight_decay : float
        AdamW's decoupled weight decay of the network's parameters (Ξ gets none: it has the L1 term).
    lr_schedule : {"cosine", "onecycle"}
        Cosine annealing from ``learning_rate`` to 5 % of it, or torch's OneCycleLR peaking at
        ``learning_rate`` (the paper's).
    full_passes : bool
        An epoch is a pass over every window in shuffled batches of ``batch_windows`` (the
        paper's epochs), not one batch of them drawn at random; the schedule steps per batch.
    """
    torch = _torch()
    import torchdiffeq

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    xw, uw = trajectory_windows(train, window, stride=max(window // 2, 1))
    device = torch.device(device)
    X, U = torch.as_tensor(xw, device=device), torch.as_tensor(uw, device=device)
    dt = float(train.dt)
    field.dt = dt
    t_grid = torch.arange(window + 1, dtype=torch.float64, device=device) * dt
    scale_np = np.asarray(state_scale if state_scale is not None else xw.reshape(-1, xw.shape[-1]).std(axis=0) + 1e-9)
    scale = torch.as_tensor(scale_np, device=device)
    ss = [tuple(torch.as_tensor(a, device=device) if isinstance(a, np.ndarray) else a for a in p)
          for p in smallsignal_pairs(smallsignal)]
    params = [p for p in field.parameters() if p.requires_grad]
    history = TrainingHistory()
    if not params:
        return history
    field.to(device)
    try:
        batches_per_epoch = -(-X.shape[0] // batch_windows) if full_passes else 1
        opt, sched = optimiser(field, learning_rate, weight_decay, lr_schedule, epochs * batches_per_epoch)
        integrate = torchdiffeq.odeint_adjoint if adjoint else torchdiffeq.odeint
        options = {"step_size": dt / substeps} if solver in ("rk4", "euler", "midpoint") else None
        xi_scale = None
        if field.xi is not None:
            # ‖Ξ‖₁ on a common scale: each coefficient times its term's typical size over the state's scale
            theta = field.terms.evaluate(np.concatenate([xw.reshape(-1, xw.shape[-1]), uw.reshape(-1, uw.shape[-1])], 1))
            xi_scale = torch.as_tensor(np.abs(theta).mean(axis=0)[:, None] * dt / scale_np[None, :], device=device)
        kwargs = {"method": solver, "options": options} if options else {"method": solver, "rtol": 1e-6, "atol": 1e-8}
        if adjoint:
            kwargs["adjoint_params"] = tuple(params)

        def step(batch):
            """One optimiser step on the windows ``batch``: (trajectory, Jacobian, sparse) losses."""
            xb, ub = X[batch], U[batch]
            field.u_seq = ub
            pred = integrate(field, xb[:, 0], t_grid, **kwargs)  # (window+1, batch, n)
            traj = torch.mean(((pred.transpose(0, 1) - xb) / scale) ** 2)
            loss = traj
            jac_loss = torch.zeros((), device=device)
            if lambda_pert > 0 and ss:
                for x_eq, u_eq, inc, int_dx, int_du, span_t in ss:
                    fx = torch.func.jacrev(lambda x: field.field(x[None], u_eq[None])[0])(x_eq)
                    fu = torch.func.jacrev(lambda u: field.field(x_eq[None], u[None])[0])(u_eq)
                    f0 = field.field(x_eq[None], u_eq[None])[0]
                    pred_inc = span_t * f0 + int_dx @ fx.T + int_du @ fu.T
                    # on the scale of the record's own increments: 1 % steps are tiny next to the state spread
                    jac_loss = jac_loss + torch.mean(((pred_inc - inc) / (inc.std(dim=0) + 1e-12)) ** 2) / len(ss)
                loss = loss + lambda_pert * jac_loss
            sparse = torch.zeros((), device=device)
            if lambda_sparse > 0 and xi_scale is not None:
                sparse = torch.sum(torch.abs(field.coefficients()) * xi_scale)
                loss = loss + lambda_sparse * sparse
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 10.0)
            opt.step()
            sched.step()
            return float(traj.detach()), float(jac_loss.detach()), float(sparse.detach())

        started = time.monotonic()
        field.train()
        n_windows = X.shape[0]
        for epoch in range(epochs):
            if should_stop is not None and should_stop():
                raise StopRequested()
            if full_passes:
                order = rng.permutation(n_windows)
                batches = [order[k:k + batch_windows] for k in range(0, n_windows, batch_windows)]
            else:
                batches = [rng.choice(n_windows, size=min(batch_windows, n_windows), replace=False)]
            losses = np.array([step(batch) for batch in batches])
            # an epoch's losses: the mean over its batches, each weighted by its windows
            sizes = np.array([len(batch) for batch in batches], dtype=float)
            traj, jac, sparse = (sizes @ losses) / sizes.sum()
            history.epochs.append(epoch)
            history.trajectory_loss.append(float(traj))
            history.jacobian_loss.append(float(jac))
            history.sparse_loss.append(float(sparse))
            if callback is not None:
                callback(epoch, {"trajectory": history.trajectory_loss[-1], "jacobian": history.jacobian_loss[-1], "sparse": history.sparse_loss[-1]})
        field.eval()
        history.seconds = time.monotonic() - started
    finally:
        field.u_seq = None
        field.to("cpu")
    return history


def optimiser(field, learning_rate: float, weight_decay: float, lr_schedule: str, steps: int):
    """AdamW over ``field``'s trainable parameters and its learning-rate schedule over ``steps``
    optimiser steps (the scheduler steps with the optimiser).

    The network's parameters decay by ``weight_decay`` (decoupled, AdamW); the backbone's Ξ does
    not (the L1 term is its regulariser, and a decay would shrink the physics coefficients). With
    ``weight_decay`` 0 this is Adam. ``lr_schedule``: ``"cosine"`` anneals from ``learning_rate``
    to 5 % of it, ``"onecycle"`` is torch's OneCycleLR peaking at ``learning_rate`` (the paper's).

    Returns
    -------
    (torch.optim.AdamW, torch.optim.lr_scheduler.LRScheduler)
    """
    torch = _torch()
    params = [p for p in field.parameters() if p.requires_grad]
    network = [p for p in params if field.xi is None or p is not field.xi]
    groups = [{"params": network, "weight_decay": weight_decay}]
    if len(network) < len(params):
        groups.append({"params": [field.xi], "weight_decay": 0.0})
    opt = torch.optim.AdamW(groups, lr=learning_rate)
    if lr_schedule == "onecycle":
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=learning_rate, total_steps=steps)
    elif lr_schedule == "cosine":
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps, eta_min=learning_rate * 0.05)
    else:
        raise ValueError(f"lr_schedule must be cosine or onecycle, got {lr_schedule!r}")
    return opt, sched


def resolve_device(name: str) -> str:
    """``auto`` → ``cuda`` where torch sees a GPU, else ``cpu``; other names are checked."""
    torch = _torch()
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device {name!r}: {err}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r}: torch sees no CUDA GPU here (use cpu or auto)")
    return name


class NeuralModel:
    """A trained (hybrid or pure) neural vector field behind the numpy model interface.

    Parameters
    ----------
    field : HybridField
    state_names, input_names : sequence of str
    reference_points : list of dict
        ``{"inputs": [...], "state": [...]}`` where equilibrium searches start.
    backbone : ExplicitModel or None
        The explicit part (for display; the field holds the trained Ξ).
    """

    def __init__(self, field, state_names, input_names, reference_points=(), backbone=None, kind="hybrid"):
        self.field = field
        self.state_names = tuple(state_names)
        self.input_names = tuple(input_names)
        self.reference_points = list(reference_points)
        self.backbone = backbone
        self.kind = kind
        self.metadata = {"method": kind, "reference_points": self.reference_points}

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    @property
    def n_parameters(self) -> int:
        """Trainable parameters: network weights plus nonzero backbone coefficients."""
        n = 0
        if self.field.mlp is not None:
            n += sum(p.numel() for p in self.field.mlp.parameters())
        if self.field.xi is not None:
            n += int(np.count_nonzero(self.field.coefficients().detach().numpy()))
        return n

    def vector_field(self, x, u) -> np.ndarray:
        torch = _torch()
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        xt = torch.as_tensor(np.broadcast_to(x, lead + x.shape[-1:]).reshape(-1, x.shape[-1]).copy())
        ut = torch.as_tensor(np.broadcast_to(u, lead + u.shape[-1:]).reshape(-1, u.shape[-1]).copy())
        with torch.no_grad():
            out = self.field.field(xt, ut).numpy()
        return out.reshape(lead + (self.n_states,))

    def residual(self, x, u) -> np.ndarray:
        """N(x, u) alone (zeros for a model without a network)."""
        torch = _torch()
        if self.field.mlp is None:
            return np.zeros(np.shape(x))
        with torch.no_grad():
            return self.field.mlp(torch.as_tensor(np.concatenate([x, u], axis=-1))).numpy()

    def jacobian(self, x, u, wrt: str = "x") -> np.ndarray:
        torch = _torch()
        xt = torch.as_tensor(np.asarray(x, dtype=float))
        ut = torch.as_tensor(np.asarray(u, dtype=float))
        if wrt == "x":
            jac = torch.func.jacrev(lambda y: self.field.field(y[None], ut[None])[0])(xt)
        else:
            jac = torch.func.jacrev(lambda v: self.field.field(xt[None], v[None])[0])(ut)
        return jac.detach().numpy()

    def equilibrium(self, *inputs: float, x0=None, tol: float = 1e-8) -> np.ndarray:
        return find_equilibrium(self.vector_field, self.jacobian, inputs, self.reference_points, x0=x0, tol=tol,
                                what=f"{self.kind} model")

    def eigenvalues(self, *inputs: float) -> np.ndarray:
        return np.linalg.eigvals(self.jacobian(self.equilibrium(*inputs), np.array(inputs, dtype=float)))

    def simulate(self, dataset: Dataset, substeps: int = 4, method: str = "rk4") -> Dataset:
        """Replay each trajectory's measured inputs from its measured initial state."""
        return replay(self, dataset, substeps=substeps, method=method)
