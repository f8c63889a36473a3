"""Rows of a per-frame array, one per frame as a take goes by, held a block at a time and spilled to an
unnamed temporary file, so that what a run holds does not grow with the take's length.

:class:`SpilledRows` gives the rows back block by block (:meth:`SpilledRows.blocks`, for writing an
archive) or as one read-only array mapped from its file (:meth:`SpilledRows.mapped`, for readers that want
the whole take: its pages are the file's, read in as used and dropped by the OS when memory is short,
not the process's own memory). Used by ``params.npz`` / ``landmarks.npz`` (:mod:`capture.export.params`)
and by the streamed run's landmark track (:class:`capture.detector.pipeline.TrackBuilder`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Frames a whole-take computation at the end of a run (a key's digest, the landmark checks) takes at a
#: time, so that a long take's end makes no array of the take's size.
BLOCK_FRAMES = 2048


def stack_rows(rows: list, dtype, tail: tuple[int, ...] | None = None) -> np.ndarray:
    """Stack per-frame arrays; ``None`` rows become NaN of the common shape (first non-None)."""
    shape = tail
    for r in rows:
        if r is not None:
            shape = np.shape(r)
            break
    if shape is None:
        shape = (0,)
    out = np.full((len(rows),) + tuple(shape), np.nan, dtype=dtype)
    for i, r in enumerate(rows):
        if r is not None:
            r = np.asarray(r, dtype=dtype)
            if r.shape != tuple(shape):
                raise ValueError(f"frame row {i}: expected shape {tuple(shape)} like earlier frames, got {r.shape}")
            out[i] = r
    return out


def same_shape(shape: tuple[int, ...] | None, row, index: int) -> tuple[int, ...] | None:
    """The rows' shape so far after frame row ``index`` (the first row's); ValueError for a row of another."""
    if row is None:
        return shape
    got = tuple(np.shape(row))
    if shape is not None and got != shape:
        raise ValueError(f"frame row {index}: expected shape {shape} like earlier frames, got {got}")
    return got


class SpilledRows:
    """The rows of one (T, ...) array of ``dtype``, one per frame as it arrives: an array of the row shape (the
    first row's; a read-only broadcast view is fine) or None (NaN).

    At most ``BLOCK`` rows are held; each full block is stacked and appended to an unnamed temporary file in
    ``spill_dir``. :meth:`blocks` gives the array ``np.stack`` of the rows would make (None as NaN), block by
    block, and :meth:`mapped` the whole of it, read-only, from the file; ``tail`` is the row shape when every
    row is None."""

    BLOCK = 256

    def __init__(self, dtype, tail: tuple[int, ...], spill_dir: Path):
        self.dtype, self.tail, self.shape = np.dtype(dtype), tuple(tail), None
        self._dir, self._file, self._spilled, self._held = Path(spill_dir), None, 0, []
        self._mapped = False

    def __len__(self) -> int:
        return self._spilled + len(self._held)

    def append(self, row) -> None:
        if self._mapped:
            raise RuntimeError("rows cannot be added once mapped")
        self.shape = same_shape(self.shape, row, len(self))
        self._held.append(row)
        if len(self._held) >= self.BLOCK and self.shape is not None:
            self._spill()

    def _spill(self) -> None:
        if self._file is None:
            import tempfile

            self._file = tempfile.TemporaryFile(dir=self._dir, prefix=".rows-")
        self._file.write(memoryview(stack_rows(self._held, self.dtype, self.shape)).cast("B"))
        self._spilled += len(self._held)
        self._held = []

    def mapped(self) -> np.ndarray:
        """All the rows as one read-only ``(T, *row shape)`` array (None rows as NaN), mapped from the file
        (the rows still held are written to it first); no row can be added after. In memory when there is
        nothing to map: no rows, or every row None (NaN of ``tail``'s shape)."""
        if self.shape is None or len(self) == 0:
            return stack_rows(self._held, self.dtype, self.row_shape())
        import mmap

        if self._held:
            self._spill()
        self._file.flush()
        self._mapped = True
        view = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)   # its own handle on the file
        return np.frombuffer(view, self.dtype).reshape((self._spilled,) + self.shape)

    def row_shape(self, tail: tuple[int, ...] | None = None) -> tuple[int, ...]:
        return self.shape if self.shape is not None else tuple(self.tail if tail is None else tail)

    def blocks(self, tail: tuple[int, ...] | None = None):
        """``(k, *row shape)`` blocks of at most ``BLOCK`` rows, in order (``tail``: overrides the row shape
        given when every row is None)."""
        shape = self.row_shape(tail)
        if self._spilled:
            self._file.flush()
            self._file.seek(0)
            size = int(np.prod(shape, dtype=np.int64)) * self.dtype.itemsize
            for k in range(0, self._spilled, self.BLOCK):
                n = min(self.BLOCK, self._spilled - k)
                yield np.frombuffer(self._file.read(n * size), self.dtype).reshape((n,) + shape)
        if self._held:
            yield stack_rows(self._held, self.dtype, shape)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
