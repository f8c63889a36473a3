"""A registered mesh sequence as the motion of a synthetic take (``capture synth --meshes SEQ``).

``SEQ`` is either a folder of OBJ/PLY meshes (frames in file-name order) or an ``.npz`` with one
array ``(T, V, 3)`` (key ``vertices``, or its only array). Meshes are in the actor's topology (the
template's vertex order and count), in millimetres (``--units`` converts), in the template frame
(x = the actor's left, y up, z out of the face: the frame of the actor's shapes). Held-out
expression mixes, other rigs' animation and real 4D scans registered to the actor become takes with
truth this way: the head motion of the take's preset is put on top (``--preset frontal`` for none).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError

__all__ = ["read_mesh_sequence"]


def read_mesh_sequence(path: str | Path, n_vertices: int, units: str = "mm") -> np.ndarray:
    """Vertices ``(T, V, 3)`` float64 mm of the sequence at ``path`` (see the module docstring).

    Raises CaptureError when the path is missing, holds no frames, has the wrong vertex count,
    a non-finite coordinate or an array of the wrong shape.
    """
    from capture.io.meshes import load_mesh_folder, units_scale

    path = Path(path)
    scale = units_scale(units)
    if path.is_dir():
        return load_mesh_folder(path, units, n_vertices, "give a folder of meshes registered to the actor's "
                                "topology, or an .npz (T, V, 3)")[1]
    if not path.is_file():
        raise CaptureError(f"--meshes {path} does not exist; give a folder of OBJ/PLY meshes or an .npz (T, V, 3)")
    if path.suffix.lower() != ".npz":
        raise CaptureError(f"--meshes {path}: expected a folder of OBJ/PLY meshes or an .npz file")
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = list(z.keys())
            if "vertices" in keys:
                v = z["vertices"]
            elif len(keys) == 1:
                v = z[keys[0]]
            else:
                raise CaptureError(f"{path} holds {len(keys)} arrays ({', '.join(keys[:5])}) and none is named "
                                   f"'vertices'; store the sequence as vertices=(T, V, 3)")
    except (OSError, ValueError) as exc:
        raise CaptureError(f"cannot read {path}: {exc}") from None
    v = np.asarray(v, np.float64)
    if v.ndim != 3 or v.shape[2] != 3 or len(v) == 0:
        raise CaptureError(f"{path}: expected vertices of shape (T, V, 3) with T >= 1, got {v.shape}")
    if v.shape[1] != n_vertices:
        raise CaptureError(f"{path} has {v.shape[1]} vertices per frame but the actor's template has {n_vertices}; "
                           f"register the sequence to the actor's topology")
    bad = ~np.isfinite(v).all(axis=2)
    if bad.any():
        t, i = np.argwhere(bad)[0]
        raise CaptureError(f"{path}: {int(bad.sum())} vertices with NaN or infinite coordinates (first: frame {t}, "
                           f"vertex {i}); fix the sequence")
    return v * scale
