"""Actors: the learned, actor-specific face model and its package on disk.

:mod:`~capture.actor.package` reads, writes and lists actor packages (``actor.json``, weights,
template, bones, constraints); :mod:`~capture.actor.training` is the training stage of ``capture actor
train`` (inputs checked, checkpoints, resume, report) around :mod:`models.train`;
:mod:`~capture.actor.edit` applies anatomy edits (``capture actor edit``); :mod:`~capture.actor.sample`
locates the bundled sample actor's shapes and bones.
"""
