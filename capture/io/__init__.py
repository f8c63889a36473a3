"""Small file and process helpers every stage uses; no face-capture logic.

:mod:`~capture.io.errors` (the one-line user error and the interrupt), :mod:`~capture.io.atomic`
(write-then-rename files and folders), :mod:`~capture.io.signals` (SIGTERM as an interrupt),
:mod:`~capture.io.video` (reading frames and a video's identity), :mod:`~capture.io.meshes` (OBJ/PLY
meshes, shape folders and length units).
"""
