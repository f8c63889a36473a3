"""Cached arrays read back safely: NPZ archives checked before a byte of array data is loaded; and
written without a stacked copy (:func:`write_npz`).

The caches of a run (detections, fitted windows, frame fits) and the arrays of an actor package are
plain NPZ archives written by ``np.savez`` (stored, not compressed). A damaged or crafted file must
neither run code (no pickle: object arrays are refused) nor blow up memory: every member's header is
read first (dtype and shape), and the archive is refused when a member is compressed, holds objects,
declares more bytes than it stores, or when the total exceeds ``max_bytes``. Each problem is one
:class:`~capture.io.errors.CaptureError` line naming the file and saying what to do.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError

#: Default ceiling of one cached archive's arrays (bytes); callers pass a tighter one when they know the shapes.
DEFAULT_MAX_BYTES = 2 << 30


def npz_members(path: Path, max_bytes: int = DEFAULT_MAX_BYTES) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """The ``{name: (dtype, shape)}`` of an NPZ, read from the member headers only.

    Raises ValueError (with the reason) for anything :func:`load_npz` must refuse.
    """
    size = os.stat(path).st_size
    if size > max_bytes + (1 << 20):
        raise ValueError(f"{size} bytes on disk, more than the {max_bytes} expected at most")
    out: dict[str, tuple[np.dtype, tuple[int, ...]]] = {}
    total = 0
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):
                raise ValueError(f"member {info.filename!r} is not an array")
            if info.compress_type != zipfile.ZIP_STORED:
                raise ValueError(f"member {info.filename!r} is compressed (this program never writes compressed caches)")
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, _fortran, dtype = np.lib.format.read_array_header_1_0(fh, max_header_size=10000)
                elif version in ((2, 0), (3, 0)):
                    shape, _fortran, dtype = np.lib.format.read_array_header_2_0(fh, max_header_size=10000)
                else:
                    raise ValueError(f"member {info.filename!r} has an unknown .npy version {version}")
            if dtype.hasobject:
                raise ValueError(f"member {info.filename!r} holds Python objects (pickle), which are never loaded")
            nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
            if nbytes > info.file_size:
                raise ValueError(f"member {info.filename!r} declares {nbytes} bytes but stores {info.file_size}")
            total += nbytes
            if total > max_bytes:
                raise ValueError(f"its arrays hold more than {max_bytes} bytes")
            out[info.filename[:-4]] = (dtype, tuple(int(s) for s in shape))
    return out


def load_npz(path: str | os.PathLike, what: str, fix: str, max_bytes: int = DEFAULT_MAX_BYTES,
             required: tuple[str, ...] = (), only: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """All arrays of the NPZ at ``path`` after :func:`npz_members` accepted it (``only``: just these, when
    present; the others are not read).

    ``what`` names the file for the user ("fit cache", "actor constraints"); ``fix`` says what to do
    ("delete it or rerun with --overwrite"). ``required`` member names must be present.
    """
    path = Path(path)
    try:
        members = npz_members(path, max_bytes)
        missing = [k for k in required if k not in members]
        if missing:
            raise ValueError(f"it lacks {', '.join(missing)}")
        with np.load(path, allow_pickle=False) as z:
            keep = set(z.files) if only is None else set(only)
            return {k: z[k] for k in z.files if k in keep}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        reason = str(exc).splitlines()[0][:200] if str(exc).strip() else exc.__class__.__name__
        raise CaptureError(f"{what} {path} is damaged or not written by this program ({reason}); {fix}") from None


@dataclass(frozen=True)
class Blocks:
    """An array given as consecutive blocks of rows (read one at a time, e.g. from a file they were spilled to):
    ``dtype``, the whole ``shape``, and an iterable of ``(k, *shape[1:])`` arrays whose ``k`` add up to
    ``shape[0]``. :func:`write_npz` writes it as that array."""

    dtype: np.dtype
    shape: tuple[int, ...]
    blocks: Iterable[np.ndarray]


def _member(member, value: np.ndarray | list | Blocks) -> None:
    """Write one ``.npy`` member (``np.lib.format`` version 1.0) from the arrays' own memory (see :func:`write_npz`)."""
    if isinstance(value, list):
        rows = [np.asarray(r) for r in value]
        if not rows:
            raise ValueError("no rows to write: give an empty array instead")
        dtype, tail = rows[0].dtype, rows[0].shape
        for r in rows:
            if r.dtype != dtype or r.shape != tail:
                raise ValueError(f"rows of different shapes or types: {r.dtype} {r.shape} after {dtype} {tail}")
        value = Blocks(dtype, (len(rows),) + tuple(tail), (r[None] for r in rows))
    elif not isinstance(value, Blocks):
        a = np.asanyarray(value)
        value = Blocks(a.dtype, a.shape, [a])
    dtype = np.dtype(value.dtype)
    if dtype.hasobject:
        raise ValueError("object arrays are not written")
    np.lib.format.write_array_header_1_0(member, {"descr": np.lib.format.dtype_to_descr(dtype),
                                                 "fortran_order": False, "shape": tuple(value.shape)})
    for block in value.blocks:
        if block.size:
            member.write(memoryview(np.ascontiguousarray(block).reshape(-1)).cast("B"))


def write_npz(fh, arrays: dict, deflate: Iterable[str] = ()) -> None:
    """``np.savez(fh, **arrays)`` (stored, readable by ``np.load`` and :func:`load_npz`), where a value may
    also be a list of equally shaped arrays, written as their stack, or :class:`Blocks`.

    ``deflate``: keys whose members are deflated instead (zlib level 1; ``np.load`` reads them as any other,
    :func:`load_npz` refuses them: never for a cache). For an output member that repeats itself:
    ``params.npz``'s expression coefficients where all landmarks of a frame have the same (52 MB stored at
    1,200 frames of 468 landmarks, 0.5 MB deflated in 0.06 s, where writing the 52 MB cost more).

    The data go to the archive from the arrays' own memory, without the copy that ``np.lib.format.write_array``
    makes of a zip member's data (to ``bytes``) nor a stacked array: a run's fit chunks (64 frames of 9,409
    vertices, 7 MB) were copied twice, each copy a fresh mapping in the run's process, which maps blocks of
    1 MB and up (:mod:`capture.io.heap`).
    """
    deflate = set(deflate)
    with zipfile.ZipFile(fh, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as z:
        for key, value in arrays.items():
            z.compression, z.compresslevel = (zipfile.ZIP_DEFLATED, 1) if key in deflate else (zipfile.ZIP_STORED, None)
            with z.open(key + ".npy", "w", force_zip64=True) as member:
                _member(member, value)
