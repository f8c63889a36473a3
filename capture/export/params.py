"""Per-frame parameters (``params.npz``) and detected landmarks (``landmarks.npz``).

Both are plain NPZ archives (``np.load(path, allow_pickle=False)`` works). T is the number of
exported frames (in the order they arrived, increasing frame index), L the number of landmarks,
E the number of expression shapes, f the frame-code width. Values that a frame does not have
(a ``skipped`` frame has no fit) are NaN.

``params.npz``:

=========================  ===========  =========  ==================================================
key                        shape        dtype      meaning
=========================  ===========  =========  ==================================================
frame_index                (T,)         int64      index of the frame in the video
time_s                     (T,)         float64    frame_index / fps
head_R                     (T, 3, 3)    float64    head rotation: x_cam = head_R @ x_head + head_t
head_t_mm                  (T, 3)       float64    head translation, mm, camera frame
jaw_R                      (T, 3, 3)    float64    jaw rotation (in the head frame)
jaw_t_mm                   (T, 3)       float64    jaw translation, mm
codes                      (T, f)       float32    frame codes z_j
coefficients_landmarks     (T, L, E)    float32    expression coefficients w_j(c) at the landmarks
coefficients_base          (T, E)       float32    the per-frame base b_j: w_j(c) = b_j + F_W(z_j, c)
reprojection_rms_px        (T,)         float64    RMS of fitted vs detected landmarks, pixels
status                     (T,)         int8       0 fitted, 1 bridged, 2 skipped (see status_names)
status_names               (3,)         <U7        the legend: ["fitted", "bridged", "skipped"]
fps                        ()           float64    video frame rate
image_size                 (2,)         int64      width, height in pixels
=========================  ===========  =========  ==================================================

``landmarks.npz`` (written when detections were passed with the frames):

=========================  ===========  =========  ==================================================
key                        shape        dtype      meaning
=========================  ===========  =========  ==================================================
frame_index                (T,)         int64      index of the frame in the video
points                     (T, L, 2)    float64    detected landmarks, full-frame px (OpenCV centres)
confidence                 (T, L)       float32    per-landmark confidence 0..1; NaN when none given
face_found                 (T,)         bool       the detector found a face
landmarks_fit              (T, L, 2)    float64    the fitted mesh's landmarks projected, px
fps                        ()           float64    video frame rate
image_size                 (2,)         int64      width, height in pixels
=========================  ===========  =========  ==================================================

The rows are written atomically by ``close()``; every export run rewrites them whole. While the take goes
by, each array's rows are held ``BLOCK`` frames at a time and full blocks are spilled to an unnamed
temporary file beside the outputs (gone when the process ends, however it ends), so the writer's memory
stays flat in the take's length; ``close()`` copies the blocks into the archive. ``coefficients_landmarks``
is the large one (4 L E bytes per frame, 45 KB at 468 landmarks and 24 shapes): a frame whose coefficients
are one row repeated (the 2D fit while F_W is zero, :func:`capture.fit.records.repeated_rows`) is kept as
that row and expanded only as its block is written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.export.base import STATUSES, ExportContext, FrameFitLike, PendingFile, status_code
from capture.fit.records import is_repeated_rows
from capture.io.arrays import Blocks, write_npz
from capture.io.rows import SpilledRows, same_shape

PARAMS_FILE = "params.npz"
LANDMARKS_FILE = "landmarks.npz"


class _Coefficients:
    """``coefficients_landmarks`` rows (L, E): a frame's repeated row (:func:`capture.fit.records.repeated_rows`)
    is kept as its one row of E numbers, any other as float32 (L, E); both spilled as :class:`SpilledRows`."""

    dtype = np.dtype(np.float32)
    #: frames per block of :meth:`blocks`, all in one buffer: ~360 KB at 468 landmarks and 24 expressions stays in
    #: the cache and maps no fresh memory (a 256-frame block was 11.5 MB: 0.11 s to deflate 1,200 frames, now 0.07)
    BLOCK_FRAMES = 8

    def __init__(self, spill_dir: Path):
        from array import array

        self.kinds = array("b")       # per frame: 0 none, 1 one row repeated, 2 full
        self.shape: tuple[int, ...] | None = None
        self._one = SpilledRows(np.float32, (0,), spill_dir)
        self._full = SpilledRows(np.float32, (0, 0), spill_dir)

    def __len__(self) -> int:
        return len(self.kinds)

    def append(self, w) -> None:
        self.shape = same_shape(self.shape, w, len(self))
        if w is None:
            self.kinds.append(0)
        elif is_repeated_rows(w):
            self._one.append(np.asarray(w)[0])
            self.kinds.append(1)
        else:
            self._full.append(w)
            self.kinds.append(2)

    def row_shape(self, tail=None) -> tuple[int, ...]:
        return self.shape if self.shape is not None else (0, 0)

    @property
    def repeated(self) -> bool:
        """No frame has rows of its own (each has one row repeated, or none): the stack repeats itself."""
        return 2 not in self.kinds

    def blocks(self, tail=None):
        """The (k, L, E) float32 blocks of the stacked rows (NaN for a frame without them), each written into the
        same buffer: a block must be used before the next is asked for (as :func:`capture.io.arrays.write_npz`
        does)."""
        shape = self.row_shape()
        one = (r for b in self._one.blocks(shape[1:]) for r in b)
        full = (r for b in self._full.blocks(shape) for r in b)
        buf = np.empty((self.BLOCK_FRAMES,) + tuple(shape), np.float32)
        for k in range(0, len(self.kinds), self.BLOCK_FRAMES):
            kinds = self.kinds[k:k + self.BLOCK_FRAMES]
            out = buf[:len(kinds)]
            for i, kind in enumerate(kinds):
                out[i] = np.nan if kind == 0 else next(one) if kind == 1 else next(full)
            yield out

    def close(self) -> None:
        self._one.close()
        self._full.close()


def _savez(fh, arrays: dict, tails: dict | None = None) -> None:
    """``np.savez(fh, **arrays)`` where a value may also be :class:`SpilledRows` or :class:`_Coefficients`
    (written block by block: the same bytes as its stacked array, which ``np.load`` reads back; ``tails``:
    the row shape of such a value whose rows are all None)."""
    tails = tails or {}

    def member(key, value):
        if not isinstance(value, (SpilledRows, _Coefficients)):
            return value
        tail = tails.get(key)
        return Blocks(value.dtype, (len(value),) + tuple(value.row_shape(tail)), value.blocks(tail))

    # coefficients that repeat one row per frame (the 2D default) are deflated: 52 MB -> 0.5 MB at 1,200 frames
    deflate = [k for k, v in arrays.items() if isinstance(v, _Coefficients) and v.repeated]
    write_npz(fh, {k: member(k, v) for k, v in arrays.items()}, deflate=deflate)


def _opt(fit, name):
    v = getattr(fit, name, None)
    return None if v is None else np.asarray(v)


class ParamsWriter:
    """Takes per-frame parameters and detections as they come (held in blocks, spilled: :class:`SpilledRows`);
    writes both NPZ files on close."""

    needs_image = False

    #: the per-frame arrays: key -> (dtype, row shape when no frame has the array)
    ROWS = {"head_R": (np.float64, (3, 3)), "head_t_mm": (np.float64, (3,)), "jaw_R": (np.float64, (3, 3)),
            "jaw_t_mm": (np.float64, (3,)), "codes": (np.float32, (0,)), "coefficients_base": (np.float32, (0,)),
            "points": (np.float64, (0, 2)), "confidence": (np.float32, (0,)), "landmarks_fit": (np.float64, (0, 2))}

    def __init__(self, out_dir: Path, ctx: ExportContext):
        from array import array

        self.out_dir, self.ctx = Path(out_dir), ctx
        self._rows = {k: SpilledRows(dtype, tail, self.out_dir) for k, (dtype, tail) in self.ROWS.items()}
        self._coefficients = _Coefficients(self.out_dir)
        self._frames, self._status = array("q"), array("b")
        self._rms, self._found = array("d"), array("b")
        self._any_detection = False
        self._pending: list[PendingFile] = []

    def write(self, fit: FrameFitLike, image=None, detection=None) -> None:
        r = self._rows
        frame = int(fit.frame)
        if self._frames and frame <= self._frames[-1]:
            raise ValueError(f"frames must arrive in increasing order: {frame} after {self._frames[-1]}")
        status = status_code(getattr(fit, "status", "fitted"))
        w = _opt(fit, "coefficients_landmarks")
        base = _opt(fit, "coefficients_base")
        if base is None and w is not None:   # fits cached before the base was stored: while F_W is zero the
            base = np.asarray(w, np.float64).reshape(-1, np.shape(w)[-1]).mean(0)   # base is the landmark mean
        for key, attr in (("head_R", "head_R"), ("head_t_mm", "head_t"), ("jaw_R", "jaw_R"), ("jaw_t_mm", "jaw_t"),
                          ("codes", "code"), ("landmarks_fit", "landmarks_fit")):
            r[key].append(_opt(fit, attr))
        r["coefficients_base"].append(base)
        self._coefficients.append(w)
        if detection is not None:
            self._any_detection = True
            r["points"].append(np.asarray(detection.points, np.float64))
            conf = getattr(detection, "confidence", None)
            r["confidence"].append(None if conf is None else np.asarray(conf, np.float32))
            found = bool(detection.face_found)
        else:
            r["points"].append(None)
            r["confidence"].append(None)
            found = False
        rms = getattr(fit, "reprojection_rms_px", None)
        self._frames.append(frame)
        self._status.append(status)
        self._rms.append(np.nan if rms is None else float(rms))
        self._found.append(found)

    def _arrays(self) -> tuple[dict, dict | None, dict]:
        """The archives' arrays (per-frame ones as :class:`SpilledRows`) and the row shapes of those that no frame
        has, by archive key."""
        r, ctx = self._rows, self.ctx
        frame_index = np.asarray(self._frames, np.int64)
        common = {"fps": np.float64(ctx.fps), "image_size": np.asarray(ctx.image_size, np.int64)}
        params = {
            "frame_index": frame_index,
            "time_s": frame_index / float(ctx.fps),
            "head_R": r["head_R"], "head_t_mm": r["head_t_mm"], "jaw_R": r["jaw_R"], "jaw_t_mm": r["jaw_t_mm"],
            "codes": r["codes"],
            "coefficients_landmarks": self._coefficients,
            "coefficients_base": r["coefficients_base"],
            "reprojection_rms_px": np.asarray(self._rms, np.float64),
            "status": np.asarray(self._status, np.int8),
            "status_names": np.asarray(STATUSES, dtype="<U7"),
            **common,
        }
        if not self._any_detection:
            return params, None, {}
        n_lm = r["points"].row_shape()[0]
        landmarks = {
            "frame_index": frame_index,
            "points": r["points"],
            "confidence": r["confidence"],
            "face_found": np.asarray(self._found, np.int8).astype(bool),
            "landmarks_fit": r["landmarks_fit"],
            **common,
        }
        return params, landmarks, {"confidence": (n_lm,), "landmarks_fit": (n_lm, 2)}

    def close(self) -> list[Path]:
        params, landmarks, tails = self._arrays()
        out = []
        try:
            for name, arrays in ((PARAMS_FILE, params), (LANDMARKS_FILE, landmarks)):
                if arrays is None:
                    continue
                pending = PendingFile(self.out_dir / name)
                self._pending.append(pending)
                with open(pending.tmp, "wb") as fh:
                    _savez(fh, arrays, tails if arrays is landmarks else None)
            for p in self._pending:
                out.append(p.commit())
        except BaseException:
            self.abort()
            raise
        finally:
            self._release()
        return out

    def _release(self) -> None:
        for rows in self._rows.values():
            rows.close()
        self._coefficients.close()

    def abort(self) -> None:
        for p in self._pending:
            p.discard()
        self._pending.clear()
        self._release()
