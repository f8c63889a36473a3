"""``capture batch``: every take of a shoot, in parallel on Ray, resumable and failure-isolated.

:mod:`~capture.batch.shoot` parses the shoot file (TOML); :mod:`~capture.batch.runner` plans the takes,
shows the shoot's progress and collects results (:func:`~capture.batch.runner.run_batch`);
:mod:`~capture.batch.cluster` is the Ray side (connect, tasks, retries); :mod:`~capture.batch.take`
runs one take (as ``capture run`` does) and decides what is already done; :mod:`~capture.batch.segments`
splits long takes into overlapping segments and blends them; :mod:`~capture.batch.report` writes the
shoot's report and summary table.
"""
