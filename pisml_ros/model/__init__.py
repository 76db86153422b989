"""Explicit models: named terms + coefficients, JSON, sympy/LaTeX, evaluation, simulation."""
from .explicit import EquilibriumNotFound, ExplicitModel, ModelFormatError
from .expressions import ExpressionError, TermSet, parse_term, term_set

__all__ = ["ExplicitModel", "ModelFormatError", "EquilibriumNotFound", "ExpressionError", "TermSet", "parse_term",
           "term_set"]
