"""``capture synth --meshes``: a registered mesh sequence rendered as a take with truth, read back by the detector."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from calib.camera import default_camera
from capture.cli import main
from capture.synth.scene import head_transforms
from tests.test_synth_detector import _detect
from tests.test_synth_take import train_tiny_actor
from tests.tiny_actor import tiny_shapes


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_meshes")
    actor = train_tiny_actor(root)
    shapes, faces = tiny_shapes((1.0, 1.0, 1.0))
    # a sequence the actor's model does not produce: its shapes exaggerated, plus a local bulge
    names = [n for n in shapes if n != "neutral"]
    seq = np.stack([shapes["neutral"] + 1.5 * (shapes[n] - shapes["neutral"]) for n in names[:3]])
    seq[1, :, 2] += 3.0 * np.exp(-np.sum((seq[1] - seq[1].mean(0)) ** 2, 1) / 400.0)
    npz = root / "seq.npz"
    np.savez(npz, vertices=seq)
    objs = root / "objs"
    objs.mkdir()
    for j, v in enumerate(seq):   # the same sequence in cm, as OBJ files
        trimesh.Trimesh(v / 10.0, faces, process=False).export(objs / f"f{j:03d}.obj")
    out = root / "take"
    assert main(["synth", "--actor", str(actor), "--out", str(out), "--meshes", str(npz), "--preset", "frontal",
                 "--size", "640x360", "--landmarks", "300", "--no-progress"]) == 0
    return root, actor, seq, out


def test_truth_is_the_sequence(rendered):
    _, actor, seq, out = rendered
    report = json.loads((out / "truth.json").read_text())
    assert report["meshes"]["frames"] == 3 and report["settings"]["frames"] == 3
    truth = np.load(out / "truth_meshes.npz")["vertices"]
    params = np.load(out / "truth_params.npz")
    assert truth.shape == seq.shape
    # frontal preset: the rest placement of capture synth, x_cam = R x + t
    template = np.asarray(trimesh.load(actor / "template.ply", process=False).vertices)
    R, t = head_transforms(default_camera(640, 360), template, [0.0], [0.0], [0.0], np.zeros((1, 3)))
    np.testing.assert_allclose(params["head_R"], np.broadcast_to(R[0], (3, 3, 3)), atol=1e-6)
    np.testing.assert_allclose(truth, seq @ R[0].T + t[0], atol=1e-3)
    # the rendered video, read by the take's own detector, gives the truth's projections
    e, c, v, _ = _detect(out)
    assert np.median(e[v]) < 0.2                      # the detector's accuracy (tests/test_synth_detector.py)
    assert np.sqrt((e[v & (c > 0.5)] ** 2).mean()) <= 0.5


def test_obj_folder_in_cm_equals_npz(rendered, tmp_path):
    root, actor, _, out = rendered
    out2 = tmp_path / "take_obj"
    assert main(["synth", "--actor", str(actor), "--out", str(out2), "--meshes", str(root / "objs"), "--units", "cm",
                 "--preset", "frontal", "--size", "640x360", "--landmarks", "300", "--frames", "2",
                 "--no-progress"]) == 0
    a = np.load(out / "truth_meshes.npz")["vertices"][:2]
    b = np.load(out2 / "truth_meshes.npz")["vertices"]
    np.testing.assert_allclose(b, a, atol=1e-3)


def test_bad_sequences(rendered, tmp_path, capsys):
    _, actor, seq, _ = rendered
    bad = tmp_path / "bad.npz"
    np.savez(bad, vertices=seq[:, :-5])
    assert main(["synth", "--actor", str(actor), "--out", str(tmp_path / "o1"), "--meshes", str(bad),
                 "--no-progress"]) == 2
    assert "vertices per frame but the actor's template has" in capsys.readouterr().err
    nan = seq.copy()
    nan[1, 7, 0] = np.nan
    np.savez(bad, vertices=nan)
    assert main(["synth", "--actor", str(actor), "--out", str(tmp_path / "o2"), "--meshes", str(bad),
                 "--no-progress"]) == 2
    assert "frame 1, vertex 7" in capsys.readouterr().err
    assert main(["synth", "--actor", str(actor), "--out", str(tmp_path / "o3"), "--meshes",
                 str(tmp_path / "missing"), "--no-progress"]) == 2
    assert not (tmp_path / "o3").exists()                # nothing written for bad input
