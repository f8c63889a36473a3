"""``capture run`` and ``capture fit3d``: one take from its video (or meshes) to its outputs.

:mod:`~capture.run.take` drives a take (:func:`~capture.run.take.run_take`): :mod:`~capture.run.inputs`
checks and resolves every input before anything is written, :mod:`~capture.run.store` claims the output
folder and fingerprints inputs, :mod:`~capture.run.stages` runs detect -> fit -> export with a cache per
stage (resume), :mod:`~capture.run.progress` shows it and :mod:`~capture.run.report` writes
``report.json``. :mod:`~capture.run.fit3d` is the same for registered 3D mesh sequences.
"""
