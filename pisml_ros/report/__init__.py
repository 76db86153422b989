"""Figures and tables (matplotlib, headless)."""
