"""Do anatomical rules say how an unseen expression moves in depth? (issue 12, "What limits it")

From 2D landmarks the depth of the lips is not determined (``bench_outofspan_limits.py``); a prior would
have to supply it. Two anatomical rules could, if the truth obeyed them. On ICT's held-out expressions
(the identity of the sample actor, each at weights 1 and 0.5), over the mouth region's vertices that the
expression moves by more than 1 mm (``bench_outofspan.region_masks``), against the actor's bones
(``BONES_DIR`` of the actor: skull and jaw fitted to its neutral, mm, template frame):

* **constant tissue thickness** (the skin slides over the bone, as lips over the teeth): the change of
  each vertex's distance to the bone, against its motion along the bone's normal at rest (what the
  linear prior ``bone normal`` of the field removes); and the depth the rule predicts, the point on the
  vertex's true sideways and vertical position (template x, y; the face looks along +z) whose distance to
  the bone is the rest distance, nearest the rest depth, against "no depth motion" (the rest depth);
* **constant tissue volume** (soft tissue is nearly incompressible): the vertex's distance to the bone
  scaled by the inverse of its one-ring area's stretch (and by its square root), against no change.

Printed per expression and pooled (RMS, mm). A rule helps where its error is well below the error of
"no change"; the bone distances are to 400,000 points drawn evenly on the bones (spacing ~0.3 mm).

    python benchmarks/bench_depth_rules.py [--actor capture/data/demo_actor] [--every 2]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages
from benchmarks.bench_outofspan import SAMPLE_JSON, region_masks
from benchmarks.heldout import DEFAULT_ICT, EXCLUDED, load_ict_identity, sample_actor_split
from benchmarks.takes import DEFAULT_ACTOR, REPO

DEPTH_SEARCH_MM = 6.0      # the thickness rule's depth is searched within this of the rest depth
DEPTH_STEP_MM = 0.05


def one_ring_area(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(V,)`` a third of the area of the triangles around each vertex."""
    a = 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                      vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    out = np.zeros(len(vertices))
    for k in range(3):
        np.add.at(out, faces[:, k], a / 3)
    return out


def thickness_depth(tree, rest: np.ndarray, moved: np.ndarray, d0: np.ndarray) -> np.ndarray:
    """``(N,)`` the depth (template z) at each moved point's true x, y whose bone distance is ``d0``, nearest
    the rest depth (the rest depth where no such depth lies within ``DEPTH_SEARCH_MM``)."""
    off = np.arange(-DEPTH_SEARCH_MM, DEPTH_SEARCH_MM + DEPTH_STEP_MM / 2, DEPTH_STEP_MM)
    q = np.repeat(moved[:, None, :], len(off), 1)
    q[:, :, 2] = rest[:, None, 2] + off
    f = tree.query(q.reshape(-1, 3))[0].reshape(len(moved), len(off)) - d0[:, None]
    z = rest[:, 2].copy()
    for k in range(len(moved)):
        s = np.flatnonzero(np.sign(f[k, :-1]) != np.sign(f[k, 1:]))
        if len(s):
            r = off[s] - f[k, s] * (off[s + 1] - off[s]) / (f[k, s + 1] - f[k, s])
            z[k] += r[np.argmin(np.abs(r))]
    return z


def main(argv: list[str] | None = None) -> dict:
    import trimesh
    from scipy.spatial import cKDTree

    from capture.actor.package import BONES_DIR
    from capture.io.atomic import write_text

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--actor", default=str(DEFAULT_ACTOR))
    ap.add_argument("--ict", default=str(DEFAULT_ICT))
    ap.add_argument("--every", type=int, default=2, help="every n-th moving vertex (the depth search is slow)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "depth_rules.json"))
    args = ap.parse_args(argv)

    bone_dir = Path(args.actor) / BONES_DIR
    bones = trimesh.util.concatenate([trimesh.load(p, process=False) for p in sorted(bone_dir.glob("*.ply"))])
    samples, _ = trimesh.sample.sample_surface_even(bones, 400_000, seed=0)
    tree = cKDTree(samples)
    template = trimesh.load(Path(args.actor) / "template.ply", process=False)
    faces = np.asarray(template.faces)
    _, held_out = sample_actor_split(SAMPLE_JSON)
    ident = load_ict_identity(Path(args.ict))
    mouth = region_masks(ident)["mouth"]
    rest_all = ident.neutral
    area0 = one_ring_area(rest_all, faces)

    def rms(a) -> float:
        return float(np.sqrt(np.mean(np.square(np.concatenate(a) if isinstance(a, list) else a))))

    keys = ("motion", "normal", "thickness_change", "depth_no_motion", "depth_thickness_rule",
            "thickness_volume_rule", "thickness_sqrt_volume_rule")
    res = {"actor": str(args.actor), "every": args.every, "weights": {}}
    for w in (1.0, 0.5):
        pooled = {k: [] for k in keys}
        rows = {}
        print(f"\nweight {w}: RMS mm over the mouth's moving vertices   |motion|  along normal  thickness change"
              f"  | depth: no motion  thickness rule | thickness: volume rule  sqrt")
        for name in held_out:
            if name in EXCLUDED or name not in ident.deltas:
                continue
            moved_all = rest_all + w * ident.deltas[name]
            idx = np.flatnonzero(mouth & (np.linalg.norm(ident.deltas[name], axis=1) * w > 1.0))[::args.every]
            if len(idx) == 0:
                continue
            rest, moved = rest_all[idx], moved_all[idx]
            d0, i0 = tree.query(rest)
            d1 = tree.query(moved)[0]
            normal = (rest - samples[i0]) / d0[:, None]
            stretch = area0[idx] / one_ring_area(moved_all, faces)[idx]
            e = {"motion": np.linalg.norm(moved - rest, axis=1),
                 "normal": np.einsum("ij,ij->i", normal, moved - rest),
                 "thickness_change": d1 - d0,
                 "depth_no_motion": moved[:, 2] - rest[:, 2],
                 "depth_thickness_rule": moved[:, 2] - thickness_depth(tree, rest, moved, d0),
                 "thickness_volume_rule": d1 - d0 * stretch,
                 "thickness_sqrt_volume_rule": d1 - d0 * np.sqrt(stretch)}
            rows[name] = {"vertices": int(len(idx)), **{k: rms(v) for k, v in e.items()}}
            for k in keys:
                pooled[k].append(e[k])
            r = rows[name]
            print(f"  {name:18s} {len(idx):5d} {r['motion']:7.2f} {r['normal']:10.2f} {r['thickness_change']:12.2f}"
                  f"   | {r['depth_no_motion']:10.2f} {r['depth_thickness_rule']:10.2f}"
                  f"   | {r['thickness_volume_rule']:10.2f} {r['thickness_sqrt_volume_rule']:6.2f}")
        res["weights"][str(w)] = {"expressions": rows, "pooled": {k: rms(v) for k, v in pooled.items()}}
        p = res["weights"][str(w)]["pooled"]
        print(f"  pooled: motion {p['motion']:.2f}, along normal {p['normal']:.2f}, thickness change "
              f"{p['thickness_change']:.2f}; depth error with no motion {p['depth_no_motion']:.2f}, with the "
              f"thickness rule {p['depth_thickness_rule']:.2f}; thickness error with no change "
              f"{p['thickness_change']:.2f}, volume rule {p['thickness_volume_rule']:.2f}, sqrt "
              f"{p['thickness_sqrt_volume_rule']:.2f}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, json.dumps(res, indent=1))
    print(f"numbers: {out}")
    return res


if __name__ == "__main__":
    main()
