"""Fitting a take: detections (or meshes) in, per-frame fitted meshes and parameters out.

:mod:`~capture.fit.init` gives each frame a first rigid head pose (PnP on the landmarks);
:mod:`~capture.fit.take` cuts the take into overlapping windows, fits each with :mod:`models.fit` and
blends the windows into per-frame results (``FrameFit``). The math lives in :mod:`models`; this package
owns the per-frame bookkeeping.
"""
