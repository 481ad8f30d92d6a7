"""The calibration campaign (paper sections 3.3-3.7): ``pipeline`` runs it, ``report`` writes it."""
