"""Bad input across every command: exit status 2, one line on stderr, no traceback, nothing damaged.

Each case builds its bad input in its own folder (copies of a tiny actor, take and finished run shared
at module scope), runs the command in-process through :func:`capture.cli.main` and checks:
* the exit status is 2 and stderr is exactly one line ``capture: error: ...`` (no traceback);
* every file that existed before (the shared fixtures and the case's own files) is unchanged.
A few cases run as subprocesses (library log noise reaches the real stderr there), and the damage
tests check what the issue found: ``--overwrite`` keeps the old run until the new one succeeded,
no write through a symbolic link, temp files of a killed run removed, a lock, and a kill at
several points resumes to identical outputs.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from capture.cli import main
from tests.tiny_actor import synth_tiny_take, train_tiny_actor

REPO = Path(__file__).resolve().parents[1]
FAST = ["--iterations", "5", "--window", "8", "--threads", "1", "--no-progress"]
N_FRAMES = 8


@dataclass
class Env:
    root: Path
    actor: Path
    take: Path
    run: Path

    @property
    def video(self) -> Path:
        return self.take / "take.mp4"

    @property
    def camera(self) -> Path:
        return self.take / "camera.json"


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> Env:
    """A tiny actor (30 iterations, width 32), an 8-frame 320x240 take of it, and a finished run."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("bad")
    actor = train_tiny_actor(root, iterations=30, width=32)
    take = synth_tiny_take(actor, root / "take", frames=N_FRAMES, landmarks=100)
    run = root / "run"
    assert main(["run", str(take / "take.mp4"), "--actor", str(actor), "--camera", str(take / "camera.json"),
                 "--out", str(run), *FAST]) == 0
    yield Env(root, actor, take, run)
    torch.set_num_threads(threads)


def snapshot(*roots: Path) -> dict[Path, tuple[int, int, bytes]]:
    """Every file under ``roots``: (size, mtime_ns, first bytes) -- a changed file changes one of them."""
    out = {}
    for r in roots:
        for p in Path(r).rglob("*"):
            if p.name == ".capture.lock":   # a run's lock notes its process; it is not an output
                continue
            if p.is_file() and not p.is_symlink():
                st = p.stat()
                with open(p, "rb") as fh:
                    out[p] = (st.st_size, st.st_mtime_ns, fh.read(64))
    return out


def one_line_error(rc: int, err: str) -> str:
    lines = err.strip().splitlines()
    assert rc == 2, (rc, err)
    assert "Traceback" not in err, err
    assert len(lines) == 1, lines
    assert lines[0].startswith("capture: error: "), lines
    return lines[0]


# ------------------------------------------------------------------------------------------ builders
def run_args(e: Env, video=None, actor=None, camera="default", out=None, *extra) -> list[str]:
    a = ["run", str(video or e.video), "--actor", str(actor or e.actor)]
    if camera is not None:
        a += ["--camera", str(e.camera if camera == "default" else camera)]
    return a + (["--out", str(out)] if out else []) + [str(x) for x in extra] + FAST


def copy_actor(e: Env, d: Path, name: str = "broken") -> Path:
    dst = d / "actors" / name
    shutil.copytree(e.actor, dst)
    return dst


def edit_json(path: Path, fn: Callable[[dict], object]) -> None:
    obj = json.loads(path.read_text())
    path.write_text(json.dumps(fn(obj)))


def cam_json(e: Env, d: Path, fn=None, text: str | None = None, name: str = "cam.json") -> Path:
    p = d / name
    if text is not None:
        p.write_text(text)
        return p
    obj = json.loads(e.camera.read_text())
    res = fn(obj) if fn else obj
    p.write_text(json.dumps(obj if res is None else res))
    return p


def set_k(i, j, v):
    def fn(o):
        o["K"][i][j] = v
    return fn


def cam_yaml(d: Path, body: str, name: str = "cam.yaml") -> Path:
    p = d / name
    p.write_text("%YAML:1.0\n---\n" + body)
    return p


K_YAML = ("camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
          "   data: [ 277.1, 0., 159.5, 0., 277.1, 119.5, 0., 0., 1. ]\n")
D_YAML = "distortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
WH_YAML = "image_width: 320\nimage_height: 240\n"


def det_copy(e: Env, d: Path, spec_fn=None, onnx_bytes: bytes | None = None, spec_text: str | None = None) -> Path:
    src = next((e.take / "detector").glob("*.onnx"))
    (d / "det").mkdir()
    onnx = d / "det" / src.name
    if onnx_bytes is None:
        shutil.copy(src, onnx)
    else:
        onnx.write_bytes(onnx_bytes)
    spec = onnx.with_suffix(".json")
    if spec_text is not None:
        spec.write_bytes(spec_text if isinstance(spec_text, bytes) else spec_text.encode())
    elif spec_fn is not None:
        obj = json.loads(src.with_suffix(".json").read_text())
        res = spec_fn(obj)
        spec.write_text(json.dumps(obj if res is None else res))
    else:
        shutil.copy(src.with_suffix(".json"), spec)
    return onnx


def run_copy(e: Env, d: Path) -> Path:
    out = d / "run"
    shutil.copytree(e.run, out)
    return out


def first_chunk(run: Path) -> Path:
    return next(run.glob("fit/*/frames_*.npz"))


def crafted_npz_big_header(path: Path) -> None:
    """An NPZ whose one member declares a 10^12-element array but stores a few bytes."""
    hdr = {"descr": "<f8", "fortran_order": False, "shape": (10 ** 12,)}
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, hdr)
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("points.npy", buf.getvalue() + b"\0" * 64)


def crafted_npz_compressed(path: Path) -> None:
    np.savez_compressed(path, points=np.zeros(50_000_000, np.uint8))   # 50 MB in ~50 kB


def crafted_npz_object(path: Path) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, points=np.array([{"a": 1}, None], dtype=object))


def weights_other_width(e: Env, d: Path) -> Path:
    a = copy_actor(e, d)
    from safetensors.torch import load_file, save_file

    t = load_file(str(a / "weights.safetensors"))
    k = next(k for k, v in t.items() if k.startswith("model.") and v.ndim == 2)
    t[k] = t[k][: t[k].shape[0] // 2].contiguous()
    save_file(t, str(a / "weights.safetensors"))
    return a


def weights_nan(e: Env, d: Path) -> Path:
    a = copy_actor(e, d)
    from safetensors.torch import load_file, save_file

    t = load_file(str(a / "weights.safetensors"))
    k = next(k for k, v in t.items() if k.startswith("model.") and v.is_floating_point())
    t[k] = t[k].clone()
    t[k].view(-1)[0] = float("nan")
    save_file(t, str(a / "weights.safetensors"))
    return a


def weights_drop(e: Env, d: Path, key: str) -> Path:
    a = copy_actor(e, d)
    from safetensors.torch import load_file, save_file

    t = load_file(str(a / "weights.safetensors"))
    t.pop(key)
    save_file(t, str(a / "weights.safetensors"))
    return a


def actor_with(e: Env, d: Path, fn: Callable[[Path], None]) -> Path:
    a = copy_actor(e, d)
    fn(a)
    return a


def meta_edit(fn):
    return lambda a: edit_json(a / "actor.json", fn)


def _del(key):
    def fn(o):
        o.pop(key)
        return o
    return fn


def _set(key, value):
    def fn(o):
        o[key] = value
        return o
    return fn


def shapes_dir(e: Env, d: Path, fn=None, name="shapes") -> Path:
    dst = d / name
    shutil.copytree(e.root / "shapes", dst)
    if fn:
        fn(dst)
    return dst


def meshes_dir(e: Env, d: Path, n: int = 3, scale: float = 1.0, fn=None) -> Path:
    import trimesh

    z = np.load(e.take / "truth_meshes.npz")
    folder = d / "scans"
    folder.mkdir()
    for i in range(n):
        trimesh.Trimesh(z["vertices"][i] * scale, z["faces"], process=False).export(folder / f"scan_{i:03d}.obj")
    if fn:
        fn(folder)
    return folder


def write_file(d: Path, text: str | bytes, name: str) -> Path:
    p = d / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text)
    return p


def shoot(d: Path, text: str | bytes, name: str = "shoot.toml") -> Path:
    return write_file(d, text, name)


def region(d: Path, text: str | bytes, name: str = "region.json") -> Path:
    return write_file(d, text, name)


def edit_args(e: Env, d: Path, reg=None, *extra, actor=None) -> list[str]:
    reg = reg if reg is not None else region(d, "[1, 2, 3]")
    return ["actor", "edit", str(actor or e.actor), "--thickness-scale", "1.2", "--region", str(reg),
            "--out", str(d / "actors" / "edited"), *[str(x) for x in extra]]


def train_args(shapes, d: Path, *extra) -> list[str]:
    return ["actor", "train", str(d / "actors" / "new"), "--shapes", str(shapes), "--iterations", "2",
            "--no-progress", *[str(x) for x in extra]]


def fit3d_args(e: Env, folder, d: Path, *extra) -> list[str]:
    return ["fit3d", str(folder), "--actor", str(e.actor), "--out", str(d / "f3d"), *[str(x) for x in extra], *FAST]


def synth_args(e: Env, d: Path, *extra, actor=None) -> list[str]:
    return ["synth", "--actor", str(actor or e.actor), "--out", str(d / "synth"), "--frames", "2", "--size", "64x48",
            "--no-progress", *[str(x) for x in extra]]


def retarget_args(e: Env, d: Path, run=None, *extra) -> list[str]:
    return ["retarget", str(run or e.run), "--to", str(e.actor), "--out", str(d / "rt"), "--no-progress",
            *[str(x) for x in extra]]


def crafted_window(e: Env, d: Path, how: str) -> Path:
    r = run_copy(e, d)
    w = sorted(r.glob("fit/*/windows/win_*.pt"))[0]
    if how == "pickle":
        import pickle

        class Boom:
            def __reduce__(self):
                return (os.system, ("touch /tmp/capture_pwned",))

        w.write_bytes(pickle.dumps(Boom()))
    elif how == "garbage":
        w.write_bytes(b"\x00garbage" * 10)
    elif how == "truncated":
        w.write_bytes(w.read_bytes()[:100])
    elif how == "not_tensors":
        import torch

        torch.save({"codes": [1, 2, 3]}, w)
    return r


def video_folder(d: Path) -> Path:
    p = d / "take.mp4"
    p.mkdir()
    return p


def truncated_video(e: Env, d: Path) -> Path:
    p = d / "cut.mp4"
    p.write_bytes(e.video.read_bytes()[:3000])
    return p


def locked_out(e: Env, d: Path):
    from capture.io.outdir import OutLock

    out = d / "locked"
    out.mkdir()
    lock = OutLock(out).acquire()
    d.joinpath(".keep_lock").write_text("")
    _LOCKS.append(lock)
    return out


_LOCKS: list = []


def another_take_out(e: Env, d: Path) -> Path:
    r = run_copy(e, d)
    edit_json(r / "run.json", _set("take_id", "another"))
    return r


def link_out(e: Env, d: Path, name: str) -> Path:
    out = d / "linked"
    out.mkdir()
    (d / "elsewhere").mkdir()
    (out / name).symlink_to(d / "elsewhere")
    return out


# ------------------------------------------------------------------------------------------- cases
CAM_CASES = {
    "cam_missing": lambda e, d: run_args(e, camera=d / "nope.json"),
    "cam_dir": lambda e, d: run_args(e, camera=d),
    "cam_suffix": lambda e, d: run_args(e, camera=cam_json(e, d, name="cam.txt")),
    "cam_json_invalid": lambda e, d: run_args(e, camera=cam_json(e, d, text="{nope")),
    "cam_json_list": lambda e, d: run_args(e, camera=cam_json(e, d, text="[1, 2]")),
    "cam_json_not_utf8": lambda e, d: run_args(e, camera=region(d, b"\xff\xfe{", "cam.json")),
    "cam_missing_K": lambda e, d: run_args(e, camera=cam_json(e, d, _del("K"))),
    "cam_K_2x2": lambda e, d: run_args(e, camera=cam_json(e, d, _set("K", [[1, 0], [0, 1]]))),
    "cam_K_strings": lambda e, d: run_args(e, camera=cam_json(e, d, _set("K", "eye"))),
    "cam_K_nan": lambda e, d: run_args(e, camera=cam_json(e, d, set_k(0, 0, float("nan")))),
    "cam_dist_inf": lambda e, d: run_args(e, camera=cam_json(e, d, _set("dist", [float("inf"), 0, 0, 0]))),
    "cam_dist_3": lambda e, d: run_args(e, camera=cam_json(e, d, _set("dist", [0.1, 0.0, 0.0]))),
    "cam_dist_strings": lambda e, d: run_args(e, camera=cam_json(e, d, _set("dist", ["a"]))),
    "cam_size_strings": lambda e, d: run_args(e, camera=cam_json(e, d, _set("image_size", ["320", "240"]))),
    "cam_size_one": lambda e, d: run_args(e, camera=cam_json(e, d, _set("image_size", [320]))),
    "cam_unknown_key": lambda e, d: run_args(e, camera=cam_json(e, d, _set("focal", 3))),
    "cam_version": lambda e, d: run_args(e, camera=cam_json(e, d, _set("version", 9))),
    "cam_format": lambda e, d: run_args(e, camera=cam_json(e, d, _set("format", "other"))),
    "cam_fx_negative": lambda e, d: run_args(e, camera=cam_json(e, d, set_k(0, 0, -277.0))),
    "cam_fx_tiny": lambda e, d: run_args(e, camera=cam_json(e, d, set_k(0, 0, 1e-300))),
    "cam_fx_huge": lambda e, d: run_args(e, camera=cam_json(e, d, set_k(0, 0, 1e12))),
    "cam_aspect": lambda e, d: run_args(e, camera=cam_json(e, d, set_k(1, 1, 277.0 * 10))),
    "cam_skew": lambda e, d: run_args(e, camera=cam_json(e, d, set_k(0, 1, 3.0))),
    "cam_pp_outside": lambda e, d: run_args(e, camera=cam_json(e, d, lambda o: (set_k(0, 2, -5000.0)(o),
                                                                                 set_k(1, 2, 9000.0)(o)) and None)),
    "cam_pp_outside_x": lambda e, d: run_args(e, camera=cam_json(e, d, set_k(0, 2, 900.0))),
    "cam_k_huge": lambda e, d: run_args(e, camera=cam_json(e, d, _set("dist", [1e6, 1e6, 0, 0, 0]))),
    "cam_rms_negative": lambda e, d: run_args(e, camera=cam_json(e, d, _set("rms_px", -1))),
    "cam_other_aspect": lambda e, d: run_args(e, camera=cam_json(e, d, _set("image_size", [640, 360]))),
    "cam_empty_file": lambda e, d: run_args(e, camera=cam_json(e, d, text="")),
    "yaml_scalar_K": lambda e, d: run_args(e, camera=cam_yaml(d, "camera_matrix: 5\n" + D_YAML + WH_YAML)),
    "yaml_string_K": lambda e, d: run_args(e, camera=cam_yaml(d, "camera_matrix: eye\n" + D_YAML + WH_YAML)),
    "yaml_missing_dist": lambda e, d: run_args(e, camera=cam_yaml(d, K_YAML + WH_YAML)),
    "yaml_width_string": lambda e, d: run_args(e, camera=cam_yaml(d, K_YAML + D_YAML +
                                                                  "image_width: wide\nimage_height: 240\n")),
    "yaml_width_float": lambda e, d: run_args(e, camera=cam_yaml(d, K_YAML + D_YAML +
                                                                 "image_width: 320.5\nimage_height: 240\n")),
    "yaml_K_2x2": lambda e, d: run_args(e, camera=cam_yaml(d, "camera_matrix: !!opencv-matrix\n   rows: 2\n"
                                                              "   cols: 2\n   dt: d\n   data: [1., 0., 0., 1.]\n"
                                                           + D_YAML + WH_YAML)),
    "yaml_garbage": lambda e, d: run_args(e, camera=region(d, "{{{: : :\n\t- [", "cam.yaml")),
    "yaml_empty": lambda e, d: run_args(e, camera=region(d, "", "cam.yaml")),
    "xml_garbage": lambda e, d: run_args(e, camera=region(d, "<opencv_storage><camera_matrix>", "cam.xml")),
    "yaml_pp_outside": lambda e, d: run_args(e, camera=cam_yaml(d, K_YAML.replace("159.5", "-5000.") + D_YAML +
                                                                WH_YAML)),
    "yaml_rms_string": lambda e, d: run_args(e, camera=cam_yaml(d, K_YAML + D_YAML + WH_YAML +
                                                                "avg_reprojection_error: low\n")),
}

ACTOR_CASES = {
    "actor_unknown": lambda e, d: run_args(e, actor="nosuch"),
    "actor_is_file": lambda e, d: run_args(e, actor=region(d, "x", "actor.txt")),
    "actor_json_list": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "actor.json").write_text("[]"))),
    "actor_json_invalid": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "actor.json").write_text("{"))),
    "actor_json_not_utf8": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "actor.json").write_bytes(
        b"\xff\xfe\x00{"))),
    "actor_json_no_model": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(_del("model")))),
    "actor_json_model_list": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(_set("model", [1])))),
    "actor_json_model_unknown": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(
        lambda o: {**o, "model": {**o["model"], "nonsense": 1}}))),
    "actor_json_shapes_null": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(_set("shape_names", None)))),
    "actor_json_shapes_short": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(_set("shape_names", ["n"])))),
    "actor_json_version": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(_set("format_version", 7)))),
    "actor_json_name_int": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(_set("name", 5)))),
    "actor_json_nvertices": lambda e, d: run_args(e, actor=actor_with(e, d, meta_edit(_set("n_vertices", 12)))),
    "weights_missing": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "weights.safetensors").unlink())),
    "weights_truncated": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "weights.safetensors")
                                                                   .write_bytes((a / "weights.safetensors")
                                                                                .read_bytes()[:500]))),
    "weights_garbage": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "weights.safetensors")
                                                                 .write_bytes(b"\x00" * 64))),
    "weights_other_width": lambda e, d: run_args(e, actor=weights_other_width(e, d)),
    "weights_nan": lambda e, d: run_args(e, actor=weights_nan(e, d)),
    "weights_no_jaw": lambda e, d: run_args(e, actor=weights_drop(e, d, "jaw_rot6d")),
    "template_missing": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "template.ply").unlink())),
    "template_corrupt": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "template.ply")
                                                                  .write_bytes(b"ply\nformat nonsense\n"))),
    "template_empty": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: (a / "template.ply").write_bytes(b""))),
    "actor_no_embedding": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: shutil.rmtree(a / "landmarks"))),
    "embedding_garbage": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: [
        p.write_text("{garbage") for p in (a / "landmarks").glob("*.json")])),
    "embedding_list": lambda e, d: run_args(e, actor=actor_with(e, d, lambda a: [
        p.write_text("[]") for p in (a / "landmarks").glob("*.json")])),
}

DET_CASES = {
    "det_missing": lambda e, d: run_args(e, None, None, "default", None, "--detector", d / "no.onnx"),
    "det_is_dir": lambda e, d: run_args(e, None, None, "default", None, "--detector", d),
    "det_spec_missing": lambda e, d: run_args(e, None, None, "default", None, "--detector",
                                              (lambda o: (o.with_suffix(".json").unlink(), o)[1])(det_copy(e, d))),
    "det_spec_invalid": lambda e, d: run_args(e, None, None, "default", None, "--detector",
                                              det_copy(e, d, spec_text="{nope")),
    "det_spec_list": lambda e, d: run_args(e, None, None, "default", None, "--detector", det_copy(e, d, spec_text="[]")),
    "det_spec_not_utf8": lambda e, d: run_args(e, None, None, "default", None, "--detector",
                                               det_copy(e, d, spec_text=b"\xff\xfe{}")),
    "det_spec_huge_input": lambda e, d: run_args(e, None, None, "default", None, "--detector", det_copy(
        e, d, lambda o: o["input"].__setitem__("size", [30000, 30000]))),
    "det_spec_size_mismatch": lambda e, d: run_args(e, None, None, "default", None, "--detector", det_copy(
        e, d, lambda o: o["input"].__setitem__("size", [128, 128]))),
    "det_spec_unknown_key": lambda e, d: run_args(e, None, None, "default", None, "--detector", det_copy(
        e, d, _set("nonsense", 1))),
    "det_onnx_garbage": lambda e, d: run_args(e, None, None, "default", None, "--detector",
                                              det_copy(e, d, onnx_bytes=b"not a model")),
    "det_onnx_empty": lambda e, d: run_args(e, None, None, "default", None, "--detector", det_copy(e, d, onnx_bytes=b"")),
    "det_spec_given": lambda e, d: run_args(e, None, None, "default", None, "--detector",
                                            det_copy(e, d).with_suffix(".json")),
    "det_none_beside": lambda e, d: run_args(e, video=(lambda p: (shutil.copy(e.video, p), p)[1])(d / "copy.mp4")),
}

VIDEO_OUT_CASES = {
    "video_missing": lambda e, d: run_args(e, video=d / "nope.mp4"),
    "video_folder": lambda e, d: run_args(e, video=video_folder(d)),
    "video_text": lambda e, d: run_args(e, video=region(d, "not a video", "t.mp4")),
    "video_empty": lambda e, d: run_args(e, video=region(d, b"", "e.mp4")),
    "video_truncated": lambda e, d: run_args(e, video=truncated_video(e, d)),
    "frames_abc": lambda e, d: run_args(e, None, None, "default", None, "--frames", "abc"),
    "frames_past_end": lambda e, d: run_args(e, None, None, "default", None, "--frames", "5:100"),
    "frames_reversed": lambda e, d: run_args(e, None, None, "default", None, "--frames", "6:2"),
    "frames_three": lambda e, d: run_args(e, None, None, "default", None, "--frames", "1:2:3"),
    "frames_empty_range": lambda e, d: run_args(e, None, None, "default", None, "--frames", "3:3"),
    "frames_float": lambda e, d: run_args(e, None, None, "default", None, "--frames", "1.5:3"),
    "frames_neg_far": lambda e, d: run_args(e, None, None, "default", None, "--frames", "-100:"),
    "formats_gif": lambda e, d: run_args(e, None, None, "default", None, "--formats", "obj,gif"),
    "formats_empty_item": lambda e, d: run_args(e, None, None, "default", None, "--formats", "obj,,usd"),
    "preset_unknown": lambda e, d: run_args(e, None, None, "default", None, "--preset", "fastest"),
    "iterations_zero": lambda e, d: ["run", str(e.video), "--actor", str(e.actor), "--iterations", "0"],
    "window_one": lambda e, d: ["run", str(e.video), "--actor", str(e.actor), "--window", "1"],
    "threads_zero": lambda e, d: ["run", str(e.video), "--actor", str(e.actor), "--threads", "0"],
    "device_unknown": lambda e, d: run_args(e, None, None, "default", None, "--device", "tpu"),
    "device_cuda": lambda e, d: run_args(e, None, None, "default", None, "--device", "cuda"),
    "seed_text": lambda e, d: ["run", str(e.video), "--actor", str(e.actor), "--seed", "abc"],
    "no_actor_option": lambda e, d: ["run", str(e.video)],
    "unknown_option": lambda e, d: ["run", str(e.video), "--actor", str(e.actor), "--fast"],
    "unknown_command": lambda e, d: ["capturez"],
    "out_is_file": lambda e, d: run_args(e, out=region(d, "x", "out.txt")),
    "out_under_file": lambda e, d: run_args(e, out=region(d, "x", "f.txt") / "sub"),
    "out_not_a_run": lambda e, d: run_args(e, out=(lambda o: (o.mkdir(), (o / "mine.txt").write_text("m"), o)[2])(
        d / "mine")),
    "out_other_take": lambda e, d: run_args(e, out=another_take_out(e, d)),
    "out_locked": lambda e, d: run_args(e, out=locked_out(e, d)),
    "out_meshes_link": lambda e, d: run_args(e, out=link_out(e, d, "meshes")),
    "out_fit_link": lambda e, d: run_args(e, out=link_out(e, d, "fit")),
    "out_detections_link": lambda e, d: run_args(e, out=link_out(e, d, "detections")),
    "out_broken_link": lambda e, d: run_args(e, out=(lambda p: (p.symlink_to(d / "gone"), p)[1])(d / "dangling")),
    "cache_chunk_object": lambda e, d: run_args(e, out=(lambda r: (crafted_npz_object(first_chunk(r)), r)[1])(
        run_copy(e, d))),
    "cache_chunk_compressed": lambda e, d: run_args(e, out=(lambda r: (crafted_npz_compressed(first_chunk(r)), r)[1])(
        run_copy(e, d))),
    "cache_chunk_big_header": lambda e, d: run_args(e, out=(lambda r: (crafted_npz_big_header(first_chunk(r)), r)[1])(
        run_copy(e, d))),
    "cache_chunk_garbage": lambda e, d: run_args(e, out=(lambda r: (first_chunk(r).write_bytes(b"PK\x03\x04junk"), r)[1])(
        run_copy(e, d))),
}

FIT3D_CASES = {
    "fit3d_missing": lambda e, d: fit3d_args(e, d / "nope", d),
    "fit3d_empty": lambda e, d: fit3d_args(e, (lambda p: (p.mkdir(), p)[1])(d / "empty"), d),
    "fit3d_wrong_count": lambda e, d: fit3d_args(e, meshes_dir(e, d, fn=lambda f: (e.root / "skull.ply").replace(
        f / "scan_001.ply") if False else shutil.copy(e.root / "skull.ply", f / "scan_001b.ply")), d),
    "fit3d_corrupt": lambda e, d: fit3d_args(e, meshes_dir(e, d, fn=lambda f: (f / "scan_001.obj").write_text("v 1 2\nf x")),
                                             d),
    "fit3d_units_m": lambda e, d: fit3d_args(e, meshes_dir(e, d), d, "--units", "m"),
    "fit3d_units_unknown": lambda e, d: fit3d_args(e, meshes_dir(e, d), d, "--units", "parsec"),
    "fit3d_overlay": lambda e, d: fit3d_args(e, meshes_dir(e, d), d, "--formats", "obj,overlay"),
    "fit3d_fps_zero": lambda e, d: fit3d_args(e, meshes_dir(e, d), d, "--fps", "0"),
    "fit3d_nan": lambda e, d: fit3d_args(e, meshes_dir(e, d, fn=lambda f: (f / "scan_000.obj").write_text(
        (f / "scan_000.obj").read_text().replace("v ", "v nan ", 1).replace("nan ", "", 0))), d),
    "fit3d_actor_unknown": lambda e, d: ["fit3d", str(d), "--actor", "nosuch"],
}

SYNTH_CASES = {
    "synth_actor_unknown": lambda e, d: synth_args(e, d, actor="nosuch"),
    "synth_size_text": lambda e, d: synth_args(e, d, "--size", "big"),
    "synth_size_zero": lambda e, d: synth_args(e, d, "--size", "0x0"),
    "synth_size_huge": lambda e, d: synth_args(e, d, "--size", "100000x100000"),
    "synth_frames_zero": lambda e, d: synth_args(e, d, "--frames", "0"),
    "synth_fps_zero": lambda e, d: synth_args(e, d, "--fps", "0"),
    "synth_preset": lambda e, d: synth_args(e, d, "--preset", "dance"),
    "synth_distortion_text": lambda e, d: synth_args(e, d, "--distortion", "a,b"),
    "synth_distortion_count": lambda e, d: synth_args(e, d, "--distortion", "0.1,0.2,0.3"),
    "synth_distortion_wild": lambda e, d: synth_args(e, d, "--distortion", "1e6,1e6,0,0"),
    "synth_camera_bad": lambda e, d: synth_args(e, d, "--camera", cam_json(e, d, set_k(0, 2, -5000.0))),
    "synth_codec": lambda e, d: synth_args(e, d, "--codec", "gif"),
    "synth_landmarks_zero": lambda e, d: synth_args(e, d, "--landmarks", "0"),
    "synth_crf": lambda e, d: synth_args(e, d, "--crf", "99"),
    "synth_out_file": lambda e, d: ["synth", "--actor", str(e.actor), "--out", str(region(d, "x", "o.txt")),
                                    "--frames", "2", "--size", "64x48", "--no-progress"],
    "synth_broken_actor": lambda e, d: synth_args(e, d, actor=weights_nan(e, d)),
}

CALIB_CASES = {
    "calib_missing": lambda e, d: ["calibrate", str(d / "nope.mp4"), "--board", "checker:cols=9,rows=6,square=25"],
    "calib_board_garbage": lambda e, d: ["calibrate", str(e.video), "--board", "garbage"],
    "calib_board_dict": lambda e, d: ["calibrate", str(e.video), "--board",
                                      "charuco:cols=5,rows=4,square=30,marker=22,dict=DICT_NOPE"],
    "calib_board_negative": lambda e, d: ["calibrate", str(e.video), "--board", "checker:cols=-9,rows=6,square=25"],
    "calib_empty_folder": lambda e, d: ["calibrate", str((lambda p: (p.mkdir(), p)[1])(d / "imgs")), "--board",
                                        "checker:cols=9,rows=6,square=25"],
    "calib_text_video": lambda e, d: ["calibrate", str(region(d, "nope", "v.mp4")), "--board",
                                      "checker:cols=9,rows=6,square=25"],
    "calib_out_suffix": lambda e, d: ["calibrate", str(e.video), "--board", "checker:cols=9,rows=6,square=25",
                                      "--out", str(d / "cam.txt")],
    "calib_no_board": lambda e, d: ["calibrate", str(e.video), "--board", "checker:cols=9,rows=6,square=25",
                                    "--max-frames", "2", "--out", str(d / "cam.json")],
}

TRAIN_CASES = {
    "train_shapes_missing": lambda e, d: train_args(d / "nope", d),
    "train_shapes_empty": lambda e, d: train_args((lambda p: (p.mkdir(), p)[1])(d / "empty"), d),
    "train_no_neutral": lambda e, d: train_args(shapes_dir(e, d, lambda s: (s / "neutral.ply").rename(s / "n0.ply")), d),
    "train_neutral_unknown": lambda e, d: train_args(shapes_dir(e, d), d, "--neutral", "rest"),
    "train_topology": lambda e, d: train_args(shapes_dir(e, d, lambda s: shutil.copy(e.root / "skull.ply",
                                                                                   s / "smile.ply")), d),
    "train_only_neutral": lambda e, d: train_args(shapes_dir(e, d, lambda s: [p.unlink() for p in s.iterdir()
                                                                            if p.stem != "neutral"]), d),
    "train_corrupt_shape": lambda e, d: train_args(shapes_dir(e, d, lambda s: (s / "smile.ply").write_bytes(b"ply\n")),
                                                   d),
    "train_units_m": lambda e, d: train_args(shapes_dir(e, d), d, "--units", "m"),
    "train_units_unknown": lambda e, d: train_args(shapes_dir(e, d), d, "--units", "parsec"),
    "train_skull_missing": lambda e, d: train_args(shapes_dir(e, d), d, "--skull", d / "nope.ply"),
    "train_plane_bad": lambda e, d: train_args(shapes_dir(e, d), d, "--symmetry-plane", "1,0"),
    "train_forehead_range": lambda e, d: train_args(shapes_dir(e, d), d, "--forehead", region(d, "[99999999]")),
    "train_forehead_garbage": lambda e, d: train_args(shapes_dir(e, d), d, "--forehead", region(d, "[\"x\"]")),
    "train_preset": lambda e, d: train_args(shapes_dir(e, d), d, "--preset", "nope"),
    "train_hidden_matmul": lambda e, d: train_args(shapes_dir(e, d), d, "--hidden-matmul", "half"),
    "train_iterations_zero": lambda e, d: ["actor", "train", str(d / "a"), "--shapes", str(shapes_dir(e, d)),
                                           "--iterations", "0", "--no-progress"],
    "train_sample_and_shapes": lambda e, d: ["actor", "train", str(d / "a"), "--sample", "--shapes", str(d)],
    "train_no_shapes": lambda e, d: ["actor", "train", str(d / "a")],
    "train_skull_corrupt": lambda e, d: train_args(shapes_dir(e, d), d, "--skull", region(d, "ply\nnonsense", "s.ply"),
                                                   "--jaw", e.root / "jaw.ply"),
    "train_bone_units": lambda e, d: train_args(shapes_dir(e, d), d, "--skull", e.root / "skull.ply", "--jaw",
                                                e.root / "jaw.ply", "--bone-units", "parsec"),
}

EDIT_CASES = {
    "edit_actor_unknown": lambda e, d: edit_args(e, d, actor="nosuch"),
    "edit_region_missing": lambda e, d: edit_args(e, d, d / "nope.json"),
    "edit_region_garbage": lambda e, d: edit_args(e, d, region(d, "{garbage")),
    "edit_region_range": lambda e, d: edit_args(e, d, region(d, "[1, 99999999]")),
    "edit_region_negative": lambda e, d: edit_args(e, d, region(d, "[-1]")),
    "edit_region_strings": lambda e, d: edit_args(e, d, region(d, "[\"a\"]")),
    "edit_region_weights": lambda e, d: edit_args(e, d, region(d, "{\"vertices\": [1, 2], \"weights\": [0.5, 3]}")),
    "edit_region_keys": lambda e, d: edit_args(e, d, region(d, "{\"verts\": [1]}")),
    "edit_region_empty": lambda e, d: edit_args(e, d, region(d, "[]")),
    "edit_region_not_utf8": lambda e, d: edit_args(e, d, region(d, b"\xff\xfe[1]")),
    "edit_region_txt": lambda e, d: edit_args(e, d, region(d, "1 2 x", "r.txt")),
    "edit_region_mesh_other": lambda e, d: edit_args(e, d, shutil.copy(e.root / "skull.ply", d / "r.ply")),
    "edit_region_suffix": lambda e, d: edit_args(e, d, region(d, "1", "r.csv")),
    "edit_scale_zero": lambda e, d: ["actor", "edit", str(e.actor), "--thickness-scale", "0", "--region",
                                     str(region(d, "[1]")), "--out", str(d / "e")],
    "edit_falloff": lambda e, d: edit_args(e, d, None, "--falloff", "-1"),
    "edit_out_source": lambda e, d: ["actor", "edit", str(e.actor), "--thickness-scale", "1.2", "--region",
                                     str(region(d, "[1]")), "--out", str(e.actor)],
    "edit_out_busy": lambda e, d: ["actor", "edit", str(e.actor), "--thickness-scale", "1.2", "--region",
                                   str(region(d, "[1]")), "--out", str(
                                       (lambda p: (p.mkdir(), (p / "x").write_text("x"), p)[2])(d / "busy")),
                                   "--overwrite"],
    "edit_broken_actor": lambda e, d: edit_args(e, d, None, actor=weights_other_width(e, d)),
}

SHOW_CASES = {
    "show_unknown": lambda e, d: ["actor", "show", "nosuch"],
    "show_list_json": lambda e, d: ["actor", "show", str(actor_with(e, d, lambda a: (a / "actor.json").write_text("[]")))],
    "show_no_quality": lambda e, d: ["actor", "show", str(actor_with(e, d, meta_edit(_del("quality"))))],
    "show_quality_list": lambda e, d: ["actor", "show", str(actor_with(e, d, meta_edit(_set("quality", []))))],
    "show_not_utf8": lambda e, d: ["actor", "show", str(actor_with(e, d, lambda a: (a / "actor.json")
                                                                    .write_bytes(b"\xff{")))],
    "show_json_shapes_null": lambda e, d: ["actor", "show", "--json", str(actor_with(
        e, d, meta_edit(_set("shape_names", None))))],
    "show_unfinished": lambda e, d: ["actor", "show", str((lambda p: (p.mkdir(parents=True), p)[1])(
        d / "actors" / "half" / "training"))[:-len("/training")]],
}

RETARGET_CASES = {
    "rt_run_missing": lambda e, d: retarget_args(e, d, d / "nope"),
    "rt_not_a_run": lambda e, d: retarget_args(e, d, d),
    "rt_unfinished": lambda e, d: retarget_args(e, d, (lambda r: (edit_json(r / "run.json", _set("status", "running")),
                                                                  r)[1])(run_copy(e, d))),
    "rt_run_json_list": lambda e, d: retarget_args(e, d, (lambda r: ((r / "run.json").write_text("[]"), r)[1])(
        run_copy(e, d))),
    "rt_no_settings": lambda e, d: retarget_args(e, d, (lambda r: (edit_json(r / "run.json", _del("settings")), r)[1])(
        run_copy(e, d))),
    "rt_no_export": lambda e, d: retarget_args(e, d, (lambda r: ((r / "export.json").unlink(), r)[1])(run_copy(e, d))),
    "rt_window_pickle": lambda e, d: retarget_args(e, d, crafted_window(e, d, "pickle")),
    "rt_window_garbage": lambda e, d: retarget_args(e, d, crafted_window(e, d, "garbage")),
    "rt_window_truncated": lambda e, d: retarget_args(e, d, crafted_window(e, d, "truncated")),
    "rt_window_not_tensors": lambda e, d: retarget_args(e, d, crafted_window(e, d, "not_tensors")),
    "rt_to_unknown": lambda e, d: ["retarget", str(e.run), "--to", "nosuch", "--out", str(d / "rt")],
    "rt_parts": lambda e, d: retarget_args(e, d, None, "--parts", "nose"),
    "rt_formats": lambda e, d: retarget_args(e, d, None, "--formats", "gif"),
    "rt_out_is_source": lambda e, d: ["retarget", str(e.run), "--to", str(e.actor), "--out", str(e.run)],
    "rt_mesh_frame": lambda e, d: retarget_args(e, d, None, "--mesh-frame", "world"),
    "rt_out_file": lambda e, d: ["retarget", str(e.run), "--to", str(e.actor), "--out", str(region(d, "x", "f.txt"))],
}

GOOD_TAKE = '[[take]]\nvideo = "take.mp4"\nactor = "anna"\n'
BATCH_CASES = {
    "batch_missing": lambda e, d: ["batch", str(d / "nope.toml"), "--dry-run"],
    "batch_dir": lambda e, d: ["batch", str(d), "--dry-run"],
    "batch_not_toml": lambda e, d: ["batch", str(shoot(d, "[[take]\nvideo=")), "--dry-run"],
    "batch_not_utf8": lambda e, d: ["batch", str(shoot(d, b"\xff\xfe[shoot]")), "--dry-run"],
    "batch_unknown_key": lambda e, d: ["batch", str(shoot(d, GOOD_TAKE + "speed = 3\n")), "--dry-run"],
    "batch_unknown_table": lambda e, d: ["batch", str(shoot(d, "[nonsense]\na = 1\n" + GOOD_TAKE)), "--dry-run"],
    "batch_no_video": lambda e, d: ["batch", str(shoot(d, "[[take]]\nname = \"a\"\n")), "--dry-run"],
    "batch_wrong_type": lambda e, d: ["batch", str(shoot(d, GOOD_TAKE + "iterations = \"many\"\n")), "--dry-run"],
    "batch_dup_names": lambda e, d: ["batch", str(shoot(d, GOOD_TAKE + GOOD_TAKE)), "--dry-run"],
    "batch_no_takes": lambda e, d: ["batch", str(shoot(d, "[shoot]\nname = \"x\"\n")), "--dry-run"],
    "batch_segments_negative": lambda e, d: ["batch", str(shoot(d, "[shoot]\nsegment_frames = -5\n" + GOOD_TAKE)),
                                             "--dry-run"],
    "batch_bad_name": lambda e, d: ["batch", str(shoot(d, "[[take]]\nvideo = \"a.mp4\"\nname = \"../up\"\n")),
                                    "--dry-run"],
    "batch_formats": lambda e, d: ["batch", str(shoot(d, GOOD_TAKE + "formats = \"obj,gif\"\n")), "--dry-run"],
    "batch_workers_zero": lambda e, d: ["batch", str(shoot(d, GOOD_TAKE)), "--dry-run", "--workers", "0"],
}

DEMO_CASES = {
    "demo_out_file": lambda e, d: ["demo", "--out", str(region(d, "x", "demo.txt"))],
    "demo_out_under_file": lambda e, d: ["demo", "--out", str(region(d, "x", "demo.txt") / "sub")],
    "demo_unknown_option": lambda e, d: ["demo", "--fast"],
}

CASES: dict[str, Callable[[Env, Path], list[str]]] = {
    **CAM_CASES, **ACTOR_CASES, **DET_CASES, **VIDEO_OUT_CASES, **FIT3D_CASES, **SYNTH_CASES, **CALIB_CASES,
    **TRAIN_CASES, **EDIT_CASES, **SHOW_CASES, **RETARGET_CASES, **BATCH_CASES, **DEMO_CASES,
}


def test_there_are_enough_cases():
    assert len(CASES) >= 150


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_is_one_line_exit_2_and_nothing_changes(name, env, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CAPTURE_ACTORS", str(tmp_path / "actors"))
    argv = CASES[name](env, tmp_path)
    before = snapshot(env.root, tmp_path)
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    finally:
        while _LOCKS:
            _LOCKS.pop().release()
    out = capsys.readouterr()
    one_line_error(rc, out.err)
    after = snapshot(env.root, tmp_path)
    changed = [str(p) for p, v in before.items() if after.get(p) != v]
    assert not changed, changed
    assert not Path("/tmp/capture_pwned").exists()


# ------------------------------------------------------------------------------------- subprocesses
def _cli(args: list[str], timeout: float = 180) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.pop("CAPTURE_VERBOSE", None)
    from capture.io.quiet import QUIET_ENV

    for k in QUIET_ENV:  # set in this process by the in-process cases; the subprocess decides for itself
        env.pop(k, None)
    return subprocess.run([sys.executable, "-m", "capture.cli", *[str(a) for a in args]], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_library_noise_is_silenced_unless_verbose(env, tmp_path):
    """FFmpeg's own complaints about a damaged video reach the real stderr only with --verbose."""
    bad = truncated_video(env, tmp_path)
    quiet = _cli(["run", bad, "--actor", env.actor, "--out", tmp_path / "o"])
    msg = one_line_error(quiet.returncode, quiet.stderr)
    assert "cannot open video" in msg or "no readable frames" in msg
    loud = _cli(["run", bad, "--actor", env.actor, "--out", tmp_path / "o", "--verbose"])
    assert loud.returncode == 2 and loud.stderr.strip().splitlines()[-1] == msg
    assert len(loud.stderr.strip().splitlines()) > 1   # FFmpeg's "moov atom not found" and the like


# ------------------------------------------------------------------------------------------- damage
def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_overwrite_keeps_the_old_run_until_the_new_one_succeeded(env, tmp_path, monkeypatch, capsys):
    from capture.export.params import ParamsWriter

    out = run_copy(env, tmp_path)
    edit_json(out / "run.json", _set("take_id", "another"))
    (out / "meshes" / "mine.txt").write_text("the user's own file")
    before = _files(out)

    def interrupted(*a, **k):   # Ctrl-C during the export, streamed or not
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(ParamsWriter, "write", interrupted)
        assert main(run_args(env, None, None, "default", out, "--formats", "npz", "--overwrite")) == 130
    after = _files(out)
    assert {k: v for k, v in after.items() if k in before} == before   # the old run is whole
    assert main(run_args(env, None, None, "default", out, "--formats", "npz", "--overwrite")) == 0
    capsys.readouterr()
    assert json.loads((out / "run.json").read_text())["take_id"] != "another"
    assert not list((out / "meshes").glob("*.obj")) and (out / "meshes" / "mine.txt").read_text().startswith("the")
    assert (out / "params.npz").is_file() and not (out / "overlay.mp4").exists()
    assert not (out / ".overwrite").exists() and not (out / ".swap.json").exists()
    assert not list(out.rglob("*.~tmp*"))


def test_a_swap_cut_short_is_finished_by_the_next_run(env, tmp_path, monkeypatch, capsys):
    import capture.run.store as store

    out = run_copy(env, tmp_path)
    edit_json(out / "run.json", _set("take_id", "another"))
    real = store.finish_swap
    calls = []

    def dies_once(o, extra=()):
        if not calls and (Path(o) / ".swap.json").is_file():
            calls.append(1)
            raise KeyboardInterrupt   # killed between writing the journal and moving the files
        return real(o, extra)

    with monkeypatch.context() as m:
        m.setattr(store, "finish_swap", dies_once)
        assert main(run_args(env, None, None, "default", out, "--formats", "npz", "--overwrite")) == 130
        assert (out / ".swap.json").is_file()
        assert main(run_args(env, None, None, "default", out, "--formats", "npz")) == 0
    capsys.readouterr()
    assert json.loads((out / "run.json").read_text())["take_id"] != "another"
    assert not (out / "meshes").exists() and not (out / ".overwrite").exists()


def test_nothing_is_written_through_a_link(env, tmp_path, capsys):
    out = link_out(env, tmp_path, "meshes")
    assert main(run_args(env, out=out)) == 2
    assert "symbolic link" in one_line_error(2, capsys.readouterr().err)
    assert not any((tmp_path / "elsewhere").iterdir())


def test_temp_files_of_a_killed_run_are_removed_by_the_next(env, tmp_path, capsys):
    out = run_copy(env, tmp_path)
    stale = [out / "meshes" / ".frame_000001.~tmpab12cd34.obj", out / ".take.~tmpzz99yy88.usdc",
             next(out.glob("fit/*")) / ".frames_000000.~tmp0123abcd.npz"]
    for p in stale:
        p.write_bytes(b"x" * 1000)
    (out / ".notes").write_text("the user's hidden file")
    from capture.run.store import open_run_dir

    run = json.loads((out / "run.json").read_text())
    with open_run_dir(out, run["take_id"], run["take_label"], overwrite=False) as folder:  # what every run does first
        assert folder.work == out
    assert not any(p.exists() for p in stale) and (out / ".notes").is_file()


def test_a_second_run_on_the_same_out_fails_at_once(env, tmp_path, capsys):
    from capture.io.outdir import OutLock

    out = run_copy(env, tmp_path)
    with OutLock(out):
        t0 = time.perf_counter()
        assert main(run_args(env, out=out)) == 2
        msg = one_line_error(2, capsys.readouterr().err)
        assert "another capture run" in msg and str(os.getpid()) in msg
        assert time.perf_counter() - t0 < 60
    OutLock(out).acquire().release()   # the lock goes with its holder


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_forked_child_does_not_keep_a_killed_runs_lock(tmp_path):
    """A run killed with -9 while its forked fit or figure process winds down: the next run gets the folder at
    once. (The child shared the lock's open file description; flock held until it exited too.) The parent is
    killed once the child runs its target, so after the fork's hooks: on a loaded machine the kill could
    otherwise land between the fork and the child's first instructions, a window no user can hit."""
    from capture.io.outdir import OutLock

    script = (
        "import multiprocessing as mp, sys, time\n"
        "from capture.io.outdir import OutLock\n"
        "def nap(started):\n"
        "    started.set()\n"
        "    time.sleep(60)\n"
        "OutLock(sys.argv[1]).acquire()\n"
        "ctx = mp.get_context('fork')\n"
        "started = ctx.Event()\n"
        "child = ctx.Process(target=nap, args=(started,), daemon=True)\n"
        "child.start()\n"
        "started.wait(30)\n"
        "print(child.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    pyenv = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                            env=pyenv)
    child = 0
    try:
        child = int(proc.stdout.readline())
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        os.kill(child, 0)  # the child still lives (it sleeps for a minute) ...
        OutLock(tmp_path).acquire().release()  # ... and the folder is free
    finally:
        proc.kill()
        if child:
            try:
                os.kill(child, signal.SIGKILL)
            except ProcessLookupError:
                pass


@pytest.mark.parametrize("err", ["ENOSPC", "EROFS", "EACCES"])
def test_disk_full_or_read_only_is_one_line(env, tmp_path, monkeypatch, capsys, err):
    import errno

    import capture.io.atomic as atomic

    def fail(src, dst):
        raise OSError(getattr(errno, err), os.strerror(getattr(errno, err)), str(dst))

    monkeypatch.setattr(atomic.os, "replace", fail)
    out = tmp_path / "o"
    rc = main(run_args(env, out=out))
    msg = one_line_error(rc, capsys.readouterr().err)
    assert ("space" in msg) if err == "ENOSPC" else ("write" in msg)


def test_export_key_describes_the_files_on_disk(env, tmp_path, monkeypatch, capsys):
    """An export interrupted after a settings change must not keep the old fit's frame files on resume."""
    import capture.export.mesh_files as mesh_files

    out = run_copy(env, tmp_path)
    fresh = tmp_path / "fresh"
    changed = ("--seed", "3", "--formats", "obj")
    real = mesh_files.MeshSequenceWriter.write
    count = []

    def dies_after_three(self, *a, **k):
        if len(count) == 3:
            raise KeyboardInterrupt
        count.append(1)
        return real(self, *a, **k)

    with monkeypatch.context() as m:
        m.setattr(mesh_files.MeshSequenceWriter, "write", dies_after_three)
        assert main(run_args(env, None, None, "default", out, *changed)) == 130
    state = json.loads((out / "export.json").read_text())
    assert state["status"] == "running" and state.get("key") is None   # no key until the files are written
    assert main(run_args(env, None, None, "default", out, *changed)) == 0
    assert main(run_args(env, None, None, "default", fresh, *changed)) == 0
    capsys.readouterr()
    for p in sorted((fresh / "meshes").glob("*.obj")):
        assert (out / "meshes" / p.name).read_bytes() == p.read_bytes(), p.name


def test_frames_without_a_face_are_bridged_as_documented(env, tmp_path, capsys):
    """README: a frame without a face is listed as skipped in report.json and gets a bridged mesh."""
    from capture.synth.video import VideoWriter, read_frames

    blank = tmp_path / "blank" / "take.mp4"
    blank.parent.mkdir()
    shutil.copytree(env.take / "detector", blank.parent / "detector")
    frames = list(read_frames(env.video))
    with VideoWriter(blank, (320, 240), 25.0) as w:
        for i, f in enumerate(frames):
            w.write(np.zeros_like(f) if i == 3 else f)
    out = tmp_path / "out"
    assert main(run_args(env, blank, None, "default", out, "--formats", "obj,npz")) == 0
    capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    assert [s["frame"] for s in report["skipped_frames"]] == [3]
    assert "bridged" in report["skipped_frames"][0]["output"]
    assert (out / "meshes" / "frame_000003.obj").is_file()
    with np.load(out / "params.npz") as p:
        assert p["status"][3] == 1 and np.isnan(p["reprojection_rms_px"][3])


def test_collapsed_detector_output_is_an_error_not_a_success(env, tmp_path, monkeypatch, capsys):
    from capture.run.checks import landmark_problems

    pts = np.zeros((2, 10, 2)) + 50.0
    pts[1] += np.random.default_rng(0).normal(0, 20, (10, 2))
    problems = landmark_problems(pts, None)
    assert "collapsed" in problems[0] and problems[1] == ""

    from capture.detector.runtime import Detector

    orig = Detector.run_lanes

    def collapsed(self, lanes, *a, **k):   # the detector's output, streamed or not, collapses onto one pixel
        out = orig(self, lanes, *a, **k)
        for lane in lanes:
            for r in lane.results:
                r.points = np.zeros_like(r.points) + 100.0
        return out

    monkeypatch.setattr(Detector, "run_lanes", collapsed)
    rc = main(run_args(env, out=tmp_path / "o"))
    msg = one_line_error(rc, capsys.readouterr().err)
    assert "collapsed" in msg


def test_head_depth_check_flags_and_fails(tmp_path):
    from capture.run.checks import check_head_depths
    from capture.run.stages import DONE_JSON
    from capture.run.store import save_frame_fits

    @__import__("dataclasses").dataclass
    class F:
        frame: int
        head_t: np.ndarray
        status: str = "fitted"

    fits = [F(0, np.array([0, 0, 600.0])), F(1, np.array([0, 0, 8.4e15])), F(2, np.array([0, 0, 80000.0]))]
    save_frame_fits(tmp_path / "frames_000000.npz", fits)
    (tmp_path / DONE_JSON).write_text(json.dumps({"key": {}, "chunks": ["frames_000000.npz"], "frames": [0, 1, 2]}))
    import capture.run.stages as stages

    orig = stages._frame_fit_class
    stages._frame_fit_class = lambda: F
    try:
        rows = [{"frame": i} for i in range(3)]
        msg = check_head_depths(tmp_path, rows)
    finally:
        stages._frame_fit_class = orig
    assert rows[0].get("flags") is None and rows[1]["flags"] == ["head_depth_implausible"] == rows[2]["flags"]
    assert msg is not None and "2 of 3 frames" in msg


# -------------------------------------------------------------------------------------------- kill
KILL_POINTS = ("detections/*/seg_*.npz", "fit/*/windows/win_*.pt", "meshes/frame_*.obj")


@pytest.mark.slow
def test_sigkill_at_several_points_then_resume_gives_identical_outputs(env, tmp_path, capsys):
    """kill -9 after the detections, after the first solved window and during the export; the resumed
    run's outputs are byte-identical to the uninterrupted run's (meshes) and equal in every array."""
    out = tmp_path / "killed"
    args = run_args(env, out=out)
    pyenv = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    killed = 0
    for pattern in KILL_POINTS:
        proc = subprocess.Popen([sys.executable, "-m", "capture.cli", *args], cwd=REPO, env=pyenv,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.time() + 240
            while time.time() < deadline and proc.poll() is None and not list(out.glob(pattern)):
                time.sleep(0.005)
            if proc.poll() is None:
                proc.send_signal(signal.SIGKILL)
                killed += 1
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert killed >= 2, "the runs ended before they could be killed"
    assert main(args) == 0
    capsys.readouterr()
    assert not list(out.rglob("*.~tmp*"))
    ref = _files(env.run)
    got = _files(out)
    for name in [k for k in ref if k.startswith("meshes/")]:
        assert got[name] == ref[name], name
    for name in ("params.npz", "landmarks.npz"):
        with np.load(out / name) as a, np.load(env.run / name) as b:
            assert a.files == b.files
            for k in a.files:
                np.testing.assert_array_equal(a[k], b[k], err_msg=f"{name}:{k}")


def test_one_broken_actor_does_not_break_actor_list(env, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CAPTURE_ACTORS", str(tmp_path / "actors"))
    copy_actor(env, tmp_path, "good")
    actor_with(env, tmp_path, lambda a: (a / "actor.json").write_bytes(b"\xff\xfe[")) .rename(tmp_path / "actors" / "bad")
    monkeypatch.setenv("COLUMNS", "300")
    assert main(["actor", "list"]) == 0
    out = capsys.readouterr()
    assert out.err == ""
    rows = [line for line in out.out.splitlines() if line.strip().startswith("│")]
    bad = [r for r in rows if "unusable" in r]
    assert len(bad) == 1 and "bad" in bad[0]
    assert any("good" in r and "unusable" not in r for r in rows)   # the good one, listed by the name --actor takes


def test_a_crafted_detection_cache_is_never_loaded_whole(env, tmp_path, capsys):
    """A few hundred kB of compressed zeros posing as a detection segment (300 MB when loaded) is refused from its
    headers and detected again: the run's traced memory stays far below the archive's declared size."""
    import tracemalloc

    out = run_copy(env, tmp_path)
    seg = next(out.glob("detections/*/seg_*.npz"))
    np.savez_compressed(seg, frame_index=np.zeros(1, np.int64), points=np.zeros(300_000_000, np.uint8))
    (out / "detections" / "track.npz").unlink()
    assert seg.stat().st_size < 2_000_000
    from capture.detector.pipeline import _read_segment

    count = int(np.load(env.run / "landmarks.npz")["points"].shape[1])
    tracemalloc.start()
    try:
        assert _read_segment(seg, "synthetic", count) is None   # refused from its headers: detect again
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20_000_000, peak
    assert main(run_args(env, out=out)) == 0
    capsys.readouterr()
    with np.load(out / "landmarks.npz") as a, np.load(env.run / "landmarks.npz") as b:
        np.testing.assert_array_equal(a["points"], b["points"])
