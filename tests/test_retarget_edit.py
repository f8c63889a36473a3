"""``capture retarget`` and ``capture actor edit`` on two tiny actors (two identities, one expression set).

* Retargeting: a 3D take of A posed with known parameters is fitted (``capture fit3d``) and played on B;
  B's meshes must equal B posed with the same parameters, within the fit's own error; the replay equals
  a slow per-frame reference through ``AnatomicalFaceModel.shape``; A played on A reproduces the run;
  the jaw and soft-tissue parts add up to the full performance; actors that do not correspond are refused.
* Anatomy editing: the region moves along the bone normals by (S - 1) w d (w from a scipy KD-tree
  reference), nothing beyond the falloff moves, expressions follow through the LBS, and the edited actor
  works in fit3d and retargeting.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from capture.cli import main
from tests.tiny_actor import train_tiny_actor

PROPORTIONS_B = (1.1, 0.93, 1.05)   # B: 10 % wider, 7 % shorter, 5 % deeper than A
T = 6                                # frames of the known take
FIT = ["--iterations", "300", "--window", "8", "--threads", "1", "--no-progress"]


@pytest.fixture(scope="module")
def actors(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # shared cores: one thread wastes least
    root = tmp_path_factory.mktemp("retarget")
    a = train_tiny_actor(root / "a", name="A")
    b = train_tiny_actor(root / "b", name="B", proportions=PROPORTIONS_B)
    yield root, a, b
    torch.set_num_threads(threads)


def _known_params():
    """Jaw opening 0..10 deg about x, three global coefficient curves (browUp, jawOpen, smile order)."""
    R = Rotation.from_euler("x", np.linspace(0.0, 10.0, T)[:, None], degrees=True).as_matrix()
    r6 = torch.tensor(np.concatenate([R[:, :, 0], R[:, :, 1]], 1), dtype=torch.float32)
    co = np.stack([np.linspace(1.0, 0.0, T), np.linspace(0.0, 0.5, T), 0.8 * np.sin(np.linspace(0.0, 3.0, T))], 1)
    return r6, torch.zeros(T, 3), torch.tensor(co, dtype=torch.float32)


def _posed(actor_dir: Path, r6, jt, co) -> np.ndarray:
    from capture.actor.package import load_actor

    act = load_actor(str(actor_dir))
    assert act.shape_names[1:] == ["browUp", "jawOpen", "smile"]
    v = torch.tensor(np.asarray(act.template.vertices), dtype=torch.float32)
    with torch.no_grad():
        return act.model.shape(act.model(v), r6, jt, co).numpy().astype(np.float64)


OBJ_UNIT = 1e-4 + 1e-9
"""OBJ files hold 4 decimals: the same vertex reached by two float paths (a run, its replay) can round to
neighbouring values, one unit (0.1 um) apart; seen on one CPU and not on another."""


def _meshes(folder: Path) -> np.ndarray:
    return np.stack([trimesh.load(p, process=False, maintain_order=True).vertices
                     for p in sorted(folder.glob("frame_*.obj"))])


@pytest.fixture(scope="module")
def fitted(actors):
    """A 6-frame 3D take of A with known parameters, fitted by capture fit3d; and B's truth."""
    root, a, b = actors
    params = _known_params()
    truth_a, truth_b = _posed(a, *params), _posed(b, *params)
    scans = root / "scans"
    scans.mkdir()
    faces = trimesh.load(a / "template.ply", process=False).faces
    for i in range(T):
        trimesh.Trimesh(truth_a[i], faces, process=False).export(scans / f"scan_{i:03d}.ply")
    run = root / "run_a"
    assert main(["fit3d", str(scans), "--actor", str(a), "--out", str(run), "--formats", "obj,npz", *FIT]) == 0
    return run, truth_a, truth_b


def test_retarget_plays_known_parameters_on_b(actors, fitted, tmp_path):
    root, a, b = actors
    run, truth_a, truth_b = fitted
    out = tmp_path / "on_b"
    assert main(["retarget", str(run), "--to", str(b), "--out", str(out), "--parts", "full,jaw,soft_tissue",
                 "--no-progress"]) == 0
    fit_a, got_b = _meshes(run / "meshes"), _meshes(out / "meshes")
    err_a = np.linalg.norm(fit_a - truth_a, axis=-1).mean(1)
    err_b = np.linalg.norm(got_b - truth_b, axis=-1).mean(1)
    motion_b = np.linalg.norm(truth_b - truth_b[:1], axis=-1).mean(1)
    # Tolerance: retargeting adds no error of its own, so B's error is A's fit error carried over (the
    # same parameters on a 5-10 % different face): per frame within 1.5x A's fit error + 0.1 mm, far below
    # the motion (up to ~4.5 mm mean) and the identity difference (a copy of A's meshes is ~6 mm off).
    assert np.all(err_b <= 1.5 * err_a + 0.1), (err_a, err_b)
    assert err_b.mean() < 0.5 and motion_b.max() > 3.0
    assert np.linalg.norm(fit_a - truth_b, axis=-1).mean() > 10 * err_b.mean()

    # The replay equals a slow per-frame reference: B's AnatomicalFaceModel.shape with A's coefficient field
    # F_W(z_j, c_A) + per-point field + coeff0_j at the corresponding vertices, then the head transform (frames 0..3 lie in the first window
    # only, so no overlap blend is involved).
    from capture.actor.package import load_actor
    from models.fit import FitSettings, SequenceFit
    from models.rotation import matrix_to_rot6d

    A, B = load_actor(str(a)), load_actor(str(b))
    state = torch.load(next(run.glob("fit/*/windows/win_000000.pt")), weights_only=True)
    settings = FitSettings(**json.loads((run / "run.json").read_text())["settings"]["fit_settings"])
    sf = SequenceFit(state["codes"].shape[0], 3, settings, state["head_R0"], state["head_t0"])
    sf.load_state_dict(state)
    va = torch.tensor(np.asarray(A.template.vertices), dtype=torch.float32)
    vb = torch.tensor(np.asarray(B.template.vertices), dtype=torch.float32)
    with torch.no_grad():
        x = (va - A.model.center) / A.config.scale
        pose = sf.poses()
        anat_b = B.model(vb)
        for j in range(4):
            # (V, E) at A's points: F_W's field, the per-point coefficient field (normalised Gaussians
            # around its centres, at A's template points in mm) and the frame's base coefficients
            w = sf.F_W(torch.cat([sf.codes[j].expand(len(va), -1), x], 1)) + sf.coeff0[j]
            if sf.field.shape[1]:
                g = torch.exp(-torch.cdist(va.double(), sf.field_centres.double()).square()
                              / (2 * settings.field_sigma_mm ** 2))
                w = w + ((g / g.sum(1, keepdim=True)) @ sf.field[j].double()).float()
            local = B.model.shape(anat_b, matrix_to_rot6d(pose.jaw_R[j:j + 1]), pose.jaw_t[j:j + 1], w[None])[0]
            ref = (local @ pose.head_R[j].T + pose.head_t[j]).numpy()
            assert np.abs(ref - got_b[j]).max() < 2e-3  # OBJ keeps 4 decimals; float32 sums

    # The parts: full + T_g(s0) = jaw (T_g(LBS(s0))) + soft tissue (T_g(s0 + sum w E)), per vertex.
    with np.load(out / "params.npz", allow_pickle=False) as p:
        head_R, head_t = p["head_R"], p["head_t_mm"]
        assert p["frame_index"].tolist() == list(range(T))
    s0 = anat_b.neutral.numpy().astype(np.float64)
    jaw, soft = _meshes(out / "jaw" / "meshes"), _meshes(out / "soft_tissue" / "meshes")
    posed_s0 = np.einsum("tij,vj->tvi", head_R, s0) + head_t[:, None]
    assert np.abs(got_b + posed_s0 - jaw - soft).max() < 2e-3
    assert np.linalg.norm(jaw - posed_s0, axis=-1).max() > 1.0  # the jaw really moves in the jaw part
    report = json.loads((out / "report.json").read_text())
    assert report["command"] == "capture retarget" and report["frames"]["count"] == T
    assert report["actors"]["target"]["name"] == "B" and report["correspondence"]["same_order"]
    assert json.loads((out / "run.json").read_text())["status"] == "done"
    # A rerun replays nothing and exports nothing.
    assert main(["retarget", str(run), "--to", str(b), "--out", str(out), "--parts", "full,jaw,soft_tissue",
                 "--no-progress"]) == 0
    assert {s["status"] for s in json.loads((out / "report.json").read_text())["stages"][1:]} == {"skipped"}


def test_retarget_onto_itself_reproduces_the_run(actors, fitted, tmp_path):
    _, a, _ = actors
    run = fitted[0]
    out = tmp_path / "on_a"
    assert main(["retarget", str(run), "--to", str(a), "--out", str(out), "--formats", "obj", "--no-progress"]) == 0
    assert np.abs(_meshes(out / "meshes") - _meshes(run / "meshes")).max() <= OBJ_UNIT


def test_retarget_a_video_run_with_all_its_outputs(actors, tmp_path):
    """capture run on a synthetic take of A, then retarget to B with the run's formats (overlay included)."""
    import av

    from tests.tiny_actor import synth_tiny_take

    _, a, b = actors
    take = synth_tiny_take(a, tmp_path / "take", frames=8, landmarks=100)
    run = tmp_path / "run"
    assert main(["run", str(take / "take.mp4"), "--actor", str(a), "--camera", str(take / "camera.json"), "--out",
                 str(run), "--iterations", "20", "--window", "5", "--threads", "1", "--no-progress"]) == 0
    out = tmp_path / "on_b"
    assert main(["retarget", str(run), "--to", str(b), "--out", str(out), "--no-progress"]) == 0
    assert len(list((out / "meshes").glob("frame_*.obj"))) == 8 and (out / "take.usdc").is_file()
    with av.open(str(out / "overlay.mp4")) as c:
        assert sum(1 for _ in c.decode(video=0)) == 8
    with np.load(run / "params.npz", allow_pickle=False) as p, np.load(out / "params.npz", allow_pickle=False) as q:
        for k in ("frame_index", "head_R", "head_t_mm", "jaw_R", "jaw_t_mm", "codes", "status"):
            assert np.array_equal(p[k], q[k]), k   # the played parameters are the run's
    # Windows [0, 5) and [4, 8) overlap by one frame: played on A itself, the blend reproduces the run.
    assert main(["retarget", str(run), "--to", str(a), "--out", str(tmp_path / "on_a"), "--formats", "obj",
                 "--no-progress"]) == 0
    assert np.abs(_meshes(tmp_path / "on_a" / "meshes") - _meshes(run / "meshes")).max() <= OBJ_UNIT


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("capture: error: "), err
    return err[0]


def test_retarget_refuses_what_does_not_correspond(actors, fitted, tmp_path, capsys):
    root, a, b = actors
    run = fitted[0]
    renamed = tmp_path / "B_renamed"
    shutil.copytree(b, renamed)
    meta = json.loads((renamed / "actor.json").read_text())
    meta["shape_names"] = ["neutral", "browRaise", "jawOpen", "smile"]
    (renamed / "actor.json").write_text(json.dumps(meta))
    assert main(["retarget", str(run), "--to", str(renamed), "--out", str(tmp_path / "x"), "--no-progress"]) == 2
    msg = _error(capsys)
    assert "do not correspond" in msg and "browUp" in msg and "browRaise" in msg
    fewer = tmp_path / "B_fewer"
    shutil.copytree(b, fewer)
    t = trimesh.load(fewer / "template.ply", process=False)
    t.submesh([np.arange(len(t.faces) - 100)], append=True).export(fewer / "template.ply")
    assert main(["retarget", str(run), "--to", str(fewer), "--out", str(tmp_path / "y"), "--no-progress"]) == 2
    assert "vertices" in _error(capsys)
    assert main(["retarget", str(tmp_path), "--to", str(b), "--out", str(tmp_path / "z"), "--no-progress"]) == 2
    assert "not a run folder" in _error(capsys)
    assert main(["retarget", str(run), "--to", str(b), "--out", str(tmp_path / "w"), "--parts", "lips",
                 "--no-progress"]) == 2
    assert "--parts" in _error(capsys)
    assert not (tmp_path / "x").exists() and not (tmp_path / "w").exists()


# ------------------------------------------------------------------------------------ anatomy edit
S, FALLOFF = 1.6, 12.0


@pytest.fixture(scope="module")
def edited(actors):
    root, a, _ = actors
    v = np.asarray(trimesh.load(a / "template.ply", process=False).vertices)
    region = np.flatnonzero(np.linalg.norm(v[:, :2] - [30.0, -20.0], axis=1) < 15.0)  # the left cheek
    (root / "cheek.json").write_text(json.dumps(region.tolist()))
    out = root / "a" / "actors" / "A_cheeks"
    assert main(["actor", "edit", str(a), "--thickness-scale", str(S), "--region", str(root / "cheek.json"),
                 "--falloff", str(FALLOFF), "--out", str(out)]) == 0
    return out, region


def test_edit_moves_the_region_along_the_bone_normals(actors, edited, capsys):
    from capture.actor.package import load_actor
    from models.rotation import rot6d_to_matrix

    _, a, _ = actors
    out, region = edited
    A, E = load_actor(str(a)), load_actor(str(out))
    meta = E.metadata["edit"]
    core = meta["core_mm"]
    assert meta["source_actor"] == "A" and meta["thickness_scale"] == S and meta["falloff_mm"] == FALLOFF
    v = torch.tensor(np.asarray(A.template.vertices), dtype=torch.float32)
    with torch.no_grad():
        before, after = A.model(v), E.model(v)
        shapes_b = A.model.training_shapes(before, A.jaw_rot6d, A.jaw_t).numpy()
        shapes_a = E.model.training_shapes(after, E.jaw_rot6d, E.jaw_t).numpy()
    d, n = before.thickness.numpy(), before.normal.numpy()
    # Reference weight: distance to the nearest painted vertex (scipy KD-tree), smoothstep falloff.
    dist = cKDTree(v.numpy()[region]).query(v.numpy())[0]
    t = np.clip((dist - core) / FALLOFF, 0.0, 1.0)
    w = 1.0 - t * t * (3.0 - 2.0 * t)
    move = after.neutral.numpy() - before.neutral.numpy()
    expected = ((S - 1.0) * w * d)[:, None] * n
    assert np.abs(move - expected).max() < 1e-3
    assert np.allclose(np.einsum("vi,vi->v", move[region], n[region]), (S - 1.0) * d[region], atol=1e-3)
    assert np.abs(move[region]).max() > 2.0                       # the cheek really moved (mm)
    outside = dist >= core + FALLOFF
    assert outside.sum() > 0.8 * len(dist) and np.all(move[outside] == 0.0)
    # Expressions follow through the LBS: shape_i' - shape_i = ((1 - k) I + k R_i) (s0' - s0).
    k = before.skin_weight.numpy()
    R = rot6d_to_matrix(A.jaw_rot6d).numpy()
    for i in range(3):
        lin = (1 - k)[:, None] * move + k[:, None] * (move @ R[i].T)
        assert np.abs(shapes_a[i + 1] - shapes_b[i + 1] - lin).max() < 1e-3
        assert np.all(shapes_a[i + 1][outside] == shapes_b[i + 1][outside])
    assert main(["actor", "show", str(out)]) == 0
    assert "EDITED from actor 'A'" in capsys.readouterr().out


def test_edited_actor_works_in_fit3d_and_retargeting(actors, fitted, edited, tmp_path):
    _, a, _ = actors
    run = fitted[0]
    out, region = edited
    # A's run played on its edit: identical outside the region and its falloff, the cheek moved.
    rt = tmp_path / "on_edit"
    assert main(["retarget", str(run), "--to", str(out), "--out", str(rt), "--formats", "obj", "--no-progress"]) == 0
    got, ref = _meshes(rt / "meshes"), _meshes(run / "meshes")
    moved = np.linalg.norm(got - ref, axis=-1).max(0)
    v = np.asarray(trimesh.load(a / "template.ply", process=False).vertices)
    core = json.loads((out / "actor.json").read_text())["edit"]["core_mm"]
    far = cKDTree(v[region]).query(v)[0] >= core + FALLOFF
    assert moved[far].max() < 1e-4 and moved[region].min() > 1.0
    # fit3d accepts the edited actor like any other.
    assert main(["fit3d", str(rt / "meshes"), "--actor", str(out), "--out", str(tmp_path / "f3"), "--formats", "npz",
                 "--iterations", "20", "--window", "8", "--no-progress"]) == 0


def test_region_files_and_bad_input(actors, tmp_path, capsys):
    from capture.actor.edit import read_region
    from models.anatomy_edit import region_weight

    root, a, _ = actors
    tmpl = trimesh.load(a / "template.ply", process=False)
    V = len(tmpl.vertices)
    # A painted PLY: grey levels are the mask (mean of R, G, B / 255).
    colours = np.zeros((V, 4), np.uint8)
    colours[:, 3] = 255
    colours[[5, 6, 7], :3] = 255
    colours[8, :3] = 51
    painted = trimesh.Trimesh(tmpl.vertices, tmpl.faces, vertex_colors=colours, process=False)
    painted.export(tmp_path / "mask.ply")
    idx, m = read_region(tmp_path / "mask.ply", V)
    assert idx.tolist() == [5, 6, 7, 8] and np.allclose(m, [1, 1, 1, 0.2])
    (tmp_path / "soft.json").write_text(json.dumps({"vertices": [5, 9], "weights": [1.0, 0.5]}))
    idx, m = read_region(tmp_path / "soft.json", V)
    assert idx.tolist() == [5, 9] and m.tolist() == [1.0, 0.5]
    # Soft masks: w(c) = max_i m_i phi(...) against a brute-force numpy reference at random points.
    rng = np.random.default_rng(0)
    pts, c = rng.normal(size=(7, 3)) * 10, rng.normal(size=(50, 3)) * 15
    mask = rng.uniform(0.1, 1.0, 7)
    dd = np.linalg.norm(c[:, None] - pts[None], axis=-1)
    tt = np.clip((dd - 2.0) / 9.0, 0, 1)
    ref = (mask * (1 - tt * tt * (3 - 2 * tt))).max(1)
    got = region_weight(torch.tensor(c), torch.tensor(pts), torch.tensor(mask), 2.0, 9.0, chunk=16).numpy()
    assert np.allclose(got, ref, atol=1e-12)

    def edit(*args):
        return main(["actor", "edit", str(a), "--out", str(tmp_path / "E"), *args])

    (tmp_path / "bad.json").write_text(json.dumps([0, V + 3]))
    assert edit("--thickness-scale", "1.2", "--region", str(tmp_path / "bad.json")) == 2
    assert "0.." in _error(capsys)
    plain = trimesh.Trimesh(tmpl.vertices, tmpl.faces, process=False)
    plain.export(tmp_path / "plain.ply")
    assert edit("--thickness-scale", "1.2", "--region", str(tmp_path / "plain.ply")) == 2
    assert "no vertex colours" in _error(capsys)
    assert edit("--thickness-scale", "-1", "--region", str(tmp_path / "soft.json")) == 2
    assert "--thickness-scale" in _error(capsys)
    assert main(["actor", "edit", str(a), "--out", str(a), "--thickness-scale", "1.2", "--region",
                 str(tmp_path / "soft.json")]) == 2
    assert "source actor itself" in _error(capsys)
    assert not (tmp_path / "E").exists()
