"""On-disk state of a run folder: ``run.json``, fingerprints, and the stored frame fits.

``run.json`` names the take (the video's identity) and holds the resolved settings and the
fingerprints of the inputs; it is written before any work, so a folder that holds another take is
recognised and refused without ``--overwrite``. Frame fits are stored as plain arrays in chunks
(``fit/<key>/frames_<first>.npz``, listed by ``fit/<key>/done.json``) so that exports can be redone
without fitting again, and memory stays flat in the take's length.

:func:`open_run_dir` claims a folder for a run: it creates and locks it (:mod:`capture.io.outdir`),
finishes a swap cut short, removes temporary files of killed runs, refuses symbolic links among the
run's entries, and decides where the run is built: in the folder itself, or -- when ``--overwrite``
replaces a run -- in ``OUT/.overwrite/``, swapped in by :meth:`RunFolder.commit` only once the new
run has succeeded (a journal, ``OUT/.swap.json``, lets the next run finish a swap that was cut short).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import re
import shutil
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from capture.fit.records import ROW_SUFFIX, ROWS_SUFFIX, is_repeated_rows, stored_rows
from capture.io.arrays import write_npz
from capture.io.atomic import atomic_path, is_temp_name, write_json
from capture.io.errors import CaptureError

RUN_JSON = "run.json"
RUN_FORMAT = "capture-run"
#: What a run folder may hold (removed by ``--overwrite`` when the folder holds another take).
OWNED = ("run.json", "report.json", "report.html", "export.json", "landmarks.npz", "detections", "fit", "meshes",
         "params.npz", "curves.csv", "take.usd", "take.usda", "take.usdc", "overlay.mp4", "detect")
#: Files ``capture batch`` keeps in a take's run folder (its log and state); they may be there before
#: the folder is claimed (a take that failed on its input) and are not removed by ``--overwrite``.
BATCH_FILES = ("batch_take.json", "batch_take.log")
#: What ``capture detect`` writes into the same folder (the shared detection cache and its outputs); a
#: folder holding only these is claimed like an empty one.
DETECT_FILES = ("detections", "detect")


def digest(obj: Any) -> str:
    """sha256 of the canonical JSON of ``obj`` (plain data)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclasses.dataclass(frozen=True)
class Blocks:
    """An array given block by block along its first axis, for :func:`array_digest` (which hashes it as it
    would the whole array) when the whole is not wanted in memory: its ``dtype``, the ``shape`` of the
    whole, and ``blocks()`` giving the blocks in order."""

    dtype: Any
    shape: tuple
    blocks: Any     # () -> iterable of arrays


def array_digest(*arrays: np.ndarray | Blocks | None) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        if isinstance(a, Blocks):
            dtype, shape, rows = np.dtype(a.dtype), tuple(int(n) for n in a.shape), 0
            h.update(str((dtype.str, shape)).encode())
            for b in a.blocks():
                b = np.ascontiguousarray(b, dtype)
                if b.shape[1:] != shape[1:]:
                    raise ValueError(f"block of shape {b.shape} in an array of shape {shape}")
                rows += len(b)
                h.update(memoryview(b.reshape(-1)).cast("B"))
            if rows != shape[0]:
                raise ValueError(f"blocks of {rows} rows in all for an array of shape {shape}")
            continue
        a = np.ascontiguousarray(a)   # no copy when it is already C-contiguous
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(memoryview(a.reshape(-1)).cast("B"))   # the bytes of tobytes(), not copied
    return h.hexdigest()


def read_json(path: Path) -> dict | None:
    """The JSON object in ``path``, or None when it is missing, unreadable or not an object."""
    try:
        obj = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


def claim_run_dir(out: Path, take_id: str, take_label: str, overwrite: bool) -> None:
    """Make sure ``out`` may hold this take: empty, new, or a run of the same take.

    A folder whose ``run.json`` names another take is refused without ``overwrite``; with it, the
    previous run's files (:data:`OWNED`) are removed. A non-empty folder that is not a run folder is
    always refused (nothing of the user's is deleted). ``capture run``, ``fit3d`` and ``retarget`` use
    :func:`open_run_dir` instead, which never deletes before the new run has succeeded.
    """
    out = Path(out)
    if _claim_mode(out, take_id, overwrite) == "replace":
        _remove_run(out, out)


def _claim_mode(out: Path, take_id: str, overwrite: bool) -> str:
    """``"here"`` (build in ``out``) or ``"replace"`` (a run to be replaced); one line when refused."""
    if out.exists() and not out.is_dir():
        raise CaptureError(f"--out {out} is a file; give a folder")
    # Hidden files (such as the temporary sibling of an atomic write in progress by a concurrent task of
    # the same take, the lock, a staged replacement), the batch's files and capture detect's outputs do not make a
    # folder "not empty".
    if not out.exists() or not any(p.name not in BATCH_FILES + DETECT_FILES and not p.name.startswith(".")
                                   for p in out.iterdir()):
        return "here"
    prev = read_json(out / RUN_JSON)
    if not isinstance(prev, dict) or prev.get("format") != RUN_FORMAT:
        raise CaptureError(f"output folder {out} is not empty and holds no run ({RUN_JSON}); choose an empty "
                           f"or new folder with --out")
    same = prev.get("take_id") == take_id
    if same and not overwrite:
        return "here"
    if not same and not overwrite:
        raise CaptureError(f"output folder {out} holds the run of another take ({prev.get('take_label', '?')}); "
                           f"choose another --out or pass --overwrite to replace it")
    return "replace"


def _export_files(folder: Path) -> list[str]:
    exported = read_json(folder / "export.json")
    if not isinstance(exported, dict):
        return []
    return [str(f) for f in list(exported.get("files", [])) + list(exported.get("previous_files", []))]


def _remove_run(out: Path, folder: Path, extra: tuple[str, ...] = ()) -> None:
    """Remove the run files in ``folder`` (its export's files, :data:`OWNED`, ``extra``); a user's own files stay."""
    root = folder.resolve()
    for rel in _export_files(folder):
        p = folder / rel
        if p.is_file() and not p.is_symlink() and p.resolve().is_relative_to(root):
            p.unlink()
    for name in OWNED + extra:
        p = folder / name
        if p.is_symlink():
            p.unlink()
        elif p.is_dir():
            if name == "meshes":  # the export's files are gone; what is left there is the user's
                if not any(p.iterdir()):
                    p.rmdir()
                continue
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


FRAME_FILE = re.compile(r"^frame_\d{6}\.(obj|ply)$")  # the per-frame files an export writes in meshes/
STAGING = ".overwrite"       # a replacing run is built here, inside --out, and swapped in on success
SWAP_JOURNAL = ".swap.json"  # written before the swap; a swap cut short is finished by the next run
#: Hidden entries of a run folder that :func:`open_run_dir` checks and cleans besides :data:`OWNED`.
HIDDEN = (STAGING,)


@dataclasses.dataclass
class RunFolder:
    """A claimed, locked output folder. Stages write to ``work``; :meth:`commit` makes it ``out``.

    ``work`` is ``out`` itself, or ``out/.overwrite`` when ``--overwrite`` replaces a run: the previous
    run stays complete until the new one has succeeded (:meth:`commit` swaps them).
    """

    out: Path
    work: Path
    lock: Any
    extra: tuple[str, ...] = ()

    @property
    def replacing(self) -> bool:
        return self.work != self.out

    def commit(self) -> None:
        """Swap a staged replacement into ``out`` (no-op when building in place)."""
        if self.replacing:
            entries = sorted(p.name for p in self.work.iterdir() if not is_temp_name(p.name))
            write_json(self.out / SWAP_JOURNAL, {"staging": STAGING, "entries": entries,
                                                 "old_files": _export_files(self.out)})
            finish_swap(self.out, self.extra)

    def close(self) -> None:
        self.lock.release()

    def __enter__(self) -> "RunFolder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def finish_swap(out: Path, extra: tuple[str, ...] = ()) -> None:
    """Finish a swap described by ``out/.swap.json`` (idempotent: a swap cut short is finished here)."""
    out = Path(out)
    journal = read_json(out / SWAP_JOURNAL)
    if not isinstance(journal, dict):
        return
    staging = out / STAGING
    old_files = [str(f) for f in journal.get("old_files", [])]
    root = out.resolve()
    for rel in old_files:
        p = out / rel
        if p.is_file() and not p.is_symlink() and p.resolve().is_relative_to(root):
            p.unlink()
    meshes = out / "meshes"
    if "meshes" in journal.get("entries", []) and meshes.is_dir() and not meshes.is_symlink():
        for f in meshes.iterdir():  # frame files of the old run that no export listed (one cut short)
            if FRAME_FILE.match(f.name) and f.is_file() and not (staging / "meshes" / f.name).exists():
                f.unlink()
    for name in journal.get("entries", []):
        src, dst = staging / name, out / name
        if not (src.exists() or src.is_symlink()):
            continue  # moved already
        if name == "meshes" and dst.is_dir() and not dst.is_symlink():
            for f in src.iterdir():     # merge: a user's own files in meshes/ stay
                os.replace(f, dst / f.name)
            src.rmdir()
            continue
        if dst.is_dir() and not dst.is_symlink():
            shutil.rmtree(dst)
        elif dst.exists() or dst.is_symlink():
            dst.unlink()
        os.replace(src, dst)
    for name in OWNED + extra:  # entries of the old run the new one does not have (e.g. another format)
        if name in journal.get("entries", []) or name == "meshes":
            continue
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
    if meshes.is_dir() and "meshes" not in journal.get("entries", []):
        for f in meshes.iterdir():
            if FRAME_FILE.match(f.name) and f.is_file():
                f.unlink()
    if meshes.is_dir() and "meshes" not in journal.get("entries", []) and not any(meshes.iterdir()):
        meshes.rmdir()
    if staging.exists():
        shutil.rmtree(staging)
    (out / SWAP_JOURNAL).unlink()


def open_run_dir(out: Path, take_id: str, take_label: str, overwrite: bool, what: str = "run",
                 extra: tuple[str, ...] = ()) -> RunFolder:
    """Create, lock, tidy and claim ``out`` for this take; where to build (see :class:`RunFolder`).

    Under the lock: a swap cut short is finished, temporary files of killed runs are removed, and a
    run folder with symbolic links among its entries is refused. ``extra`` names further entries the
    command owns (retarget's part folders).
    """
    from capture.io.outdir import OutLock, check_no_links, clean_temp_files, make_out_dir

    out = make_out_dir(Path(out))
    lock = OutLock(out, what).acquire()
    try:
        finish_swap(out, extra)
        owned = OWNED + extra + HIDDEN
        check_no_links(out, owned)
        clean_temp_files(out, owned)
        mode = _claim_mode(out, take_id, overwrite)
        work = out
        staging = out / STAGING
        if mode == "replace":
            work = staging
            prev = read_json(staging / RUN_JSON)
            if staging.exists() and not (isinstance(prev, dict) and prev.get("take_id") == take_id):
                shutil.rmtree(staging)  # a replacement of another take, cut short
            staging.mkdir(exist_ok=True)
        elif staging.exists():
            shutil.rmtree(staging)      # a replacement that was given up (rerun without --overwrite)
        return RunFolder(out, work, lock, extra)
    except BaseException:
        lock.release()
        raise


def _comparable(run: dict) -> Any:
    """``run.json`` content as plain data without the output folder (a moved run folder is the same run)."""
    d = json.loads(json.dumps(run, default=str))
    if isinstance(d.get("settings"), dict):
        d["settings"].pop("out", None)
    return d


def write_run_json(out: Path, take_id: str, take_label: str, settings: dict, fingerprints: dict,
                   status: str) -> Path:
    """Write ``run.json``; a rerun of a finished run with the same settings and inputs leaves it as it is."""
    prev = read_json(Path(out) / RUN_JSON)
    same = {"format": RUN_FORMAT, "version": 1, "take_id": take_id, "take_label": take_label,
            "settings": settings, "fingerprints": fingerprints}
    if (status == "running" and prev is not None and prev.get("status") == "done"
            and _comparable({k: prev.get(k) for k in same}) == _comparable(same)):
        return Path(out) / RUN_JSON
    return write_json(Path(out) / RUN_JSON, {"format": RUN_FORMAT, "version": 1, "take_id": take_id,
                                             "take_label": take_label, "status": status, "settings": settings,
                                             "fingerprints": fingerprints})


# ------------------------------------------------------------------------------------ frame fits
STACK_BYTES = 1 << 20   # a field of frame fits at least this large is written frame by frame (capture.io.arrays)


MESH_BASIS = "mesh_basis.npy"   # a fit folder's (K, V) float32 basis of the frames' mesh maps


def save_frame_fits(path: Path, fits: Sequence[Any], basis: np.ndarray | None = None,
                    vertices_from_maps: bool = False) -> Path:
    """Stack the fields of dataclass frame fits into one NPZ (None -> NaN; strings as unicode arrays).

    A field whose every value is a :func:`capture.fit.records.repeated_rows` view (one row repeated: the
    2D fit's coefficients while F_W is zero) is stored as ``NAME@row`` (n, E) and ``NAME@rows`` (n,), and
    read back as such views.

    ``basis`` (the actor's features, :func:`models.fit_state.mesh_basis`): where every fit's ``vertices`` are
    exactly :func:`models.mesh_map.map_vertices` of its ``mesh_map`` and this basis (checked frame by frame),
    the vertices are not stored (113 KB a frame at 9,409 vertices against the map's 960 bytes at 24
    expressions): the basis goes once into the folder (:data:`MESH_BASIS`) and :func:`load_frame_fits` makes
    them again, to the bit. ``vertices_from_maps``: the caller made every fit's vertices that way (a streamed run
    as it receives the fits' maps), so they are not made again to check it (0.2 ms a frame at 9,409 vertices)."""
    if not fits:
        raise ValueError("no frame fits to save")
    drop = basis is not None and ((vertices_from_maps and _has_maps(fits, basis)) or _maps_make_vertices(fits, basis))
    if drop:
        _save_basis(Path(path).parent / MESH_BASIS, basis)
    arrays: dict[str, np.ndarray] = {}
    for f in dataclasses.fields(fits[0]):
        if drop and f.name == "vertices":
            continue
        values = [getattr(x, f.name) for x in fits]
        if all(v is None for v in values):
            continue
        if any(isinstance(v, str) for v in values):
            arrays[f.name] = np.array(["" if v is None else str(v) for v in values])
            continue
        arrs = [None if v is None else np.asarray(_to_numpy(v)) for v in values]
        rows = stored_rows(f.name, arrs) if all(is_repeated_rows(a) for a in arrs) else None
        if rows is not None:                            # one row per frame, and how often it repeats
            arrays.update(rows)
            continue
        ref = next(a for a in arrs if a is not None)
        if any(a is None for a in arrs):
            arrs = [np.full(ref.shape, np.nan) if a is None else a.astype(np.float64) for a in arrs]
        big = sum(a.nbytes for a in arrs) >= STACK_BYTES and len({(a.dtype, a.shape) for a in arrs}) == 1
        arrays[f.name] = arrs if big else np.stack(arrs)     # big: written row by row, never stacked
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            write_npz(fh, arrays)       # the frames' rows, not stacked first
    return Path(path)


def _has_maps(fits: Sequence[Any], basis: np.ndarray) -> bool:
    """Has every fit a float32 ``mesh_map`` of ``basis``'s features and ``vertices`` of its points?"""
    for f in fits:
        m, v = getattr(f, "mesh_map", None), getattr(f, "vertices", None)
        if m is None or v is None or m.dtype != np.float32 or m.shape != (3, basis.shape[0]) \
                or v.shape != (basis.shape[1], 3):
            return False
    return True


def _maps_make_vertices(fits: Sequence[Any], basis: np.ndarray) -> bool:
    """Does every fit's ``mesh_map`` give its ``vertices`` bit for bit (0.2 ms a frame at 9,409 vertices)?"""
    from models.mesh_map import map_vertices

    return _has_maps(fits, basis) and all(np.array_equal(map_vertices(f.mesh_map, basis), f.vertices) for f in fits)


def _save_basis(path: Path, basis: np.ndarray) -> None:
    """Write a fit folder's mesh basis once (atomically); one already there must be the same."""
    if path.is_file():
        if not np.array_equal(_load_basis(path), basis):
            raise ValueError(f"{path} holds another actor's mesh basis")   # a fit folder is keyed by its actor
        return
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.ascontiguousarray(basis, np.float32), allow_pickle=False)


def _load_basis(path: Path) -> np.ndarray:
    st = Path(path).stat()
    return _read_basis(str(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=4)
def _read_basis(path: str, mtime_ns: int, size: int) -> np.ndarray:
    """A fit folder's basis (read once per file version: every chunk of a fit uses it)."""
    b = np.load(path, allow_pickle=False)
    if b.dtype != np.float32 or b.ndim != 2:
        raise ValueError(f"{path}: not a (K, V) float32 mesh basis")
    b.setflags(write=False)
    return b


def _to_numpy(v):
    if hasattr(v, "detach"):
        return v.detach().cpu().numpy()
    return v


def load_frame_fits(path: Path, cls, fields: Iterable[str] | None = None) -> list[Any]:
    """The frame fits saved by :func:`save_frame_fits`, as instances of the dataclass ``cls`` (``fields``:
    only these are read, the others are None; ``frame`` always)."""
    from capture.io.arrays import load_npz

    want = None if fields is None else {"frame", *fields} | ({"mesh_map"} if "vertices" in fields else set())
    only = None if want is None else {k + s for k in want for s in ("", ROW_SUFFIX, ROWS_SUFFIX)}
    g = load_npz(path, "fit cache", "delete it (or rerun with --overwrite) to fit again", only=only)
    n = len(next(iter(g.values()))) if g else 0
    names = {f.name for f in dataclasses.fields(cls)}
    rows = {k[:-len(ROW_SUFFIX)] for k in g if k.endswith(ROW_SUFFIX)}
    known = names | {k + s for k in rows & names for s in (ROW_SUFFIX, ROWS_SUFFIX)}
    if not n or any(k not in known or v.ndim == 0 or len(v) != n for k, v in g.items()) \
            or any(k + ROWS_SUFFIX not in g or g[k + ROW_SUFFIX].ndim != 2 or (g[k + ROWS_SUFFIX] < 1).any()
                   for k in rows):
        raise CaptureError(f"fit cache {path} does not hold frame fits of one length; delete it (or rerun with "
                           f"--overwrite) to fit again")
    if "vertices" in names and "vertices" not in g and "mesh_map" in g and (fields is None or "vertices" in fields):
        g = dict(g)
        g["vertices"] = _vertices_from_maps(Path(path), g["mesh_map"])
        if fields is not None and "mesh_map" not in fields:
            del g["mesh_map"]
    out = []
    for i in range(n):
        kw = {}
        for f in dataclasses.fields(cls):
            if f.name in rows:
                row = g[f.name + ROW_SUFFIX][i]
                kw[f.name] = np.broadcast_to(row, (int(g[f.name + ROWS_SUFFIX][i]), len(row)))
                continue
            if f.name not in g:
                kw[f.name] = None
                continue
            v = g[f.name][i]
            if v.dtype.kind == "U":
                v = str(v)
            elif v.ndim == 0:
                v = v.item()
            kw[f.name] = v
        out.append(cls(**kw))
    return out


def _vertices_from_maps(path: Path, maps: np.ndarray) -> list[np.ndarray]:
    """The vertices of a chunk stored without them (:func:`save_frame_fits`' ``basis``)."""
    from models.mesh_map import map_vertices

    bpath = path.parent / MESH_BASIS
    try:
        basis = _load_basis(bpath)
        if maps.ndim != 3 or maps.shape[1:] != (3, basis.shape[0]) or maps.dtype != np.float32:
            raise ValueError(f"mesh maps {maps.dtype} {maps.shape} do not fit a basis {basis.shape}")
    except (OSError, ValueError) as exc:
        raise CaptureError(f"fit cache {path}: its meshes need {bpath.name} beside it ({exc}); delete the fit "
                           f"folder (or rerun with --overwrite) to fit again") from None
    return [map_vertices(m, basis) for m in maps]


def frames_of(fits: Iterable[Any]) -> list[int]:
    return [int(f.frame) for f in fits]
