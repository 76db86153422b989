"""The gap workflow: find where simulation and measurement disagree, name the missing effect,
add it, and show the gap shrink."""
from .catalogue import Candidate, catalogue
from .reference import ModelReference, PlantReference
from .workflow import GapSettings, GapWorkflow, gap_percent

__all__ = ["Candidate", "catalogue", "ModelReference", "PlantReference", "GapSettings", "GapWorkflow",
           "gap_percent"]
