"""Cameras: calibration from board footage, camera files, and differentiable projection.

The one place where cameras, their files and their conventions live (conventions are stated in
:mod:`calib.camera` and :mod:`calib.projection`). Modules, one concept each:

- :mod:`calib.camera`      the frozen :class:`~calib.camera.Camera` value, resize/crop, default guess
- :mod:`calib.camera_io`   camera JSON and OpenCV YAML/XML files
- :mod:`calib.projection`  torch/kornia projection and undistortion (what the fit calls)
- :mod:`calib.board`       the ``--board SPEC`` grammar
- :mod:`calib.detect`      board detection through OpenCV
- :mod:`calib.subpix`      corners at the saddle point of the image intensity
- :mod:`calib.checks`      the geometric check of one detection (corners vs their neighbours)
- :mod:`calib.frames`      reading a video or an image folder
- :mod:`calib.views`       choosing views (only unusable ones dropped; duplicates and cap)
- :mod:`calib.models`      the lens distortion models (OpenCV flag sets)
- :mod:`calib.holdout`     the hold-out check (views left out, predicted, fold spread)
- :mod:`calib.calibrate`   ``cv2.calibrateCameraExtended``, outlier views, model choice
- :mod:`calib.uncertainty` intrinsic covariance, pixel uncertainty, camera differences, coverage
- :mod:`calib.diagnostics` what a calibration knows where, and its warnings
- :mod:`calib.plots`       the PNG figures
- :mod:`calib.pipeline`    the ``capture calibrate`` stage; :mod:`calib.cli` its options

Importing the package is cheap (no torch, OpenCV or matplotlib); import the modules you need.
"""
