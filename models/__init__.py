"""The anatomical implicit face model (AIM): networks, geometry and training. Pure math, no file I/O."""
