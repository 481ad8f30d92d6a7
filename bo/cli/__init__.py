"""Hydra entry points of the campaign commands: ``torchdem-screen``, ``-study``, ``-calibrate``, ``-discover``; shared settings in ``common``."""
