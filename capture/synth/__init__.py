"""Synthetic takes with known truth (``capture synth``) and the detector that reads them.

Modules: :mod:`~capture.synth.motion` (per-frame parameters), :mod:`~capture.synth.scene` (the
head-to-camera convention and framing), :mod:`~capture.synth.raster` (z-buffer rasteriser),
:mod:`~capture.synth.texture` (position colour code, dither), :mod:`~capture.synth.look` (the shaded
look video for people), :mod:`~capture.synth.detector_onnx` (the
colour-matching ONNX detector and its spec), :mod:`~capture.synth.video` (MP4 through PyAV),
:mod:`~capture.synth.take` (orchestration and files).
"""
