"""Identification engine: libraries, sparse backbone, neural residual, distillation, baselines.

Entry point: :func:`make_estimator` (``method`` = pisml | pisml-nojac | std-sindy |
mod-sindy | node), then ``fit(train, smallsignal)``; every estimator leaves
``model_`` (simulate, jacobian, eigenvalues, n_parameters) and, where the method
has one, ``explicit_model_`` (an :class:`~pisml_ros.model.ExplicitModel`).
"""
from .config import ConfigError, IdentConfig, settings_from_assignments
from .roles import RoleError, SignalRoles

__all__ = ["ConfigError", "IdentConfig", "RoleError", "SignalRoles", "METHODS", "make_estimator",
           "settings_from_assignments", "StageUpdate", "IdentificationCancelled", "selection_warnings"]


def __getattr__(name):
    # estimators import torch lazily: keep `import pisml_ros.ident` light
    if name in ("METHODS", "make_estimator", "StageUpdate", "IdentificationCancelled"):
        from . import estimators

        return getattr(estimators, name)
    if name == "selection_warnings":
        from .selection import selection_warnings

        return selection_warnings
    raise AttributeError(name)
