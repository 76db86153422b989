"""ExplicitModel: d(state_j)/dt = Σ_k coefficients[k, j] · terms[k], as data.

The JSON form (``"format": "pisml-explicit-model/1"``, DESIGN.md) holds the
names, the term strings and the n_terms × n_states coefficient matrix; anyone
can rebuild f(x, u) from it. Loading parses the terms with a whitelist (no eval).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import sympy

from ..data import Dataset
from ..equilibrium import EquilibriumNotFound, find_equilibrium  # noqa: F401  (re-exported by pisml_ros.model)
from ..fileio import atomic_write_text
from .replay import replay
from .expressions import ExpressionError, term_set, written_numbers

FORMAT = "pisml-explicit-model/1"


class ModelFormatError(ValueError):
    """A model file that does not follow the explicit model contract; the message says where."""


class ExplicitModel:
    """An explicit ODE model over named states and inputs.

    Parameters
    ----------
    states, inputs : sequence of str
    terms : sequence of str
        sympy-parsable expressions over the state and input names.
    coefficients : array_like, shape (n_terms, n_states)
        In 1/s: d(state_j)/dt = Σ_k coefficients[k, j] · terms[k].
    metadata : dict, optional
        Provenance, fit metrics, and ``reference_points`` (a list of
        ``{"inputs": [...], "state": [...]}``) used to start equilibrium searches.
    """

    def __init__(self, states: Sequence[str], inputs: Sequence[str], terms: Sequence[str], coefficients,
                 metadata: dict | None = None):
        self.state_names = tuple(states)
        self.input_names = tuple(inputs)
        self.terms = list(terms)
        self.coefficients = np.array(coefficients, dtype=float).reshape(len(self.terms), len(self.state_names))
        self.metadata = dict(metadata or {})
        self.hidden_state_names = ()
        self._terms = term_set(self.terms, self.state_names + self.input_names)

    # ---------------------------------------------------------------- evaluation
    @property
    def n_states(self) -> int:
        return len(self.state_names)

    @property
    def n_parameters(self) -> int:
        """Nonzero coefficients, plus the distinct numbers written inside the terms in use (a fitted
        limiter's reference and limits, :mod:`pisml_ros.ident.limiter`): fitted to the data too. A
        number and its negative count once (a clamp's −m and m are one fitted value)."""
        used = np.any(self.coefficients != 0, axis=1)
        inside = set()
        for text, keep in zip(self.terms, used):
            if keep:
                inside |= written_numbers(text)
        return int(np.count_nonzero(self.coefficients)) + len(inside)

    def _stack(self, x, u):
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        if x.shape[:-1] == u.shape[:-1]:
            # a free run's case, some hundred thousand calls a fit: the broadcasting below cost 8.5 µs
            # a call against 1.8 µs (24 rows, the same array)
            return np.concatenate([x, u], axis=-1)
        lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        return np.concatenate([np.broadcast_to(x, lead + x.shape[-1:]), np.broadcast_to(u, lead + u.shape[-1:])],
                              axis=-1)

    def features(self, x, u) -> np.ndarray:
        """Term values, shape (..., n_terms)."""
        return self._terms.evaluate(self._stack(x, u))

    def vector_field(self, x, u) -> np.ndarray:
        """dx/dt, shape (..., n_states)."""
        return self.features(x, u) @ self.coefficients

    def term_gradients(self, x, u) -> np.ndarray:
        """Derivatives of every term in every signal (states, then inputs) at one point, shape
        (n_terms, n_states + n_inputs): the Jacobian's building blocks, for sensitivities in the
        coefficients."""
        return self._terms.gradient(self._stack(x, u))

    def jacobian(self, x, u, wrt: str = "x") -> np.ndarray:
        """Analytic Jacobian (sympy derivatives of the terms) at one point."""
        grad = self.term_gradients(x, u)  # (n_terms, n_signals)
        block = grad[:, :self.n_states] if wrt == "x" else grad[:, self.n_states:]
        return self.coefficients.T @ block

    # ---------------------------------------------------------------- operating points
    def equilibrium(self, *inputs: float, x0=None, tol: float = 1e-9) -> np.ndarray:
        """Equilibrium f(x, u) = 0 at the given input values (in ``input_names`` order).

        Starts from ``x0`` or from the stored reference point whose inputs are
        nearest, then follows the inputs from there in small steps (continuation).
        """
        u = np.array(inputs, dtype=float)
        if u.shape != (len(self.input_names),):
            raise ValueError(f"equilibrium needs {len(self.input_names)} input values {self.input_names}, got {inputs}")
        refs = self.metadata.get("reference_points") or [{"inputs": u.tolist(), "state": [0.0] * self.n_states}]
        return find_equilibrium(self.vector_field, self.jacobian, u, refs, x0=x0, tol=tol,
                                scale=self.residual_scale(), what="model")

    def residual_scale(self) -> np.ndarray:
        """Each equation's size (the sum of its coefficients' magnitudes, at least 1): what a root's
        residual is measured against."""
        return np.maximum(np.abs(self.coefficients).sum(axis=0), 1.0)

    def other_equilibria(self, inputs, x, tol: float = 1e-9) -> list | None:
        """Equilibria at ``inputs`` other than ``x`` (the one :meth:`equilibrium` follows from the
        nearest rest states), found from every stored rest state (``metadata["reference_points"]``)
        without following the inputs, within the rest states' span widened by its width on each
        side; None for a model without rest states.

        A model can have a second equilibrium close to the first near a fold of its own (stop 52,
        protocol recording 7 at 40 dB, ug 1.2: the branch followed from the records stable at
        -0.246 1/s, another 0.066 away in state, unstable at +0.207 1/s): which one a system sits at
        then depends on its history.
        """
        from ..equilibrium import distinct_roots

        refs = self.metadata.get("reference_points")
        if not refs:
            return None
        states = np.array([r["state"] for r in refs], dtype=float)
        width = np.maximum(states.max(axis=0) - states.min(axis=0), 0.1)
        return distinct_roots(self.vector_field, self.jacobian, inputs, states, known=[x],
                              box=(states.min(axis=0) - width, states.max(axis=0) + width), tol=tol,
                              scale=self.residual_scale())

    def eigenvalues(self, *inputs: float) -> np.ndarray:
        """Eigenvalues (1/s) at the equilibrium for the given inputs."""
        return np.linalg.eigvals(self.jacobian(self.equilibrium(*inputs), np.array(inputs, dtype=float)))

    # ---------------------------------------------------------------- simulation
    def simulate(self, dataset: Dataset, substeps: int = 4, method: str = "rk4") -> Dataset:
        """Replay each trajectory's measured inputs from its measured initial state.

        Returns
        -------
        Dataset
            Predicted states on the same time grid (non-finite after a divergence).
        """
        return replay(self, dataset, substeps=substeps, method=method)

    # ---------------------------------------------------------------- symbolic views
    def equations(self, digits: int = 6, threshold: float = 0.0, names: dict | None = None) -> list[str]:
        """Readable equations, one per state: ``d(x)/dt = c1*term1 + ...``.

        ``names`` ({term: name}) writes a name in place of a long term (the caller defines the
        names, e.g. :func:`~pisml_ros.ident.limiter.readable_equations`); without it every
        equation is complete in itself, as the JSON's ``equations`` are."""
        names = names or {}
        lines = []
        for j, name in enumerate(self.state_names):
            parts = []
            for k, term in enumerate(self.terms):
                c = self.coefficients[k, j]
                if c == 0 or abs(c) <= threshold:
                    continue
                coef = f"{c:.{digits}g}"
                term = names.get(term, term)
                parts.append(coef if term == "1" else f"{coef}*({term})" if any(ch in term for ch in "+- ")
                             else f"{coef}*{term}")
            rhs = " + ".join(parts).replace("+ -", "- ") or "0"
            lines.append(f"d({name})/dt = {rhs}")
        return lines

    def sympy_equations(self) -> list[sympy.Expr]:
        """The right-hand sides as sympy expressions."""
        exprs = self._terms.exprs
        return [sum((sympy.Float(self.coefficients[k, j]) * exprs[k] for k in range(len(exprs))
                     if self.coefficients[k, j] != 0), sympy.Integer(0)) for j in range(self.n_states)]

    def latex(self, digits: int = 4) -> list[str]:
        """LaTeX of each equation."""
        out = []
        for name, rhs in zip(self.state_names, self.sympy_equations()):
            rhs = rhs.xreplace({f: sympy.Float(f, digits) for f in rhs.atoms(sympy.Float)})
            out.append(rf"\dot{{{sympy.latex(sympy.Symbol(name))}}} = {sympy.latex(rhs)}")
        return out

    def monomial_count(self) -> int:
        """Nonzero coefficients when the equations are expanded into monomials."""
        count = 0
        for rhs in self.sympy_equations():
            expanded = sympy.expand(rhs)
            count += len(expanded.as_ordered_terms()) if expanded != 0 else 0
        return count

    def alternatives(self, source: str = "model") -> list:
        """The candidates of the fit that reproduced its records about as well as this model
        (``metadata["alternatives"]``, written by the identification's selection: name, training
        error, the terms each uses and their coefficients), as ``(name, ExplicitModel)`` pairs over
        this model's states and inputs; ``[]`` where the metadata hold none.

        Raises
        ------
        ModelFormatError
            For an entry that cannot be rebuilt, named ``<source>: metadata.alternatives[k]``.
        """
        entries = self.metadata.get("alternatives") or []
        if not isinstance(entries, list):
            raise ModelFormatError(f"{source}: metadata.alternatives must be a list, got {type(entries).__name__}")
        out = []
        for k, entry in enumerate(entries):
            where = f"{source}: metadata.alternatives[{k}]"
            if not isinstance(entry, dict) or "terms" not in entry or "coefficients" not in entry:
                raise ModelFormatError(f"{where}: expected an object with terms and coefficients")
            data = {"format": FORMAT, "states": list(self.state_names), "inputs": list(self.input_names),
                    "terms": entry["terms"], "coefficients": entry["coefficients"] or np.zeros((0, self.n_states)),
                    # where to start its equilibrium searches: the chosen model's rest points
                    "metadata": {"reference_points": self.metadata.get("reference_points") or []}}
            out.append((str(entry.get("name", f"alternative {k}")), ExplicitModel.from_dict(data, source=where)))
        return out

    # ---------------------------------------------------------------- JSON
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "states": list(self.state_names),
            "inputs": list(self.input_names),
            "terms": list(self.terms),
            "coefficients": self.coefficients.tolist(),
            "equations": self.equations(),
            "metadata": _jsonable(self.metadata),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    def save(self, path: str | Path) -> Path:
        """Write the JSON atomically (a crash never leaves a half-written model)."""
        return atomic_write_text(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, data: dict, source: str = "model") -> "ExplicitModel":
        if not isinstance(data, dict):
            raise ModelFormatError(f"{source}: expected a JSON object")
        if data.get("format") != FORMAT:
            raise ModelFormatError(f"{source}: field format must be {FORMAT!r}, got {data.get('format')!r}")
        for key in ("states", "inputs", "terms", "coefficients"):
            if key not in data:
                raise ModelFormatError(f"{source}: missing field {key!r}")
        states, inputs, terms = data["states"], data["inputs"], data["terms"]
        for key, value in (("states", states), ("inputs", inputs), ("terms", terms)):
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise ModelFormatError(f"{source}: field {key} must be a list of strings")
        try:
            coefficients = np.array(data["coefficients"], dtype=float)
        except (TypeError, ValueError):
            raise ModelFormatError(f"{source}: field coefficients must be a numeric matrix") from None
        if coefficients.shape != (len(terms), len(states)):
            raise ModelFormatError(f"{source}: field coefficients has shape {coefficients.shape}, expected "
                                   f"n_terms x n_states = ({len(terms)}, {len(states)})")
        if not np.all(np.isfinite(coefficients)):
            raise ModelFormatError(f"{source}: field coefficients contains NaN/inf")
        try:
            return cls(states, inputs, terms, coefficients, data.get("metadata") or {})
        except ExpressionError as err:
            raise ModelFormatError(f"{source}: field terms: {err}") from None

    @classmethod
    def load(cls, path: str | Path) -> "ExplicitModel":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except OSError as err:
            raise ModelFormatError(f"{path}: cannot read model ({err.strerror})") from None
        except json.JSONDecodeError as err:
            raise ModelFormatError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
        return cls.from_dict(data, source=str(path))


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
