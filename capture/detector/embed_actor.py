"""``capture actor embed A --detector X.onnx ...``: make and write ``A/landmarks/<detector>.json``.

Resolves the actor once (a bundled actor is copied to the user's actors first, with a one-line note),
reads the landmarks in the given form (:mod:`.embed`), checks the count against the detector, writes
the embedding atomically and a residual report beside it (``<detector>.report.json``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from capture.io.errors import CaptureError

REPORT_SUFFIX = ".report.json"


@dataclass
class EmbedConfig:
    actor: str
    detector: Path
    vertices: Path | None = None
    triangles: Path | None = None
    topology: Path | None = None       # with triangles: the mesh they index (same vertices as the template)
    points: Path | None = None
    mesh: Path | None = None           # the detector's canonical mesh (vertex l = landmark l)
    pairs: Path | None = None          # with mesh: landmark/vertex pairs (default: automatic)
    units: str = "mm"                  # of points / mesh
    overwrite: bool = False
    refine: Path | None = None         # a take of the actor: refine the embedding on it
    camera: Path | None = None         # the take's camera (default: the documented guess)
    refine_frames: int = 8
    cache: Path | None = None          # detection cache folder (default ./runs/<take stem>, shared with capture run)


def run_embed(cfg: EmbedConfig, say=print) -> tuple[Path, dict]:
    """Make and write the embedding; returns its path and the report."""
    import trimesh

    from capture.actor.package import TEMPLATE, read_metadata, resolve_actor, user_copy_of_bundled
    from capture.detector import embed as E
    from capture.detector.embedding import embedding_from_vertices, embedding_path, write_embedding
    from capture.detector.runtime import Detector
    from capture.io.atomic import write_json

    given = [k for k in ("vertices", "triangles", "points", "mesh") if getattr(cfg, k) is not None]
    if len(given) > 1 or (not given and cfg.refine is None):
        raise CaptureError("give exactly one of --vertices, --triangles, --points or --mesh "
                           f"(got {', '.join('--' + g for g in given) or 'none'}), or --refine TAKE alone to "
                           f"refine the actor's existing embedding")
    if cfg.topology is not None and cfg.triangles is None:
        raise CaptureError("--topology goes with --triangles (the mesh whose triangles they index)")
    if cfg.pairs is not None and cfg.mesh is None:
        raise CaptureError("--pairs goes with --mesh (landmark/template-vertex pairs for the alignment)")
    read_metadata(cfg.actor)                       # one-line error for an unknown actor
    path = resolve_actor(cfg.actor)
    detector = Detector.load(cfg.detector, threads=1)
    name, count = detector.name, detector.count
    path, note = user_copy_of_bundled(path, cfg.actor if not Path(cfg.actor).is_dir() else None)
    if note:
        say(note)
    out = embedding_path(path, name)
    if out.exists() and not cfg.overwrite and given:
        raise CaptureError(f"actor {path.name} already has an embedding for detector '{name}' ({out}); pass "
                           f"--overwrite to replace it")
    template = trimesh.load(path / TEMPLATE, process=False, maintain_order=True, force="mesh")

    if not given:
        from capture.detector.embedding import read_embedding

        emb = read_embedding(path, name, template, count)
        report = {"method": f"the existing embedding ({emb.source or 'no source noted'})"}
    elif cfg.vertices is not None:
        ids = E.read_ints(cfg.vertices)
        _check_count(len(ids), count, name, cfg.vertices)
        emb = embedding_from_vertices(template, ids, name, f"vertex ids from {Path(cfg.vertices).name}")
        report = {"method": "vertex ids"}
    elif cfg.triangles is not None:
        fi, bc = E.read_triangles(cfg.triangles)
        _check_count(len(fi), count, name, cfg.triangles)
        topo = None
        if cfg.topology is not None:
            topo = trimesh.load(cfg.topology, process=False, maintain_order=True, force="mesh")
        emb, report = E.embedding_from_triangles(template, fi, bc, name,
                                                 f"triangles from {Path(cfg.triangles).name}", topo)
    elif cfg.points is not None:
        pts = E.read_points(cfg.points, cfg.units)
        _check_count(len(pts), count, name, cfg.points)
        emb, dist = E._closest(template, pts, name, f"closest points to {Path(cfg.points).name}")
        report = {"method": "closest surface points", "surface_distance": E.surface_report(dist)}
        if report["surface_distance"]["max_mm"] > 10.0:
            raise CaptureError(f"landmark point {report['surface_distance']['worst'][0]['landmark']} is "
                               f"{report['surface_distance']['max_mm']:.1f} mm from the template; are the points in "
                               f"the template's frame, and is --units right?")
    else:
        pts = E.read_mesh_vertices(cfg.mesh, cfg.units)
        _check_count(len(pts), count, name, cfg.mesh)
        pairs = E.read_pairs(cfg.pairs) if cfg.pairs is not None else None
        emb, report = E.embedding_from_canonical_mesh(template, pts, name, pairs,
                                                      f"canonical mesh {Path(cfg.mesh).name}")
    if cfg.refine is not None:
        emb, report["refine"] = _refine(cfg, path, detector, emb, template, say)
    write_embedding(path, emb, template)
    report = {"detector": name, "count": count, "actor": str(path), **report}
    write_json(out.with_name(out.stem + REPORT_SUFFIX), report)
    return out, report


def _refine(cfg: EmbedConfig, actor_path: Path, detector, emb, template, say) -> tuple:
    """Detect on the take (cached), pick well-spread frames and refine the embedding on them."""
    import numpy as np

    from capture.actor.package import load_actor
    from capture.detector.pipeline import detect_video
    from capture.detector.refine import RefineSettings, refine_embedding, select_frames
    from capture.io.video import open_video
    from capture.run.inputs import resolve_camera

    take = Path(cfg.refine)
    if not take.is_file():
        raise CaptureError(f"--refine take {take} does not exist; check the path")
    if cfg.refine_frames < 2:
        raise CaptureError(f"--refine-frames must be at least 2, got {cfg.refine_frames}")
    with open_video(take) as reader:
        info = reader.info
    cam = resolve_camera(cfg.camera, info.width, info.height)
    say(cam.note)
    cache = Path(cfg.cache) if cfg.cache is not None else Path("runs") / take.stem
    track = detect_video(take, detector, cache_dir=cache, progress=False,
                         query_points=None if detector.spec.kind != "query" else _points(emb, template))
    w = (np.isfinite(track.points).all(axis=2).astype(np.float64) if track.confidence is None
         else np.nan_to_num(track.confidence))
    sel = select_frames(track.points, w, track.face_found, cfg.refine_frames)
    say(f"refining on frames {', '.join(map(str, sel))} of {take.name}")
    actor = load_actor(str(actor_path))
    res = refine_embedding(actor.model, template, emb, track.points[sel], w[sel], cam.camera.K, cam.camera.dist,
                           RefineSettings(frames=cfg.refine_frames), frames=sel, say=say)
    rep = res.report() | {"take": str(take), "camera": cam.source}
    return res.embedding, rep


def _points(emb, template):
    from capture.detector.embedding import embedded_points

    return embedded_points(emb, template)


def _check_count(n: int, count: int, name: str, src: Path) -> None:
    if n != count:
        raise CaptureError(f"{src} gives {n} landmarks but detector '{name}' has landmarks.count = {count}; "
                           f"give one entry per landmark, in the detector's order")


def report_lines(report: dict) -> list[str]:
    """The report as a few lines for the terminal."""
    lines = [f"{report['method']}: {report['count']} landmarks of '{report['detector']}' on {report['actor']}"]
    if "transform" in report:
        t = report["transform"]
        lines.append(f"similarity: scale {t['scale']:.5g}, translation "
                     + ", ".join(f"{x:.2f}" for x in t["translation_mm"]) + " mm")
    if "pairs_residual" in report:
        r = report["pairs_residual"]
        lines.append(f"pair residual after the similarity: RMS {r['rms_mm']:.3f} mm, max {r['max_mm']:.3f} mm")
    for key, what in (("surface_distance", "moved to the surface"), ("moved_to_surface", "moved to the surface")):
        if key in report:
            s = report[key]
            lines.append(f"{what}: median {s['median_mm']:.3f} mm, p95 {s['p95_mm']:.3f} mm, max {s['max_mm']:.3f} mm "
                         f"(worst: " + ", ".join(f"{w['landmark']} {w['mm']:.2f}" for w in s["worst"][:3]) + ")")
    if "refine" in report:
        r = report["refine"]
        lines.append(f"refined on {len(r['frames'])} frames: reprojection RMS {r['reprojection_before_rms_px']:.3f} px "
                     f"before, {r['reprojection_after_rms_px']:.3f} px after; landmarks moved median "
                     f"{r['moved_mm']['median']:.2f} mm, max {r['moved_mm']['max']:.2f} mm")
        few = r.get("landmarks_seen_in_fewer_than_2_frames", [])
        if few:
            lines.append(f"{len(few)} landmarks were confident in fewer than 2 of the frames and are barely refined "
                         f"(occluded or unreliable there): " + ", ".join(map(str, few[:10]))
                         + (" ..." if len(few) > 10 else ""))
    if "warning" in report:
        lines.append("WARNING: " + report["warning"])
    return lines
