"""Monocular video face capture with anatomically constrained implicit face models (AIM).

Importing this package does no work: commands live in :mod:`capture.cli`.
"""

__version__ = "0.1.0"
