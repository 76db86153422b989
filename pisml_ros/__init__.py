"""pisml_ros: explicit governing equations of black-box grid-connected inverters (PISML)."""
__version__ = "0.1.0"
