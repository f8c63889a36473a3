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

The rows are accumulated in memory and written once by ``close()`` (atomically); every export run
rewrites them whole. ``coefficients_landmarks`` is the large one (4 L E bytes per frame, 45 KB at 468
landmarks and 24 shapes): a frame whose coefficients are one row repeated (the 2D fit while F_W is zero,
:func:`capture.fit.records.repeated_rows`) is held as that row, and the array is written in blocks of
frames straight into the archive, so it is never held whole.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.export.base import STATUSES, ExportContext, FrameFitLike, PendingFile, status_code
from capture.fit.records import is_repeated_rows

PARAMS_FILE = "params.npz"
LANDMARKS_FILE = "landmarks.npz"


def _stack(rows: list, dtype, tail: tuple[int, ...] | None = None) -> np.ndarray:
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


class _Streamed:
    """A (T, ...) array of ``dtype`` written to the archive in blocks of ``BLOCK`` frames (:func:`_savez`);
    ``rows``: per frame an array of the row shape (a read-only broadcast view is fine) or None (NaN)."""

    BLOCK = 256

    def __init__(self, rows: list, dtype, tail: tuple[int, ...]):
        self.rows, self.dtype = rows, np.dtype(dtype)
        self.shape = next((np.shape(r) for r in rows if r is not None), tail)
        for i, r in enumerate(rows):
            if r is not None and np.shape(r) != self.shape:
                raise ValueError(f"frame row {i}: expected shape {self.shape} like earlier frames, got {np.shape(r)}")

    def blocks(self):
        for k in range(0, len(self.rows), self.BLOCK):
            yield _stack(self.rows[k:k + self.BLOCK], self.dtype, self.shape)


def _savez(fh, arrays: dict) -> None:
    """``np.savez(fh, **arrays)`` where a value may also be :class:`_Streamed` (written block by block: the
    same bytes as its stacked array, which ``np.load`` reads back)."""
    import zipfile

    with zipfile.ZipFile(fh, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as z:
        for key, value in arrays.items():
            with z.open(key + ".npy", "w", force_zip64=True) as member:
                if not isinstance(value, _Streamed):
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
                    continue
                np.lib.format.write_array_header_1_0(member, {
                    "descr": np.lib.format.dtype_to_descr(value.dtype), "fortran_order": False,
                    "shape": (len(value.rows),) + tuple(value.shape)})
                for block in value.blocks():
                    member.write(memoryview(np.ascontiguousarray(block)).cast("B"))


def _base(base_rows: list, landmark_rows: list) -> np.ndarray:
    """(T, E) per-frame base coefficients; a frame without them (fits cached before they were stored)
    gets the mean over the landmarks of its coefficients, which is the base while F_W is zero."""
    rows = [b if b is not None else (None if w is None else np.asarray(w, np.float64).reshape(-1, np.shape(w)[-1])
                                     .mean(0)) for b, w in zip(base_rows, landmark_rows)]
    return _stack(rows, np.float32, (0,))


def _opt(fit, name):
    v = getattr(fit, name, None)
    return None if v is None else np.asarray(v)


class ParamsWriter:
    """Accumulates per-frame parameters and detections; writes both NPZ files on close."""

    needs_image = False

    def __init__(self, out_dir: Path, ctx: ExportContext):
        self.out_dir, self.ctx = Path(out_dir), ctx
        self._rows: dict[str, list] = {k: [] for k in (
            "frame_index", "head_R", "head_t_mm", "jaw_R", "jaw_t_mm", "codes", "coefficients_landmarks",
            "coefficients_base", "reprojection_rms_px", "status", "points", "confidence", "face_found", "landmarks_fit")}
        self._any_detection = False
        self._pending: list[PendingFile] = []

    def write(self, fit: FrameFitLike, image=None, detection=None) -> None:
        r = self._rows
        frame = int(fit.frame)
        if r["frame_index"] and frame <= r["frame_index"][-1]:
            raise ValueError(f"frames must arrive in increasing order: {frame} after {r['frame_index'][-1]}")
        r["frame_index"].append(frame)
        r["status"].append(status_code(getattr(fit, "status", "fitted")))
        for key, attr in (("head_R", "head_R"), ("head_t_mm", "head_t"), ("jaw_R", "jaw_R"), ("jaw_t_mm", "jaw_t"),
                          ("codes", "code"), ("coefficients_base", "coefficients_base"),
                          ("landmarks_fit", "landmarks_fit")):
            r[key].append(_opt(fit, attr))
        w = _opt(fit, "coefficients_landmarks")        # held as float32, or as its one row (a view of E numbers)
        r["coefficients_landmarks"].append(w if w is None or is_repeated_rows(w) else w.astype(np.float32))
        rms = getattr(fit, "reprojection_rms_px", None)
        r["reprojection_rms_px"].append(np.nan if rms is None else float(rms))
        if detection is not None:
            self._any_detection = True
            r["points"].append(np.asarray(detection.points, np.float64))
            conf = getattr(detection, "confidence", None)
            r["confidence"].append(None if conf is None else np.asarray(conf, np.float32))
            r["face_found"].append(bool(detection.face_found))
        else:
            r["points"].append(None)
            r["confidence"].append(None)
            r["face_found"].append(False)

    def _arrays(self) -> tuple[dict, dict | None]:
        r, ctx = self._rows, self.ctx
        frame_index = np.asarray(r["frame_index"], np.int64)
        common = {"fps": np.float64(ctx.fps), "image_size": np.asarray(ctx.image_size, np.int64)}
        params = {
            "frame_index": frame_index,
            "time_s": frame_index / float(ctx.fps),
            "head_R": _stack(r["head_R"], np.float64, (3, 3)),
            "head_t_mm": _stack(r["head_t_mm"], np.float64, (3,)),
            "jaw_R": _stack(r["jaw_R"], np.float64, (3, 3)),
            "jaw_t_mm": _stack(r["jaw_t_mm"], np.float64, (3,)),
            "codes": _stack(r["codes"], np.float32, (0,)),
            "coefficients_landmarks": _Streamed(r["coefficients_landmarks"], np.float32, (0, 0)),
            "coefficients_base": _base(r["coefficients_base"], r["coefficients_landmarks"]),
            "reprojection_rms_px": np.asarray(r["reprojection_rms_px"], np.float64),
            "status": np.asarray(r["status"], np.int8),
            "status_names": np.asarray(STATUSES, dtype="<U7"),
            **common,
        }
        if not self._any_detection:
            return params, None
        points = _stack(r["points"], np.float64, (0, 2))
        n_lm = points.shape[1]
        landmarks = {
            "frame_index": frame_index,
            "points": points,
            "confidence": _stack(r["confidence"], np.float32, (n_lm,)),
            "face_found": np.asarray(r["face_found"], bool),
            "landmarks_fit": _stack(r["landmarks_fit"], np.float64, (n_lm, 2)),
            **common,
        }
        return params, landmarks

    def close(self) -> list[Path]:
        params, landmarks = self._arrays()
        out = []
        try:
            for name, arrays in ((PARAMS_FILE, params), (LANDMARKS_FILE, landmarks)):
                if arrays is None:
                    continue
                pending = PendingFile(self.out_dir / name)
                self._pending.append(pending)
                with open(pending.tmp, "wb") as fh:
                    _savez(fh, arrays)
            for p in self._pending:
                out.append(p.commit())
        except BaseException:
            self.abort()
            raise
        return out

    def abort(self) -> None:
        for p in self._pending:
            p.discard()
        self._pending.clear()
