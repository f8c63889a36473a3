"""``capture batch`` on the embedded local Ray: a shoot of short synthetic takes and one broken take.

Ray is started once for the module (2 CPUs, by the code ``capture batch`` starts it with on this
machine); the command uses the Ray the process already has. The broken take (a text file named .mp4) is reported
and does not stop the others; a rerun does no work; a dead worker's take is retried once; the shoot
file's mistakes are one-line errors; relative paths are resolved against the shoot file's folder.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest

from capture.cli import main
from capture.io.errors import CaptureError
from capture.batch.shoot import load_shoot
from tests.tiny_actor import synth_tiny_take, train_tiny_actor

FRAMES = {"a": 20, "b": 10}


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


SHOOT = """
[shoot]
name = "day1"
out = "out"

[defaults]
actor = "actors/tiny"          # relative to this file
iterations = 20
window = 8
formats = ["obj", "npz"]

[[take]]
name = "a"
video = "takes/a/take.mp4"
camera = "takes/a/camera.json"

[[take]]
name = "b"
video = "takes/b/take.mp4"
camera = "takes/b/camera.json"
frames = "0:10"
formats = "obj,usd,npz,overlay"
"""

BROKEN = """
[[take]]
name = "broken"
video = "takes/broken/take.mp4"
"""


@pytest.fixture(scope="module")
def ray_local():
    """The embedded local Ray, started by the command's own code once for the module (2 CPUs)."""
    from capture.batch import cluster

    info = cluster.connect(None, workers=2, threads=1)
    assert (info.mode, info.cpus, info.nodes) == ("embedded", 2.0, 1)
    yield
    cluster.disconnect(info)


@pytest.fixture(scope="module")
def shoot_dir(tmp_path_factory):
    """A shoot folder: the tiny actor, two short synthetic takes, a broken take, and the shoot files."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("shoot")
    train_tiny_actor(root)   # -> root/actors/tiny
    for name, n in FRAMES.items():
        synth_tiny_take(root / "actors" / "tiny", root / "takes" / name, frames=n)
    (root / "takes" / "broken").mkdir()
    (root / "takes" / "broken" / "take.mp4").write_text("not a video")
    _write(root / "shoot.toml", SHOOT + BROKEN)
    _write(root / "shoot_ok.toml", SHOOT)
    _write(root / "shoot_a.toml", SHOOT.split("[[take]]")[0] + "[[take]]" + SHOOT.split("[[take]]")[1])
    yield root
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def first_batch(shoot_dir, ray_local):
    cwd = os.getcwd()
    os.chdir(shoot_dir.parent)   # not the shoot folder: paths must resolve against the file's folder
    try:
        code = main(["batch", str(shoot_dir / "shoot.toml"), "--workers", "2", "--no-progress"])
    finally:
        os.chdir(cwd)
    return code, json.loads((shoot_dir / "out" / "batch_report.json").read_text())


def test_dry_run_lists_the_takes_and_runs_nothing(shoot_dir, capsys):
    assert main(["batch", str(shoot_dir / "shoot.toml"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    for name in ("a", "b", "broken"):
        assert name in out
    assert "3 of 3 takes would run (30 frames)" in " ".join(out.split())
    assert not (shoot_dir / "out").exists()


def test_batch_runs_every_take_and_reports_the_broken_one(shoot_dir, first_batch):
    code, report = first_batch
    assert code == 1   # a take failed
    rows = {r["take"]: r for r in report["takes"]}
    assert [rows[k]["status"] for k in ("a", "b", "broken")] == ["done", "done", "failed"]
    assert "video" in rows["broken"]["error"] and rows["broken"]["attempts"] == 1   # input errors: no retry
    assert report["totals"]["done"] == 2 and report["totals"]["failed"] == 1
    assert report["totals"]["frames_fitted"] == sum(FRAMES.values())
    assert report["ray"]["mode"] == "existing" and report["ray"]["workers"] == 2
    for name, n in FRAMES.items():
        run = shoot_dir / "out" / name
        take_report = json.loads((run / "report.json").read_text())
        assert take_report["frames"]["fitted"] == n == rows[name]["frames_fitted"]
        assert take_report["settings"]["fit_settings"]["iterations"] == 20
        assert take_report["settings"]["threads"] == 1
        # The layout of capture run --out: meshes, params and the caches; the take's log and state.
        assert len(list((run / "meshes").glob("frame_*.obj"))) == n
        with np.load(run / "params.npz", allow_pickle=False) as p:
            assert p["frame_index"].tolist() == list(range(n))
        assert rows[name]["reprojection_mean_px"] == pytest.approx(take_report["error"]["mean"])
        spans = take_report["unexplained"]["spans"]       # the frames its runs cover, each once
        assert rows[name]["frames_unexplained"] == len({f for sp in spans for f in range(sp["first"], sp["last"] + 1)})
        assert "done" in (run / "batch_take.log").read_text()
        state = json.loads((run / "batch_take.json").read_text())
        assert state["status"] == "done"
        # The take's worker ran at this process's niceness, not at Ray's default of 15 (which lets any
        # other job on the machine starve it).
        assert state["attempts"][0]["niceness"] == os.nice(0) != 15
    assert (shoot_dir / "out" / "b" / "overlay.mp4").is_file() and list((shoot_dir / "out" / "b").glob("take.usd*"))
    assert not (shoot_dir / "out" / "a" / "overlay.mp4").exists()
    assert "failed" in (shoot_dir / "out" / "broken" / "batch_take.log").read_text()
    with open(shoot_dir / "out" / "batch_summary.csv", newline="") as fh:
        table = {r["take"]: r for r in csv.DictReader(fh)}
    assert table["a"]["status"] == "done" and int(table["b"]["frames_fitted"]) == 10
    assert int(table["b"]["frames_unexplained"]) == rows["b"]["frames_unexplained"]
    assert table["broken"]["status"] == "failed" and table["broken"]["error"]


def test_rerun_does_no_work(shoot_dir, first_batch, capsys):
    runs = shoot_dir / "out"
    before = {p: p.stat().st_mtime_ns for p in runs.rglob("*") if p.is_file() and p.parent != runs}
    assert main(["batch", str(shoot_dir / "shoot_ok.toml"), "--out", str(runs), "--no-progress"]) == 0
    report = json.loads((runs / "batch_report.json").read_text())
    assert [r["status"] for r in report["takes"]] == ["already done", "already done"]
    assert report["ray"] is None                              # no task was even submitted
    after = {p: p.stat().st_mtime_ns for p in runs.rglob("*") if p.is_file() and p.parent != runs}
    assert after == before
    assert "already done" in capsys.readouterr().out


def test_a_long_take_split_into_segments_is_stitched_from_them(shoot_dir, first_batch):
    """Take a (20 frames, window 8) in segments of at most 17 frames: 0:14 and 6:20, blended over 6:14."""
    from capture.batch.segments import _smoothstep
    from capture.fit.take import FrameFit
    from capture.run.stages import iter_fits

    out = shoot_dir / "seg"
    assert main(["batch", str(shoot_dir / "shoot_a.toml"), "--out", str(out), "--segment-frames", "17",
                 "--no-progress"]) == 0
    whole, split = shoot_dir / "out" / "a", out / "a"
    report = json.loads((split / "report.json").read_text())
    assert report["segments"]["frames"] == [[0, 14], [6, 20]]
    assert report["settings"]["segments"] == [[0, 14], [6, 20]]
    stitched = [json.loads(k.read_text()) for k in split.glob("fit/*/key.json")]
    assert len(stitched) == 1 and stitched[0]["segments"] == [[0, 14], [6, 20]]   # not an unsplit fit's key
    assert report["frames"]["fitted"] == 20
    # The layout of an unsplit run, and the very same detections (the detector's tracking units are
    # independent 32-frame blocks at absolute frame numbers).
    files = lambda d: sorted(str(p.relative_to(d)) for p in d.rglob("*")
                             if p.is_file() and p.parts[len(d.parts)] not in ("fit", "detections"))
    assert files(split) == files(whole)
    with np.load(whole / "detections" / "track.npz") as a, np.load(split / "detections" / "track.npz") as b:
        np.testing.assert_array_equal(a["points"], b["points"])
    # Outside the overlap each frame is its segment's fit; inside, the smoothstep blend of both.
    seg = [{f.frame: f for f in iter_fits(Path(d))} for d in report["segments"]["segment_fit_dirs"]]
    with np.load(split / "params.npz") as p:
        assert p["frame_index"].tolist() == list(range(20))
        for i in range(20):
            if i < 6 or i >= 14:
                want = (seg[0] if i < 6 else seg[1])[i].head_t
            else:
                alpha = _smoothstep((i - 6 + 1) / 9)
                want = (1 - alpha) * seg[0][i].head_t + alpha * seg[1][i].head_t
            np.testing.assert_allclose(p["head_t_mm"][i], want, rtol=0, atol=1e-4, err_msg=f"frame {i}")
    assert max(np.abs(seg[0][i].head_t - seg[1][i].head_t).max() for i in range(6, 14)) > 1e-3   # a real blend
    assert isinstance(seg[0][0], FrameFit)
    # As close to the truth as the unsplit fit is asserted to be in test_run (tiny, briefly trained actor).
    truth = np.load(shoot_dir / "takes" / "a" / "truth_meshes.npz")["vertices"]
    import trimesh

    for i in (3, 10, 17):
        v = trimesh.load(split / "meshes" / f"frame_{i:06d}.obj", process=False).vertices
        assert np.linalg.norm(v - truth[i], axis=1).mean() < 10.0


def test_a_take_folder_is_claimed_beside_the_batch_files_and_concurrent_writes(tmp_path):
    """Segments of one take claim its folder concurrently: the batch's log and another task's atomic write
    in progress (a hidden temporary sibling) must not make the folder look like someone else's."""
    from capture.run.store import claim_run_dir

    out = tmp_path / "take"
    out.mkdir()
    (out / "batch_take.log").write_text("log")
    (out / ".run.abc123.json").write_text("{")
    claim_run_dir(out, "id", "take.mp4", overwrite=False)
    (out / "notes.txt").write_text("mine")
    with pytest.raises(CaptureError, match="not empty"):
        claim_run_dir(out, "id", "take.mp4", overwrite=False)


def test_segment_plan():
    from capture.batch.segments import plan_segments

    assert plan_segments(0, 100, 40, 10) == [(0, 40), (30, 70), (60, 100)]
    assert plan_segments(5, 30, 40, 10) == [(5, 30)]
    for n in range(1, 200, 7):
        for size, ov in ((17, 8), (40, 10), (300, 30)):
            segs = plan_segments(3, 3 + n, size, ov)
            assert segs[0][0] == 3 and segs[-1][1] == 3 + n
            assert all(e - s <= size for s, e in segs)
            assert all(a[1] - b[0] == ov for a, b in zip(segs, segs[1:]))   # each seam shares the overlap


def test_a_changed_setting_or_input_runs_the_take_again(shoot_dir, first_batch, tmp_path):
    import dataclasses
    import shutil

    from capture.batch.take import done_result, take_key

    cfg = load_shoot(shoot_dir / "shoot_ok.toml", shoot_dir / "out").takes[0].config
    key = take_key(cfg)
    assert done_result(cfg, key)["frames_fitted"] == FRAMES["a"]
    assert take_key(dataclasses.replace(cfg, threads=4, progress=True)) == key      # no effect on the outputs
    assert take_key(dataclasses.replace(cfg, iterations=21)) != key
    assert take_key(cfg, segments=[(0, 14), (6, 20)]) != key
    cam = json.loads(cfg.camera.read_text())
    cam["K"][0][0] += 1.0
    moved = tmp_path / "camera.json"
    moved.write_text(json.dumps(cam))
    assert take_key(dataclasses.replace(cfg, camera=moved)) != key                   # the file's content counts
    shutil.copy(cfg.camera, moved)
    assert take_key(dataclasses.replace(cfg, camera=moved)) == key                   # not its path


def test_a_dead_worker_is_retried_once(tmp_path, ray_local):
    import ray

    from capture.batch import cluster

    @ray.remote(max_retries=0)
    def dies_once(marker: str, name: str, attempt: int, threads: int, counter):
        if not Path(marker).exists():
            Path(marker).write_text("died")
            os._exit(1)                                      # the worker process dies
        ray.get(counter.add.remote(name, 5))                 # (a real take's last count may race its result)
        return {"take": name, "status": "done", "frames_fitted": 5}

    def always_fails(marker, name, attempt, threads, counter):
        return {"take": name, "status": "failed", "error": "boom", "retry": True}

    results, frames = {}, {}
    jobs = [cluster.Job("x", (str(tmp_path / "marker"), "x")), cluster.Job("y", ("-", "y"))]
    cluster.run_tasks(jobs[:1], 1, 1, lambda j, r: results.setdefault(j.name, r), frames.update, poll=0.1,
                        task=dies_once)
    assert results["x"]["status"] == "done" and results["x"]["attempt"] == 2
    assert frames == {"x": 5}                                 # the frames the task reported reach the driver
    assert jobs[0].attempts[0]["status"] == "failed" and "worker" in jobs[0].attempts[0]["error"]
    cluster.run_tasks(jobs[1:], 1, 1, lambda j, r: results.setdefault(j.name, r), poll=0.1,
                        task=ray.remote(max_retries=0)(always_fails))
    assert results["y"]["status"] == "failed" and len(jobs[1].attempts) == 2   # once, then once more


def test_a_take_whose_files_a_node_cannot_reach_fails_at_once(shoot_dir, tmp_path, ray_local):
    """Before any work the worker checks that it can read the take's inputs and write its output folder;
    when it cannot, the take fails at once (no retry) with one line naming the path and the node."""
    import dataclasses
    import socket

    from capture.batch import cluster

    cfg = load_shoot(shoot_dir / "shoot_ok.toml", tmp_path / "out").takes[0].config
    (tmp_path / "file").write_text("a file, not a folder")
    cases = {"no_video": dataclasses.replace(cfg, video=tmp_path / "nfs" / "take.mp4"),
             "no_camera": dataclasses.replace(cfg, camera=tmp_path / "nfs" / "camera.json"),
             "no_out": dataclasses.replace(cfg, out=tmp_path / "file" / "take")}
    results = {}
    jobs = [cluster.Job(k, (c, k)) for k, c in cases.items()]
    cluster.run_tasks(jobs, 2, 1, lambda j, r: results.setdefault(j.name, r), poll=0.1)
    want = {"no_video": f"cannot read the video {tmp_path / 'nfs' / 'take.mp4'} (No such file",
            "no_camera": f"cannot read the camera file {tmp_path / 'nfs' / 'camera.json'}",
            "no_out": f"cannot write the output folder {tmp_path / 'file' / 'take'} (Not a directory"}
    for name, text in want.items():
        r = results[name]
        assert r["status"] == "failed" and len(next(j for j in jobs if j.name == name).attempts) == 1   # no retry
        assert text in r["error"] and f"on node {socket.gethostname()} (Ray node " in r["error"], r["error"]
        assert "\n" not in r["error"] and "shared storage" in r["error"]
        assert r["seconds"] < 30                                  # at once: no detection, no fit
    assert not (tmp_path / "out" / "a" / "batch_take.log").exists()   # nothing was run


def test_joining_a_cluster_that_is_not_there_is_one_line(monkeypatch, tmp_path):
    from capture.batch.cluster import find_token, probe_cluster

    log = tmp_path / "ray.log"
    with pytest.raises(CaptureError) as exc:
        probe_cluster("127.0.0.1:1", None, log)
    msg = str(exc.value)
    assert "nothing answers there" in msg and "check the address" in msg and "\n" not in msg
    # The token is looked for where Ray's CLI looks (RAY_AUTH_MODE=disabled turns it off).
    monkeypatch.setenv("RAY_AUTH_MODE", "token")
    monkeypatch.delenv("RAY_AUTH_TOKEN", raising=False)
    monkeypatch.setenv("RAY_AUTH_TOKEN_PATH", str(tmp_path / "token"))
    assert find_token() == str(tmp_path / "token")
    monkeypatch.setenv("RAY_AUTH_TOKEN", "abc")
    assert find_token() == "RAY_AUTH_TOKEN"
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    assert find_token() is None


def test_joining_a_cluster_of_another_ray_version_names_the_skew(monkeypatch, tmp_path):
    """A head that answers with another Ray release in its metadata: one line naming both versions. The
    head is a listening socket (the reachability check) and a stand-in GCS client (Ray's own class,
    replaced: a second Ray release cannot be installed here)."""
    import json
    import socket
    import sys

    import ray
    import ray._raylet

    from capture.batch.cluster import probe_cluster

    class OtherRelease:
        def __init__(self, address):
            self.address = address

        def internal_kv_get(self, key, namespace=None, timeout=None):
            assert key == b"CLUSTER_METADATA"
            return json.dumps({"ray_version": "1.13.0", "python_version": "3.7.16"}).encode()

    monkeypatch.setattr(ray._raylet, "GcsClient", OtherRelease)
    with socket.socket() as head:
        head.bind(("0.0.0.0", 0))   # Ray turns 127.0.0.1 into this node's address
        head.listen()
        address = f"127.0.0.1:{head.getsockname()[1]}"
        with pytest.raises(CaptureError) as exc:
            probe_cluster(address, None, tmp_path / "ray.log")
    msg = str(exc.value)
    ours = f"Ray {ray.__version__} on Python {sys.version_info[0]}.{sys.version_info[1]}"
    assert "version skew: the cluster runs Ray 1.13.0 on Python 3.7" in msg and ours in msg, msg
    assert address in msg and "\n" not in msg


def test_shoot_file_mistakes_are_one_line_errors(tmp_path, monkeypatch):
    monkeypatch.delenv("CAPTURE_ACTORS", raising=False)
    ok = '[defaults]\nactor = "anna"\n\n[[take]]\nvideo = "v/t1.mp4"\n'
    shoot = load_shoot(_write(tmp_path / "s.toml", ok))
    t = shoot.takes[0]
    assert t.name == "t1" and t.config.video == tmp_path / "v" / "t1.mp4"
    assert t.config.actor == str(tmp_path / "actors" / "anna") and t.config.out == tmp_path / "runs" / "s" / "t1"
    cases = {
        ok + 'iteratons = 5\n': "unknown key 'iteratons' in take 1",
        ok.replace("[defaults]", "[default]"): "unknown key 'default'",
        ok + '\n[[take]]\nvideo = "w/t1.mp4"\n': "take name 't1' is used by takes 1 and 2",
        ok + 'seed = "one"\n': "'seed' in take 1 must be an integer",
        ok + 'window = true\n': "must be an integer",
        ok + 'formats = "obj,gif"\n': "gif",
        '[[take]]\nvideo = "a.mp4"\n': "has no actor",
        '[defaults]\nactor = "a"\n\n[[take]]\nname = "x"\n': "has no 'video'",
        '[defaults]\nactor = "a"\n': "lists no takes",
        '[take]\nvideo = "a.mp4"\n': "[[take]] (two brackets)",
        'take = [': "not valid TOML",
    }
    for text, msg in cases.items():
        with pytest.raises(CaptureError) as exc:
            load_shoot(_write(tmp_path / "bad.toml", text))
        assert msg in str(exc.value), (text, str(exc.value))
    assert main(["batch", str(_write(tmp_path / "bad.toml", ok + "bogus = 1\n"))]) == 2
    # The documented example is a valid shoot file.
    example = load_shoot(Path(__file__).resolve().parents[1] / "docs" / "shoot_example.toml")
    assert [t.name for t in example.takes] == ["t001_neutral", "t002_dialogue", "t003_b_cam"]
    assert example.takes[2].config.camera.name == "cam_b.json" and example.takes[1].config.frames == "120:2400"
    assert example.takes[2].config.iterations == 800 and example.takes[0].config.iterations == 500
    assert main(["batch", str(tmp_path / "missing.toml")]) == 2


# ------------------------------------------------------------------------------ a real Ray cluster
CLUSTER_SHOOT = """
[defaults]
actor = "actors/tiny"
iterations = 20
window = 8
formats = ["obj", "npz"]

[[take]]
name = "a"
video = "takes/a/take.mp4"
camera = "takes/a/camera.json"

[[take]]
name = "b"
video = "takes/b/take.mp4"
camera = "takes/b/camera.json"
"""


def _same_outputs(ref: Path, got: Path) -> None:
    """Byte-identical meshes and equal parameter arrays (report.json and run.json hold timings and paths)."""
    meshes = sorted(p.name for p in (ref / "meshes").glob("*.obj"))
    assert meshes and meshes == sorted(p.name for p in (got / "meshes").glob("*.obj"))
    for m in meshes:
        assert (ref / "meshes" / m).read_bytes() == (got / "meshes" / m).read_bytes(), m
    with np.load(ref / "params.npz") as a, np.load(got / "params.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.slow
def test_a_shoot_on_a_two_node_cluster_survives_a_dead_node(shoot_dir, tmp_path):
    """Two Ray nodes (separate GCS/raylet processes on 127.0.0.1, token authentication on, the token in
    the driver's ~/.ray/auth_token only). ``capture batch --address`` joins without RAY_AUTH_MODE; the
    worker node is killed while it runs a take: that take is retried on the head node and finishes,
    and both takes' outputs are identical to ``capture run`` on each take."""
    import subprocess
    import sys
    import time

    from tests.ray_cluster import LocalCluster

    shoot = _write(shoot_dir / "shoot_cluster.toml", CLUSTER_SHOOT)
    with LocalCluster(nodes=2, cpus=1) as cluster:
        env = cluster.driver_env()
        # A driver without the token cannot join: one line naming the token, no log flood. (--address auto
        # finds the cluster `ray start` recorded in this machine's Ray temp folder, here the cluster's.)
        no_token = subprocess.run([sys.executable, "-m", "capture.cli", "batch", str(shoot), "--out",
                                   str(tmp_path / "x"), "--address", "auto"],
                                  env={**env, "HOME": str(tmp_path)}, capture_output=True, text=True, timeout=300,
                                  check=False)
        assert no_token.returncode == 2
        lines = (no_token.stdout + no_token.stderr).strip().splitlines()
        assert len(lines) == 1 and "token" in lines[0] and cluster.address in lines[0], lines

        out = tmp_path / "runs"
        driver = subprocess.Popen([sys.executable, "-m", "capture.cli", "batch", str(shoot), "--out", str(out),
                                   "--address", cluster.address, "--no-progress"], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        worker_node = cluster.node_ids[1][:8]
        victim, deadline = None, time.monotonic() + 240
        while victim is None and time.monotonic() < deadline and driver.poll() is None:
            for name in ("a", "b"):
                log = out / name / "batch_take.log"
                if log.is_file() and f"Ray node {worker_node}" in log.read_text():
                    victim = name
            time.sleep(0.2)
        assert victim is not None, "no take started on the worker node"
        time.sleep(1.0)                                         # into the take's work
        assert not (out / victim / "report.json").exists()      # still running
        cluster.kill(1)
        stdout, _ = driver.communicate(timeout=600)
    assert driver.returncode == 0, stdout
    report = json.loads((out / "batch_report.json").read_text())
    assert report["ray"]["mode"] == "cluster" and report["ray"]["nodes"] == 2 and report["ray"]["auth"] == "token"
    rows = {r["take"]: r for r in report["takes"]}
    assert [rows[k]["status"] for k in ("a", "b")] == ["done", "done"]
    assert rows[victim]["attempts"] == 2
    state = json.loads((out / victim / "batch_take.json").read_text())
    assert state["attempts"][0]["status"] == "failed" and "worker" in state["attempts"][0]["error"]
    assert worker_node not in state["attempts"][1]["node"]     # the retry ran on the other node

    for name in ("a", "b"):
        take = shoot_dir / "takes" / name
        ref = tmp_path / f"run_{name}"
        assert main(["run", str(take / "take.mp4"), "--actor", str(shoot_dir / "actors" / "tiny"), "--camera",
                     str(take / "camera.json"), "--out", str(ref), "--iterations", "20", "--window", "8",
                     "--formats", "obj,npz", "--threads", "1", "--no-progress"]) == 0
        _same_outputs(ref, out / name)
