"""The sub-commands of ``capture``: one thin module each.

A command module declares its options (typer), builds the package's settings object and calls one
function of that package; :mod:`capture.cli` registers them all. ``capture calibrate`` lives in
:mod:`calib.cli`.
"""
