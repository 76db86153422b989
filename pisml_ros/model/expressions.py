"""Term expressions: safe parsing (no eval of arbitrary code) and compilation to numpy and torch.

A term is a sympy-parsable expression string over named signals, e.g.
``"vc_d*ig_d + vc_q*ig_q"`` or ``"ug*cos(theta_g - delta)"``. Parsing checks the
Python syntax tree against a whitelist (names of the signals, numbers, + - * /
**, and the functions below) before sympy sees the string, so loading a model
file never executes code from it.
"""
from __future__ import annotations

import ast
from functools import lru_cache
from typing import Sequence

import numpy as np
import sympy

#: functions a term may call (DESIGN.md, explicit model JSON)
ALLOWED_FUNCTIONS = {
    "sin": sympy.sin, "cos": sympy.cos, "exp": sympy.exp, "tanh": sympy.tanh, "sqrt": sympy.sqrt,
    "Abs": sympy.Abs, "Min": sympy.Min, "Max": sympy.Max, "sign": sympy.sign,
}
_ALLOWED_NODES = (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Call, ast.Name, ast.Load, ast.Constant,
                  ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd)


class ExpressionError(ValueError):
    """A term that is not a whitelisted expression over the known signals."""


def parse_term(text: str, names: Sequence[str]) -> sympy.Expr:
    """Parse one term string into a sympy expression, with a syntax whitelist.

    Raises
    ------
    ExpressionError
        Unknown names, disallowed syntax (attributes, subscripts, lambdas, ...), bad numbers.
    """
    if not isinstance(text, str) or not text.strip():
        raise ExpressionError(f"term {text!r}: expected a non-empty expression string")
    if len(text) > 2000:
        raise ExpressionError(f"term {text[:40]!r}...: longer than 2000 characters")
    tree = _syntax_tree(text)
    known = set(names)
    for node in ast.walk(tree):
        if not isinstance(node, _ALLOWED_NODES):
            raise ExpressionError(f"term {text!r}: {type(node).__name__} is not allowed")
        if isinstance(node, ast.Constant) and not isinstance(node.value, (int, float)) or \
                isinstance(node, ast.Constant) and isinstance(node.value, bool):
            raise ExpressionError(f"term {text!r}: only numeric constants are allowed")
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in ALLOWED_FUNCTIONS or node.keywords:
                raise ExpressionError(f"term {text!r}: only calls of {sorted(ALLOWED_FUNCTIONS)} are allowed")
        elif isinstance(node, ast.Name) and node.id not in known and node.id not in ALLOWED_FUNCTIONS:
            raise ExpressionError(f"term {text!r}: unknown signal {node.id!r} (known: {sorted(known)})")
    symbols = {name: sympy.Symbol(name, real=True) for name in names}
    return _to_sympy(tree.body, symbols)


def _syntax_tree(text: str) -> ast.Expression:
    """Python's syntax tree of a term (not evaluated), or ExpressionError where it is not an expression."""
    try:
        return ast.parse(str(text).strip(), mode="eval")
    except SyntaxError as err:
        raise ExpressionError(f"term {text!r}: not an expression ({err.msg})") from None


def written_numbers(text: str) -> set:
    """The magnitudes of the decimal numbers written in a term (``1.2``, ``-0.5``, ``2.0``; not the
    integers of its structure, ``**2`` or ``Min(1, …)``): what was fitted into the term. A number
    and its negative are one (a clamp's −m and m).

    Raises
    ------
    ExpressionError
        ``text`` is not an expression.
    """
    return {abs(node.value) for node in ast.walk(_syntax_tree(text))
            if isinstance(node, ast.Constant) and isinstance(node.value, float)}


_BINOPS = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b, ast.Mult: lambda a, b: a * b,
           ast.Div: lambda a, b: a / b, ast.Pow: lambda a, b: a ** b}


def _to_sympy(node, symbols):
    """Build the sympy expression from the checked tree (no eval)."""
    if isinstance(node, ast.BinOp):
        return _BINOPS[type(node.op)](_to_sympy(node.left, symbols), _to_sympy(node.right, symbols))
    if isinstance(node, ast.UnaryOp):
        value = _to_sympy(node.operand, symbols)
        return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, ast.Call):
        return ALLOWED_FUNCTIONS[node.func.id](*[_to_sympy(arg, symbols) for arg in node.args])
    if isinstance(node, ast.Name):
        return symbols[node.id]
    if isinstance(node, ast.Constant):
        return sympy.Float(node.value) if isinstance(node.value, float) else sympy.Integer(node.value)
    raise ExpressionError(f"unsupported syntax {type(node).__name__}")


def _torch_module():
    """The functions sympy's printer may call in compiled terms, as torch functions that also take
    plain numbers: the generated code passes them as they are written (``sqrt(2)*x`` calls sqrt
    on 2, ``Min(x, 1)`` passes 1), which torch's functions reject."""
    import torch

    def numeric(fn):
        def apply(*args):
            if all(torch.is_tensor(a) for a in args):
                return fn(*args)
            like = next((a for a in args if torch.is_tensor(a)), None)
            if like is None:  # constants only: a plain number, as the generated code expects
                return fn(*(torch.tensor(float(a), dtype=torch.float64) for a in args)).item()
            return fn(*(a if torch.is_tensor(a) else torch.tensor(float(a), dtype=like.dtype, device=like.device)
                        for a in args))

        return apply

    def bound(fn, clamp_side):
        # a limiter term's Min(1, x) / Max(-1, x): clamp takes the plain bound as it is, where
        # minimum / maximum would need a new constant tensor each call (stop 89, scratch: 119 -> 107
        # us a rate call of a limit model on 48 rows, the values equal to the bit)
        general = numeric(fn)

        def apply(*args):
            if len(args) == 2:
                tensors = [torch.is_tensor(a) for a in args]
                if tensors[0] != tensors[1]:
                    x, c = (args[0], args[1]) if tensors[0] else (args[1], args[0])
                    return torch.clamp(x, **{clamp_side: float(c)})
            return general(*args)

        return apply

    functions = {name: numeric(fn) for name, fn in (
        ("sin", torch.sin), ("cos", torch.cos), ("exp", torch.exp), ("tanh", torch.tanh), ("sqrt", torch.sqrt),
        ("Abs", torch.abs), ("sign", torch.sign), (_STEP.__name__, _step))}
    functions.update(Min=bound(torch.minimum, "max"), Max=bound(torch.maximum, "min"))
    return functions


def _step(x, at_zero=0.5):
    """sympy's Heaviside for tensors (the derivative of a Min or Max: a limiter term's)."""
    import torch

    return torch.where(x > 0, 1.0, torch.where(x < 0, 0.0, at_zero)).to(x.dtype)


#: stands in for Heaviside in torch code: sympy's printer writes Heaviside as a Python branch,
#: which runs on one number, not on a batch of rows
_STEP = sympy.Function("heaviside_step")


def _lambdify_torch(symbols, exprs):
    """``sympy.lambdify`` of ``exprs`` (an expression or a list) for torch tensors, Heaviside included."""
    def tensor_friendly(e):
        return e.replace(sympy.Heaviside, _STEP) if isinstance(e, sympy.Basic) and e.has(sympy.Heaviside) else e

    exprs = [tensor_friendly(e) for e in exprs] if isinstance(exprs, (list, tuple)) else tensor_friendly(exprs)
    return sympy.lambdify(symbols, exprs, modules=[_torch_module(), "math"], cse=True)


class TermSet:
    """A list of terms over named signals, compiled for fast evaluation.

    Parameters
    ----------
    terms : sequence of str
    signals : sequence of str
        Names the terms may use, in the column order of the arrays passed to
        :meth:`evaluate` (states first, then inputs).
    """

    def __init__(self, terms: Sequence[str], signals: Sequence[str]):
        self.terms = list(terms)
        self.signals = list(signals)
        self.exprs = [parse_term(t, self.signals) for t in self.terms]
        self._symbols = [sympy.Symbol(n, real=True) for n in self.signals]
        self._numpy = None
        self._numpy_gather = None
        self._torch = None
        self._plan = None
        self._grad_plan = None
        self._jacobian_plans = {}
        self._factors = None
        self._grad = None
        self._grad_symbolic = None
        self._derivative_exprs = None
        self._splits = {}  # state count -> :meth:`_split_plan`'s plan
        self._ones_cache = {}

    def __len__(self):
        return len(self.terms)

    def evaluate(self, z: np.ndarray) -> np.ndarray:
        """Term values for signal rows ``z`` (..., n_signals) -> (..., n_terms)."""
        z = np.asarray(z, dtype=float)
        if z.ndim > 1 and self._numpy_plan():
            return self._gathered_numpy(z)
        if self._numpy is None:
            self._numpy = sympy.lambdify(self._symbols, self.exprs, modules="numpy", cse=True)
        cols = self._numpy(*np.moveaxis(z, -1, 0))
        if z.ndim == 1:  # one point (equilibrium searches): scalars, no broadcasting needed
            return np.array(cols, dtype=float)
        # assignment broadcasts constant terms; np.stack of broadcast_to copies cost ~3x more (measured:
        # it was half of every simulation's time)
        out = np.empty(z.shape[:-1] + (len(cols),))
        for k, c in enumerate(cols):
            out[..., k] = c
        return out

    def _numpy_plan(self) -> bool:
        """Compile the product plan for numpy once (:meth:`_torch_plan`'s, over numpy arrays); False
        when the terms are not all products of factors."""
        if self._numpy_gather is None:
            layout = self._plan_layout()
            if layout is None:
                self._numpy_gather = False
            else:
                others, index = layout
                fn = sympy.lambdify(self._symbols, others, modules="numpy", cse=True) if others else None
                self._numpy_gather = (fn, len(others), index)
        return self._numpy_gather is not False

    def _gathered_numpy(self, z: np.ndarray) -> np.ndarray:
        """:meth:`evaluate` by the product plan: ``[1, signals, other factors]`` once, then each
        term's factors gathered and multiplied. A free run calls the vector field some twenty
        thousand times on a few dozen rows; per call this is ~19 µs where a generated function's
        column per term is ~33 µs (measured on a 31-term 40 dB model, 48 rows). The products are
        the generated function's own for terms of degree up to 2 (the same values to the bit)."""
        fn, n_others, index = self._numpy_gather
        n_signals = z.shape[-1]
        base = np.empty(z.shape[:-1] + (1 + n_signals + n_others,))
        base[..., 0] = 1.0
        base[..., 1:1 + n_signals] = z
        if fn is not None:
            for k, column in enumerate(fn(*np.moveaxis(z, -1, 0))):
                base[..., 1 + n_signals + k] = column
        factors = base[..., index]
        if index.shape[1] == 1:
            return factors[..., 0]
        if index.shape[1] == 2:
            return factors[..., 0] * factors[..., 1]
        return factors.prod(axis=-1)

    def _product_plan(self, whole_terms: bool = False):
        """Every term as a product of factors (signals or non-polynomial sub-expressions such as
        cos(theta_g - delta)) with positive integer powers, or None when a term is not of that form;
        with ``whole_terms`` such a term (a sum, p = vd·id + vq·iq; a quotient) is a factor of its own.

        Returns (factor expressions, index matrix n_terms × max_degree into [1, factors...]).
        """
        factors: list = []
        rows = []
        for expr in self.exprs:
            powers = _factor_powers(expr)
            if powers is None:
                if not whole_terms:
                    return None
                powers = [(expr, 1)]
            row = []
            for base, power in powers:
                if base not in factors:
                    factors.append(base)
                row += [factors.index(base) + 1] * power
            rows.append(row)
        width = max((len(r) for r in rows), default=0) or 1
        return factors, np.array([r + [0] * (width - len(r)) for r in rows], dtype=np.int64)

    def evaluate_torch(self, z):
        """Term values of a torch tensor (..., n_signals) -> (..., n_terms), differentiable.

        Products of signals (the libraries are mostly monomials) are gathered and multiplied in
        one tensor operation; this keeps training through the ODE solver fast.
        """
        import torch

        if self._torch_plan():
            return self._gathered(self._factor_base(z)).prod(dim=-1)
        if self._torch is None:
            self._torch = _lambdify_torch(self._symbols, self.exprs)
        cols = self._torch(*z.unbind(-1))
        return torch.stack([_column(c, z) for c in cols], dim=-1)

    def evaluate_split_torch(self, y, u):
        """:meth:`evaluate_torch` of ``torch.cat([y, u], dim=-1)`` for rows ``y`` (points, n_states)
        and ``u`` (points, n_inputs) without building that tensor: the same values to the bit, as a
        (points, n_terms) view of a term-major table.

        The refinement's passes evaluate the terms at every RK4 stage of every sample on small
        batches, where each operation counts. Here the base ``[1, signals, other factors]`` is laid
        out a signal per row, so that gathering each term's factors copies whole rows (a gather
        along the last axis was most of a call: measured 580 against 268 us for 480 points of 92
        terms, 126 against 102 us for 48 points of 29); the ones come from a cache and the other
        factors (cos and sin of the grid angle) are computed from the signals they use alone.
        """
        import torch

        if y.dim() != 2:
            return self.evaluate_torch(torch.cat([y, u], dim=-1))
        fn, used, n_states, index, affine = self._split_plan(y.shape[-1], y.device)
        cols = [self._ones(y), y.T, u.T]
        if fn is not None:
            values = fn(*[y[:, i] if i < n_states else u[:, i - n_states] for i in used],
                        *(() if affine is None else _affine_rows(affine, y, u, n_states)))
            cols.append(torch.stack([_column(v, y) for v in values]))
        base = torch.cat(cols)
        return torch.index_select(base, 0, index.view(-1)).view(index.shape + (y.shape[0],)).prod(dim=1).T

    def _split_plan(self, n_states: int, device):
        """:meth:`evaluate_split_torch`'s function of the other factors over the signals they use,
        those signals' positions and the plan's index on ``device`` (compiled once per state count).

        Its plan takes a term that is not a product of factors as a factor of its own
        (:meth:`_product_plan`'s ``whole_terms``), computed by the generated function as the term
        itself was, without a generated function's column per term for every term where one of them
        is a sum (the same values, to the bit but where that function's common subexpressions group
        a product of three factors otherwise). That call was a third of the saturation plant's
        limiter family, whose models keep p and q as sums (measured, stop 87: `bench/fit_time.py
        --plant saturation --seed 0 --noise 40` under py-spy, 35 % of the family's samples).

        The affine combinations of three or more signals in the other factors (a limiter's
        reference ℓ, :mod:`pisml_ros.ident.limiter`: ~10 signals, and again inside |ℓ|) come from
        one matrix product instead of an operation per signal (:func:`_affine_parts`). Forward
        values only: the training's autograd keeps :meth:`evaluate_torch` as it is.
        """
        import torch

        # a plan per state count, each built and stored whole: the shooting windows' threads call this
        # at once, and a single slot rebuilt for another count was read half-replaced (stop 92)
        split = self._splits.get(n_states)
        if split is None:
            others, index = self._plan_layout(whole_terms=True)
            parts = _affine_parts(others)
            names = [sympy.Dummy(f"affine{k}") for k in range(len(parts))]
            others = [f.xreplace(dict(zip(parts, names))) for f in others]
            used = sorted({self._symbols.index(s) for f in others for s in f.free_symbols if s in self._symbols})
            fn = _lambdify_torch([self._symbols[i] for i in used] + names, others) if others else None
            affine = None
            if parts:  # (rows: the parts; columns: 1, then the signals)
                table = [[float(p.coeff(s)) if s in p.free_symbols else 0.0 for s in self._symbols] for p in parts]
                offset = [float(p.as_coeff_Add()[0]) for p in parts]
                affine = torch.tensor([[b, *row] for b, row in zip(offset, table)], dtype=torch.float64)
            split = self._splits[n_states] = (fn, used, n_states, torch.as_tensor(index), affine)
        if split[3].device != device:  # (moved once: training on an accelerator)
            split = self._splits[n_states] = (*split[:3], split[3].to(device),
                                              None if split[4] is None else split[4].to(device))
        return split

    def _ones(self, y):
        """A row of ones, one per row of ``y`` (cached per count, type and device; never written to)."""
        import torch

        key = (y.shape[0], y.dtype, y.device)
        ones = self._ones_cache.get(key)
        if ones is None:
            if len(self._ones_cache) > 32:  # (a few window counts a fit; never more than a handful)
                self._ones_cache.clear()
            ones = self._ones_cache[key] = torch.ones((1, y.shape[0]), dtype=y.dtype, device=y.device)
        return ones

    def thread_safe_gradient(self) -> bool:
        """Whether :meth:`gradient_torch` is plain tensor operations (the product rule, or the terms'
        sympy derivatives), which threads may run side by side; else it is forward-mode autodiff,
        whose levels belong to one thread."""
        return self._torch_plan() or self._symbolic_gradient_torch() is not False

    def _symbolic_gradient_torch(self):
        """The terms' sympy derivatives compiled for torch, as a function of ``z`` (..., n_signals)
        -> (..., n_terms, n_signals), or False where they use a function torch lacks here (sympy's
        Heaviside of a Min, say).

        Most entries are constants (a term's derivative in a signal it lacks is 0), filled from a
        fixed table (:func:`_entries_torch`). Filling every entry per call was half of a
        refinement pass over long windows for a term set without a product plan (measured: 1.13
        of 2.30 s per Gauss-Newton step, windows of 50, a 24-term distilled model with p and q).
        """
        if self._grad_symbolic is None:
            gradient = _entries_torch(self._derivatives(), self._symbols)
            self._grad_symbolic = gradient if _runs_on_rows(gradient, len(self.signals)) else False
        return self._grad_symbolic

    def _derivatives(self) -> list:
        """d term / d signal as sympy expressions, (n_terms × n_signals), derived once."""
        if self._derivative_exprs is None:
            self._derivative_exprs = [[sympy.diff(e, s) for s in self._symbols] for e in self.exprs]
        return self._derivative_exprs

    def _plan_layout(self, whole_terms: bool = False):
        """The product plan over the base ``[1, every signal, the other factors]``: (the factors that
        are not plain signals, the index matrix n_terms × max_degree into the base), or None when
        the terms are not all products of factors (``whole_terms``: :meth:`_product_plan`'s). The
        signals go into the base as one block, not a generated function's column each (the
        refinement's state pass and the free runs evaluate the terms at every RK4 stage on small
        batches, where each operation launched counts)."""
        plan = self._product_plan(whole_terms)
        if plan is None:
            return None
        factors, index = plan
        others = [f for f in factors if f not in self._symbols]
        position = [0] + [1 + self._symbols.index(f) if f in self._symbols
                          else 1 + len(self._symbols) + others.index(f) for f in factors]
        return others, np.asarray(position)[index]

    def _torch_plan(self) -> bool:
        """Compile the product plan for torch once (the functions of the factors that are not plain
        signals, and the index into :meth:`_factor_base`); False when the terms are not all products
        of factors."""
        if self._plan is None:
            import torch

            layout = self._plan_layout()
            if layout is None:
                self._plan = False
            else:
                others, index = layout
                fn = _lambdify_torch(self._symbols, others) \
                    if others else None
                self._plan = (fn, torch.as_tensor(index))
                self._factors = list(self._symbols) + others  # the base's entries, for :meth:`gradient_torch`
        return self._plan is not False

    def _plan_index(self, device):
        """The product plan's index on ``device`` (moved there once: training on an accelerator)."""
        fn, index = self._plan
        if index.device != device:
            index = index.to(device)
            self._plan = (fn, index)
        return index

    def _factor_base(self, z):
        """``[1, signals..., other factor values...]`` of the product plan at ``z``:
        (..., 1 + n_signals + n_other_factors)."""
        import torch

        fn = self._plan[0]
        self._plan_index(z.device)
        cols = [torch.ones(z.shape[:-1] + (1,), dtype=z.dtype, device=z.device), z]
        if fn is not None:
            cols.append(torch.stack([_column(v, z) for v in fn(*z.unbind(-1))], dim=-1))
        return torch.cat(cols, dim=-1)

    def _gathered(self, base):
        """Each term's factors from :meth:`_factor_base`'s ``base``: (..., n_terms, degree)."""
        import torch

        index = self._plan[1]
        # one index_select of the flattened index (~2x quicker than base[..., index] on small batches)
        return torch.index_select(base, -1, index.view(-1)).view(base.shape[:-1] + index.shape)

    def values_and_gradient_torch(self, z):
        """:meth:`evaluate_torch` and :meth:`gradient_torch` at ``z`` in one pass (the factors once)."""
        if not self._torch_plan():
            return self.evaluate_torch(z), self.gradient_torch(z)
        base = self._factor_base(z)
        gathered = self._gathered(base)
        return gathered.prod(dim=-1), self._product_rule(z, gathered)

    def values_and_jacobian_torch(self, z, coefficients, n_states: int):
        """Term values and the Jacobian of the field f = Θ(z)·C in the first ``n_states`` signals.

        Parameters
        ----------
        z : torch.Tensor, shape (points, n_signals)
        coefficients : torch.Tensor, shape (n_terms, n_out)
            C: column j is output j's coefficients.
        n_states : int

        Returns
        -------
        values : torch.Tensor, shape (points, n_terms)
        jacobian : torch.Tensor, shape (points, n_out, n_states)
            ∂f_j / ∂z_s.

        Built without the (points, n_terms, n_signals) term gradients: the terms' derivatives in
        the states that are not constants (the other factor of a product, -ug·sin(...) of a grid
        term) are the columns of a (points, entries) table, and one product with a matrix that
        puts c[t, j] at (entry, (j, s)) sums them; the constant ones add C's fixed part. The
        refinement calls this for every RK4 stage of every sample, where building and contracting
        the full term gradients was a quarter of a Gauss-Newton pass (measured: 17.8 against 2.0 ms
        for 2048 points of an 81-coefficient model's 31 terms).
        """
        import torch

        plan = self._jacobian_plan(n_states, z.device)
        n_out = coefficients.shape[1]
        if plan is False:  # derivatives torch cannot run here: the term gradients, contracted
            values, grad = self.values_and_gradient_torch(z)
            jac = torch.mm(grad[..., :n_states].transpose(1, 2).reshape(-1, len(self)), coefficients)
            return values, jac.view(-1, n_states, n_out).transpose(1, 2)
        # the state pass's own values (evaluate_split_torch) where its plan differs: a term that is not
        # a product of factors, or affine sums (the same to rounding, and quicker)
        if self._torch_plan() and self._split_plan(n_states, z.device)[4] is None:
            values = self.evaluate_torch(z)
        else:
            values = self.evaluate_split_torch(z[:, :n_states], z[:, n_states:]).contiguous()
        return values, _contracted_plan(plan, z, coefficients)

    def input_jacobian_torch(self, z, coefficients, n_states: int):
        """The Jacobian of the field f = Θ(z)·C in the signals after the first ``n_states`` (the
        inputs), as :meth:`values_and_jacobian_torch` gives it in the states.

        Parameters
        ----------
        z : torch.Tensor, shape (points, n_signals)
        coefficients : torch.Tensor, shape (n_terms, n_out)
        n_states : int

        Returns
        -------
        torch.Tensor, shape (points, n_out, n_signals - n_states)
            ∂f_j / ∂u_s.
        """
        import torch

        width = z.shape[1] - n_states
        plan = self._jacobian_plan(z.shape[1], z.device, first=n_states)
        if plan is False:
            _, grad = self.values_and_gradient_torch(z)
            jac = torch.mm(grad[..., n_states:].transpose(1, 2).reshape(-1, len(self)), coefficients)
            return jac.view(-1, width, coefficients.shape[1]).transpose(1, 2)
        return _contracted_plan(plan, z, coefficients)

    def _jacobian_plan(self, n_states: int, device, first: int = 0):
        """:meth:`values_and_jacobian_torch`'s varying derivative entries (their terms, their
        signals counted from ``first``, their compiled expressions) and the constant ones as a
        (n_terms, n_states - first) table, for the signals ``first`` ... ``n_states - 1``; False
        where the compiled expressions fail (see :meth:`_symbolic_gradient_torch`)."""
        import torch

        key = (n_states, device) if first == 0 else (first, n_states, device)
        if key not in self._jacobian_plans:
            constant = np.zeros((len(self), n_states - first))
            varying = []
            for t, row in enumerate(self._derivatives()):
                for s, d in enumerate(row[first:n_states]):
                    if d.is_number and d.is_finite:
                        constant[t, s] = float(d)
                    else:
                        varying.append((t, s, d))
            fn = _lambdify_torch(self._symbols, [d for _, _, d in varying]) if varying else None
            if fn is not None and not _runs_on_rows(lambda z: fn(*z.unbind(-1)), len(self.signals)):
                self._jacobian_plans[key] = False
                return False
            self._jacobian_plans[key] = (
                torch.tensor([t for t, _, _ in varying], dtype=torch.long, device=device),
                torch.tensor([s for _, s, _ in varying], dtype=torch.long, device=device),
                fn, torch.as_tensor(constant, device=device))
        return self._jacobian_plans[key]

    def gradient_torch(self, z, base=None):
        """d term / d signal of a torch tensor (..., n_signals) -> (..., n_terms, n_signals).

        Products of factors by the product rule (7x faster than ``vmap(jacfwd(evaluate_torch))``
        on the refinement's batches, measured: 0.9 vs 6.9 ms for 480 rows of 31 terms); other
        terms by forward-mode autodiff.
        """
        import torch

        if not self._torch_plan():
            symbolic = self._symbolic_gradient_torch()
            if symbolic is not False:
                # the sympy derivatives: the same values as forward-mode autodiff, 3.6x faster
                # (measured: 2.2 vs 7.8 ms for 480 rows of the 24-term physics library), thread-safe
                return symbolic(z)
            jac = torch.func.jacfwd(self.evaluate_torch)
            return torch.func.vmap(jac)(z.reshape(-1, z.shape[-1])).reshape(z.shape[:-1] + (len(self), z.shape[-1]))
        base = self._factor_base(z) if base is None else base
        return self._product_rule(z, self._gathered(base))

    def _product_rule(self, z, gathered):
        """The product plan's term gradients at ``z`` from its gathered factor values
        ``gathered`` (..., n_terms, degree).

        The refinement calls this at every Runge-Kutta stage on small batches, where the time goes
        to launching tensor operations rather than to arithmetic: the varying factor derivatives are
        set in one indexed assignment and a degree-2 plan (the libraries' usual) takes the other
        factor as it is, which gives the same values as the general product of the others.
        """
        import torch

        if self._grad_plan is None:
            # the factors' derivatives, row 0 the plan's constant 1: constants (plain signals: 0 or 1)
            # from a fixed table, the rest (cos(theta_g - delta) and the like) evaluated per call
            rows = [[sympy.Integer(0)] * len(self._symbols)]
            rows += [[sympy.diff(factor, sym) for sym in self._symbols] for factor in self._factors]
            index = self._plan[1]
            self._grad_plan = (_entries_torch(rows, self._symbols), [index[:, m].contiguous()
                                                                     for m in range(index.shape[1])])
        d_factors, columns = self._grad_plan
        if columns[0].device != z.device:
            columns = [c.to(z.device) for c in columns]
            self._grad_plan = (d_factors, columns)
        d_factor = d_factors(z)
        width = len(columns)
        out = None
        for m, column in enumerate(columns):
            if width == 2:
                others = gathered[..., 1 - m]
            else:
                others = torch.cat([gathered[..., :m], gathered[..., m + 1:]], dim=-1).prod(dim=-1)
            term = others.unsqueeze(-1) * torch.index_select(d_factor, -2, column)  # 4x quicker than d_factor[..., column, :]
            out = term if out is None else out + term
        return out

    def gradient(self, z: np.ndarray) -> np.ndarray:
        """d term / d signal at rows ``z``: (..., n_terms, n_signals), from sympy derivatives."""
        if self._grad is None:
            self._grad = sympy.lambdify(self._symbols, self._derivatives(), modules="numpy", cse=True)
        z = np.asarray(z, dtype=float)
        rows = self._grad(*np.moveaxis(z, -1, 0))
        if z.ndim == 1:  # one point (Jacobians in equilibrium searches): 20x faster than broadcasting each entry
            return np.array(rows, dtype=float)
        return np.stack([np.stack([np.broadcast_to(c, z.shape[:-1]).astype(float) for c in row], axis=-1)
                         for row in rows], axis=-2)



def _contracted_plan(plan, z, coefficients):
    """The field's Jacobian (points, n_out, width) at ``z`` from a :meth:`TermSet._jacobian_plan` over
    ``width`` signals: its constant table contracted with C, plus the varying entries' values as the
    columns of one product with a matrix that puts c[t, j] at (entry, (j, s))."""
    import torch

    term_of, signal_of, fn, constant = plan
    n_out, width = coefficients.shape[1], constant.shape[1]
    jac = (coefficients.T @ constant.to(coefficients.dtype)).expand(z.shape[0], n_out, width)
    if term_of.numel():
        entries = torch.stack([_column(v, z) for v in fn(*z.unbind(-1))], dim=-1)
        weights = torch.zeros((term_of.numel(), n_out, width), dtype=coefficients.dtype, device=z.device)
        weights[torch.arange(term_of.numel(), device=z.device), :, signal_of] = coefficients[term_of]
        jac = torch.addmm(jac.reshape(z.shape[0], -1), entries, weights.view(term_of.numel(), -1))
    return jac.reshape(-1, n_out, width)

def _column(value, z):
    """A compiled expression's value at rows ``z`` (..., n_signals) as a tensor of shape z.shape[:-1]:
    a constant (a plain number from the generated code) filled out."""
    import torch

    if torch.is_tensor(value):
        return value
    return torch.full(z.shape[:-1], float(value), dtype=z.dtype, device=z.device)


def _affine_parts(factors) -> list:
    """The sums in ``factors`` (sympy expressions) that are affine in three or more signals, each
    once, outermost first: c0 + c1·s1 + c2·s2 + ... (TermSet._split_plan computes them as one
    matrix product)."""
    parts: list = []
    for factor in factors:
        for node in sympy.preorder_traversal(factor):
            if isinstance(node, sympy.Add) and node not in parts and len(node.free_symbols) >= 3 and all(
                    arg.is_number or arg.is_Symbol or (isinstance(arg, sympy.Mul) and len(arg.args) == 2
                                                       and arg.args[0].is_number and arg.args[1].is_Symbol)
                    for arg in node.args):
                parts.append(node)
    return parts


def _affine_rows(affine, y, u, n_states: int):
    """The values of :func:`_affine_parts`' sums at rows ``y``, ``u``: one row per sum, from the
    table ``affine`` (sums × [1, signals...])."""
    import torch

    table = affine.to(y.dtype)
    rows = torch.addmm(table[:, :1], table[:, 1:1 + n_states], y.T)
    return torch.addmm(rows, table[:, 1 + n_states:], u.T)


def _factor_powers(expr):
    """``[(factor, power), ...]`` of a term that is a product of factors with positive integer
    powers up to 4 (:meth:`TermSet._product_plan`), or None."""
    coeff, rest = sympy.expand(expr).as_coeff_Mul()
    if coeff != 1 or isinstance(rest, sympy.Add):
        # a product with an affine factor, such as (Pf - 0.5)*il_d, as it is written: the
        # factor's derivatives are constants like a signal's
        coeff, rest = expr.as_coeff_Mul()
        if coeff != 1 or isinstance(rest, sympy.Add):
            return None
    powers = list(rest.as_powers_dict().items()) if rest != 1 else []
    if not all(power.is_Integer and 0 < int(power) <= 4 for _, power in powers):
        return None
    return [(base, int(power)) for base, power in powers]


def _runs_on_rows(fn, n_signals: int) -> bool:
    """Whether compiled torch code ``fn(z)`` runs on a batch of rows: two rows of different signs
    (generated code with a Python branch, a Piecewise, runs on one row and fails on more)."""
    import torch

    probe = torch.tensor([[0.5] * n_signals, [-0.3] * n_signals], dtype=torch.float64)
    try:
        fn(probe)
    except Exception:  # noqa: BLE001 - any failure of the compiled code
        return False
    return True


def _entries_torch(entries, symbols):
    """A table of sympy expressions (rows × columns) compiled for torch: a function of ``z``
    (..., n_signals) -> (..., rows, columns). The constant entries sit in a fixed table and only
    the others are evaluated per call, set in one indexed assignment (the refinement calls this at
    every Runge-Kutta stage, where launching tensor operations is most of the time)."""
    import torch

    table = np.zeros((len(entries), len(entries[0]) if entries else 0))
    varying = []
    for i, row in enumerate(entries):
        for k, entry in enumerate(row):
            if entry.is_number and entry.is_finite:
                table[i, k] = float(entry)
            else:
                varying.append((i, k, entry))
    fn = _lambdify_torch(symbols, [e for _, _, e in varying]) if varying else None
    constants = torch.as_tensor(table)
    where = (torch.tensor([i for i, _, _ in varying], dtype=torch.long),
             torch.tensor([k for _, k, _ in varying], dtype=torch.long))
    placed = {}  # the table and the indices on each device (training may run on an accelerator)

    def evaluate(z):
        if z.device not in placed:
            placed[z.device] = (constants.to(z.device), tuple(w.to(z.device) for w in where))
        table_z, (rows, cols) = placed[z.device]
        out = table_z.to(z.dtype).expand(z.shape[:-1] + table_z.shape)
        if fn is None:
            return out
        out = out.clone()
        out[..., rows, cols] = torch.stack([_column(v, z).expand(z.shape[:-1]) for v in fn(*z.unbind(-1))], dim=-1)
        return out

    return evaluate


@lru_cache(maxsize=64)
def _cached_termset(terms: tuple, signals: tuple) -> TermSet:
    return TermSet(terms, signals)


def term_set(terms: Sequence[str], signals: Sequence[str]) -> TermSet:
    """A compiled TermSet, shared between models with the same terms and signals."""
    return _cached_termset(tuple(terms), tuple(signals))
