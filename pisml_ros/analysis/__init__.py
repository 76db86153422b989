"""Analysis of models: equilibria, linearisation, eigenvalues, damping, margins."""
from .margins import distance_to_boundary, root_locus, stability_boundaries
from .modal import ModalSummary, damping_ratio, modal_summary

__all__ = ["ModalSummary", "damping_ratio", "modal_summary", "stability_boundaries", "distance_to_boundary", "root_locus"]
