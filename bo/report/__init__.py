"""Figures shared by the stage reports."""
