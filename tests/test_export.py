"""Exporters of a run directory: every format round-trips through its reader (trimesh, USD, NumPy,
PyAV/OpenCV), unknown formats are one-line errors, and an aborted export leaves nothing half-written."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh

from calib.camera import Camera
from capture.io.errors import CaptureError
from capture.export import (
    CAMERA_TO_USD,
    EXPORTERS,
    STATUSES,
    ExportContext,
    ExportOptions,
    open_exporters,
    parse_formats,
)
from capture.export.overlay import project

FPS = 24.0
T = 12
W, H = 160, 120
L, E, F_CODE = 5, 4, 6


@dataclass
class Fit:
    frame: int
    head_R: np.ndarray
    head_t: np.ndarray
    jaw_R: np.ndarray
    jaw_t: np.ndarray
    code: np.ndarray
    coefficients_landmarks: np.ndarray
    vertices: np.ndarray
    landmarks_fit: np.ndarray
    reprojection_rms_px: float
    status: str


@dataclass
class Det:
    points: np.ndarray
    confidence: np.ndarray | None
    face_found: bool


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


@pytest.fixture(scope="module")
def take():
    """An icosphere head (radius 40 mm) turning and moving 600 mm in front of the camera."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    template = np.asarray(sphere.vertices, np.float64)
    faces = np.asarray(sphere.faces, np.int64)
    cam = Camera(K=[[150.0, 0, (W - 1) / 2], [0, 150.0, (H - 1) / 2], [0, 0, 1]],
                 dist=[-0.05, 0.01, 0.0, 0.0, 0.0], image_size=(W, H))
    rng = np.random.default_rng(0)
    fits, dets = [], []
    lm_ids = [0, 3, 7, 11, 20]
    for j in range(T):
        R, t = rot_y(0.05 * j), np.array([2.0 * j, -1.0 * j, 600.0 + 3 * j])
        v = (template @ R.T + t).astype(np.float32)
        lm = project(v[lm_ids], cam)
        status = "skipped" if j == 5 else ("bridged" if j == 6 else "fitted")
        fits.append(Fit(frame=j, head_R=R, head_t=t, jaw_R=np.eye(3), jaw_t=np.zeros(3),
                        code=rng.normal(size=F_CODE), coefficients_landmarks=rng.normal(size=(L, E)),
                        vertices=None if status == "skipped" else v, landmarks_fit=lm,
                        reprojection_rms_px=0.1 * j, status=status))
        dets.append(Det(points=lm + 0.3, confidence=np.linspace(0.2, 1.0, L), face_found=status != "skipped"))
    ctx = ExportContext(faces=faces, fps=FPS, image_size=(W, H), camera=cam, frame_count=T, source="test take")
    return dict(fits=fits, dets=dets, ctx=ctx, faces=faces, template=template, camera=cam)


def background(j: int) -> np.ndarray:
    img = np.full((H, W, 3), 60, np.uint8)
    img[:, :, 0] = 40 + j
    return img


def run_export(formats, out_dir, take, **opts):
    ctx = take["ctx"]
    if opts:
        ctx = ExportContext(faces=ctx.faces, fps=ctx.fps, image_size=ctx.image_size, camera=ctx.camera,
                            frame_count=ctx.frame_count, options=ExportOptions(**opts))
    with open_exporters(parse_formats(formats), out_dir, ctx) as writers:
        for j, (fit, det) in enumerate(zip(take["fits"], take["dets"])):
            writers.write(fit, background(j) if writers.needs_image else None, det)
    return writers.paths


def temp_files(directory: Path) -> list[Path]:
    return [p for p in Path(directory).rglob(".*") if p.is_file()]


# -- formats ------------------------------------------------------------------------------------

def test_parse_formats():
    assert parse_formats("obj, USD,npz,obj") == ("obj", "usd", "npz")
    assert set(EXPORTERS) == {"obj", "ply", "usd", "npz", "overlay", "curves"}
    assert parse_formats("curves,obj") == ("usd", "curves", "obj")   # the rig lives in take.usdc
    with pytest.raises(CaptureError) as err:
        parse_formats("obj,fbx")
    msg = str(err.value)
    assert "fbx" in msg and "\n" not in msg and all(k in msg for k in EXPORTERS)
    with pytest.raises(CaptureError):
        parse_formats("")


# -- meshes -------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["obj", "ply"])
def test_mesh_files_load_with_template_topology(tmp_path, take, fmt):
    paths = run_export(fmt, tmp_path, take)
    fitted = [f for f in take["fits"] if f.status != "skipped"]
    assert [p.name for p in paths] == [f"frame_{f.frame:06d}.{fmt}" for f in fitted]
    for fit, p in zip(fitted, paths):
        mesh = trimesh.load(p, process=False, maintain_order=True, force="mesh")
        assert mesh.vertices.shape == fit.vertices.shape
        np.testing.assert_array_equal(mesh.faces, take["faces"])
        np.testing.assert_allclose(mesh.vertices, fit.vertices, atol=1e-4)
    assert not (tmp_path / "meshes" / f"frame_000005.{fmt}").exists()  # skipped frame: no mesh
    assert temp_files(tmp_path) == []


@pytest.mark.parametrize("fmt", ["obj", "ply"])
def test_mesh_codecs_keep_unreferenced_vertices(tmp_path, fmt):
    from capture.export.mesh_files import CODECS

    rng = np.random.default_rng(1)
    v, f = rng.normal(size=(10, 3)) * 100, np.array([[0, 1, 2], [2, 3, 4]])
    block, encode = CODECS[fmt]
    path = tmp_path / f"m.{fmt}"
    path.write_bytes(encode(v, block(f), "two lines\nof header"))
    mesh = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    assert mesh.vertices.shape == (10, 3)
    np.testing.assert_array_equal(mesh.faces, f)
    np.testing.assert_allclose(mesh.vertices, v, atol=1e-4 if fmt == "obj" else 1e-4 * np.abs(v).max())


def test_mesh_head_frame_gives_the_template(tmp_path, take):
    paths = run_export("ply", tmp_path, take, mesh_frame="head")
    for p in paths:
        mesh = trimesh.load(p, process=False, force="mesh")
        np.testing.assert_allclose(mesh.vertices, take["template"], atol=1e-3)


def test_mesh_resume_skips_existing_unless_overwrite(tmp_path, take):
    run_export("obj", tmp_path, take)
    target = tmp_path / "meshes" / "frame_000003.obj"
    target.write_text("stale")
    (tmp_path / "meshes" / "frame_000004.obj").unlink()
    run_export("obj", tmp_path, take)
    assert target.read_text() == "stale"                                   # kept
    assert (tmp_path / "meshes" / "frame_000004.obj").stat().st_size > 0  # missing one rewritten
    run_export("obj", tmp_path, take, overwrite=True)
    assert trimesh.load(target, process=False, force="mesh").vertices.shape[0] == len(take["template"])


# -- USD ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("ascii_", [False, True])
def test_usd_time_samples(tmp_path, take, ascii_):
    from pxr import Usd, UsdGeom

    (path,) = run_export("usd", tmp_path, take, usd_ascii=ascii_, usd_save_every=4)
    assert path.name == ("take.usda" if ascii_ else "take.usdc") and path.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]          # no temporary left
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == FPS and stage.GetFramesPerSecond() == FPS
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, T - 1)
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Take/Face"))
    assert stage.GetDefaultPrim().GetPath() == "/Take"
    points = mesh.GetPointsAttr()
    fitted = [f.frame for f in take["fits"] if f.status != "skipped"]
    assert points.GetTimeSamples() == [float(j) for j in fitted]
    assert mesh.GetExtentAttr().GetTimeSamples() == [float(j) for j in fitted]
    assert not mesh.GetFaceVertexIndicesAttr().GetTimeSamples()               # topology once
    np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), take["faces"])
    for j in (0, 6, 11):
        got = np.asarray(points.Get(Usd.TimeCode(j)))
        want = take["fits"][j].vertices @ CAMERA_TO_USD.T
        np.testing.assert_allclose(got, want, atol=1e-3)
        ext = np.asarray(mesh.GetExtentAttr().Get(Usd.TimeCode(j)))
        np.testing.assert_allclose(ext, [want.min(0), want.max(0)], atol=1e-3)
    # OpenCV y down -> USD y up; z forward -> the face is at negative z in front of a USD camera
    p0 = np.asarray(points.Get(Usd.TimeCode(11)))
    assert p0[:, 2].max() < 0 and p0[:, 1].mean() > 0
    vis = mesh.GetVisibilityAttr()
    assert vis.Get(Usd.TimeCode(5)) == UsdGeom.Tokens.invisible
    assert vis.Get(Usd.TimeCode(4)) == vis.Get(Usd.TimeCode(6)) == UsdGeom.Tokens.inherited


# -- NPZ ----------------------------------------------------------------------------------------

def test_npz_keys_shapes_dtypes(tmp_path, take):
    paths = run_export("npz", tmp_path, take)
    assert sorted(p.name for p in paths) == ["landmarks.npz", "params.npz"]
    with np.load(tmp_path / "params.npz", allow_pickle=False) as z:
        want = {"frame_index": ((T,), np.int64), "time_s": ((T,), np.float64), "head_R": ((T, 3, 3), np.float64),
                "head_t_mm": ((T, 3), np.float64), "jaw_R": ((T, 3, 3), np.float64),
                "jaw_t_mm": ((T, 3), np.float64), "codes": ((T, F_CODE), np.float32),
                "coefficients_landmarks": ((T, L, E), np.float32), "reprojection_rms_px": ((T,), np.float64),
                "coefficients_base": ((T, E), np.float32),
                "status": ((T,), np.int8), "status_names": ((3,), np.dtype("<U7")), "fps": ((), np.float64),
                "image_size": ((2,), np.int64)}
        assert set(z.files) == set(want)
        for k, (shape, dtype) in want.items():
            assert (z[k].shape, z[k].dtype) == (shape, np.dtype(dtype)), k
        np.testing.assert_array_equal(z["frame_index"], np.arange(T))
        np.testing.assert_allclose(z["time_s"], np.arange(T) / FPS)
        np.testing.assert_allclose(z["head_R"][3], take["fits"][3].head_R)
        np.testing.assert_allclose(z["head_t_mm"][7], take["fits"][7].head_t)
        assert [str(z["status_names"][s]) for s in z["status"][4:7]] == ["fitted", "skipped", "bridged"]
        assert tuple(z["status_names"]) == STATUSES
        # fits without a stored base: the landmark mean (the base while F_W is zero)
        np.testing.assert_allclose(z["coefficients_base"][3], take["fits"][3].coefficients_landmarks.mean(0),
                                   rtol=1e-5)
    with np.load(tmp_path / "landmarks.npz", allow_pickle=False) as z:
        assert z["points"].shape == (T, L, 2) and z["confidence"].shape == (T, L)
        assert z["face_found"].dtype == bool and not z["face_found"][5] and z["face_found"][4]
        np.testing.assert_allclose(z["points"][2], take["dets"][2].points)
        assert z["landmarks_fit"].shape == (T, L, 2)


def _stacked(rows, dtype, shape):
    """The readable reference: np.stack of the rows, NaN for a frame without one."""
    return np.stack([np.full(shape, np.nan) if r is None else np.asarray(r, np.float64) for r in rows]).astype(dtype)


def test_npz_rows_spilled_in_blocks_equal_the_stacked_rows(tmp_path, take, monkeypatch):
    """Both archives' per-frame arrays are held a block of frames at a time and spilled to an unnamed file:
    the archives hold what np.stack of the frames' arrays gives (NaN for a frame without them; coefficients
    kept as their one repeated row or as float32), across block edges and with frames that lack an array
    before the first that has it; they read back with allow_pickle=False like any np.savez, and nothing of the
    spill is left beside them."""
    from dataclasses import replace

    from capture.export import params as params_module
    from capture.fit.records import repeated_rows

    monkeypatch.setattr(params_module.SpilledRows, "BLOCK", 3)        # T frames in several blocks, the last short
    monkeypatch.setattr(params_module._Coefficients, "BLOCK_FRAMES", 4)   # and the coefficients' one buffer reused
    rng = np.random.default_rng(5)
    fits, dets = [], []
    for j, (f, d) in enumerate(zip(take["fits"], take["dets"])):
        if j % 2:                                              # the 2D default: one row at every landmark
            f = replace(f, coefficients_landmarks=repeated_rows(np.tile(rng.normal(size=E), (L, 1))))
        if j == 4:
            f = replace(f, coefficients_landmarks=None)
        if j < 4:                                              # no fit yet: the first blocks have nothing
            f = replace(f, head_R=None, code=None, landmarks_fit=None)
        fits.append(f)
        dets.append(None if j in (1, 7) else replace(d, confidence=None) if j == 8 else d)
    writer = params_module.ParamsWriter(tmp_path, take["ctx"])
    for f, d in zip(fits, dets):
        writer.write(f, None, d)
    assert sorted(p.name for p in tmp_path.iterdir()) == []          # the spill has no name
    writer.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["landmarks.npz", "params.npz"]
    with np.load(tmp_path / "params.npz", allow_pickle=False) as z:
        np.testing.assert_array_equal(z["coefficients_landmarks"],
                                      _stacked([f.coefficients_landmarks for f in fits], np.float32, (L, E)))
        np.testing.assert_array_equal(z["head_R"], _stacked([f.head_R for f in fits], np.float64, (3, 3)))
        np.testing.assert_array_equal(z["codes"], _stacked([f.code for f in fits], np.float32, (F_CODE,)))
        np.testing.assert_array_equal(z["head_t_mm"], np.stack([f.head_t for f in fits]))
        np.testing.assert_allclose(z["coefficients_base"][1], fits[1].coefficients_landmarks[0], rtol=1e-6)
        np.testing.assert_allclose(z["coefficients_base"][2], fits[2].coefficients_landmarks.mean(0), rtol=1e-6)
        assert np.isnan(z["coefficients_base"][4]).all()
        np.testing.assert_array_equal(z["reprojection_rms_px"], [f.reprojection_rms_px for f in fits])
    with zipfile.ZipFile(tmp_path / "params.npz") as z:     # frames of their own: stored, as every member
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    with np.load(tmp_path / "landmarks.npz", allow_pickle=False) as z:
        np.testing.assert_array_equal(z["points"], _stacked([None if d is None else d.points for d in dets],
                                                            np.float64, (L, 2)))
        np.testing.assert_array_equal(z["confidence"], _stacked([None if d is None else d.confidence for d in dets],
                                                                np.float32, (L,)))
        np.testing.assert_array_equal(z["landmarks_fit"], _stacked([f.landmarks_fit for f in fits], np.float64,
                                                                   (L, 2)))
        np.testing.assert_array_equal(z["face_found"], [d is not None and d.face_found for d in dets])


def test_npz_coefficients_repeated_at_every_landmark_are_deflated(tmp_path, take):
    """The 2D default gives every landmark of a frame the same coefficients: params.npz then deflates that
    member (it repeats each row L times), reads back the same with np.load, and stores every other member."""
    from dataclasses import replace

    from capture.export import params as params_module
    from capture.fit.records import repeated_rows

    rng = np.random.default_rng(6)
    fits = [replace(f, coefficients_landmarks=repeated_rows(np.tile(rng.normal(size=E), (L, 1))))
            for f in take["fits"]]
    writer = params_module.ParamsWriter(tmp_path, take["ctx"])
    for f, d in zip(fits, take["dets"]):
        writer.write(f, None, d)
    writer.close()
    with zipfile.ZipFile(tmp_path / "params.npz") as z:
        kinds = {i.filename: i.compress_type for i in z.infolist()}
        stored = z.getinfo("coefficients_landmarks.npy")
        assert stored.compress_size < stored.file_size / 2     # 5 landmarks here: each row 5 times
    assert kinds.pop("coefficients_landmarks.npy") == zipfile.ZIP_DEFLATED
    assert set(kinds.values()) == {zipfile.ZIP_STORED}
    with np.load(tmp_path / "params.npz", allow_pickle=False) as z:
        got = z["coefficients_landmarks"]
        assert got.dtype == np.float32 and got.shape == (len(fits), L, E)
        np.testing.assert_array_equal(got, np.stack([f.coefficients_landmarks for f in fits]).astype(np.float32))


def test_npz_rows_of_another_shape_are_refused_when_they_arrive(tmp_path, take):
    from dataclasses import replace

    from capture.export.params import ParamsWriter

    writer = ParamsWriter(tmp_path, take["ctx"])
    writer.write(take["fits"][0], None, take["dets"][0])
    with pytest.raises(ValueError, match=r"frame row 1: expected shape \(5, 4\)"):
        writer.write(replace(take["fits"][1], coefficients_landmarks=np.zeros((L + 1, E))), None, take["dets"][1])
    writer.abort()


def test_npz_without_any_landmarks_fit_or_confidence_keeps_the_row_shapes(tmp_path, take):
    from dataclasses import replace

    from capture.export.params import ParamsWriter

    writer = ParamsWriter(tmp_path, take["ctx"])
    for f, d in zip(take["fits"], take["dets"]):
        writer.write(replace(f, landmarks_fit=None), None, replace(d, confidence=None))
    writer.close()
    with np.load(tmp_path / "landmarks.npz", allow_pickle=False) as z:
        assert z["landmarks_fit"].shape == (T, L, 2) and np.isnan(z["landmarks_fit"]).all()
        assert z["confidence"].shape == (T, L) and np.isnan(z["confidence"]).all()


# -- overlay ------------------------------------------------------------------------------------

def test_overlay_video(tmp_path, take):
    import av
    import cv2

    (path,) = run_export("overlay", tmp_path, take)
    assert path.name == "overlay.mp4" and temp_files(tmp_path) == []
    with av.open(str(path)) as c:
        s = c.streams.video[0]
        assert (s.codec_context.name, s.codec_context.pix_fmt) == ("h264", "yuv420p")
        frames = [f.to_ndarray(format="bgr24") for f in c.decode(video=0)]
    assert len(frames) == T and frames[0].shape == (H, W, 3)
    cap = cv2.VideoCapture(str(path))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == T and cap.get(cv2.CAP_PROP_FPS) == pytest.approx(FPS)
    cap.release()
    # the most confident detected landmark (radius 4 px, green) on frame 8
    x, y = np.round(take["dets"][8].points[-1]).astype(int)
    pix, bg = frames[8][y, x].astype(int), background(8)[y, x].astype(int)
    assert np.abs(pix - bg).sum() > 60 and pix[1] > pix[0] and pix[1] > pix[2]
    # the mesh is drawn somewhere else inside its silhouette (not on a landmark): frames differ
    # from the background well away from the text line
    assert np.abs(frames[8][40:, :].astype(int) - background(8)[40:, :].astype(int)).sum(-1).max() > 60


def test_overlay_drawn_by_threads_is_the_one_drawn_in_order(tmp_path, take, monkeypatch):
    """Frames drawn by 3 threads ahead of the encoder reach it as those drawn one by one in the caller's
    thread, in order and bit for bit, though the caller refills one image buffer for every frame. (The
    encoded videos are not compared: libx264 with its own threads does not repeat itself to the bit.)"""
    import threading

    from capture.export.overlay import OverlayWriter

    encoded: dict[int, list] = {}
    original = OverlayWriter._encode

    def record(self, out):
        encoded[self.test_threads].append(out.copy())
        original(self, out)

    monkeypatch.setattr(OverlayWriter, "_encode", record)
    for threads in (1, 3):
        out = tmp_path / str(threads)
        out.mkdir()
        writer = OverlayWriter(out, take["ctx"], threads=threads)
        writer.test_threads, encoded[threads] = threads, []
        buf = np.empty((H, W, 3), np.uint8)
        for j, (fit, det) in enumerate(zip(take["fits"], take["dets"])):
            buf[...] = background(j)
            writer.write(fit, buf, det)
            if threads > 1:
                assert len(writer._drawing) <= 2 * threads
                assert len(encoded[threads]) == max(0, j + 1 - 2 * threads)   # drawn ahead, not all held
        (path,) = writer.close()
        assert path.is_file() and temp_files(out) == []
    assert len(encoded[1]) == len(encoded[3]) == T
    for a, b in zip(encoded[1], encoded[3]):
        np.testing.assert_array_equal(a, b)
    assert not any(np.array_equal(a, b) for a, b in zip(encoded[1], encoded[1][1:]))   # frames differ
    assert not [t for t in threading.enumerate() if t.name.startswith("overlay-draw")]


def test_overlay_abort_while_drawing_leaves_nothing(tmp_path, take):
    import threading

    from capture.export.overlay import OverlayWriter

    writer = OverlayWriter(tmp_path, take["ctx"], threads=2)
    for j, (fit, det) in enumerate(zip(take["fits"][:5], take["dets"])):
        writer.write(fit, background(j), det)
    writer.abort()
    assert list(tmp_path.iterdir()) == []
    assert not [t for t in threading.enumerate() if t.name.startswith("overlay-draw")]


def test_overlay_needs_images(tmp_path, take):
    writer = EXPORTERS["overlay"].open(tmp_path, take["ctx"])
    with pytest.raises(ValueError, match="needs the video frame"):
        writer.write(take["fits"][0], None)
    writer.abort()
    assert list(tmp_path.iterdir()) == []


# -- abort --------------------------------------------------------------------------------------

def test_failure_midway_leaves_no_temporaries(tmp_path, take):
    from pxr import Usd

    # a finished export from an earlier run must survive an aborted rerun
    run_export("usd", tmp_path, take)
    before = (tmp_path / "take.usdc").read_bytes()
    ctx = take["ctx"]
    with pytest.raises(RuntimeError, match="boom"):
        with open_exporters(parse_formats("obj,ply,usd,npz,overlay"), tmp_path, ctx) as writers:
            for j, (fit, det) in enumerate(zip(take["fits"], take["dets"])):
                if j == 7:
                    raise RuntimeError("boom")
                writers.write(fit, background(j), det)
    assert temp_files(tmp_path) == []
    names = {p.name for p in tmp_path.iterdir()}
    assert names == {"take.usdc", "meshes"}                    # no half-written MP4 or NPZ
    assert (tmp_path / "take.usdc").read_bytes() == before     # the earlier USD is untouched
    assert len(Usd.Stage.Open(str(tmp_path / "take.usdc")).GetPrimAtPath("/Take/Face")
               .GetAttribute("points").GetTimeSamples()) == T - 1
    # per-frame meshes written before the failure are complete files
    for p in (tmp_path / "meshes").iterdir():
        assert trimesh.load(p, process=False, force="mesh").vertices.shape[0] == len(take["template"])


def test_bad_vertex_shape_is_reported(tmp_path, take):
    fit = take["fits"][0]
    bad = Fit(**{**fit.__dict__, "vertices": fit.vertices[:-1]})
    writer = EXPORTERS["obj"].open(tmp_path, take["ctx"])
    writer.write(fit)
    with pytest.raises(ValueError, match=r"expected \(162, 3\)"):
        writer.write(Fit(**{**bad.__dict__, "frame": 1}))
