"""How the lens-model choice of `capture calibrate` trades wins against losses, rule by rule.

For every case of benchmarks/bench_calib.py (rendered ChArUco footage with a known lens) this detects
and selects views as `capture calibrate` does, then solves every candidate lens model on the same
views and records its whole-image model error against the true lens, its hold-out check and its
covariance evidence (calib.calibrate.model_evidence). It then replays calib.calibrate.choose_model
with several thresholds (``simpler_sigma_ratio``, ``simpler_agreement``) on the same evidence, and
prints, per rule, how many runs came out more than 0.5 px worse than OpenCV's default model on the
same views (= plain `cv2.calibrateCamera`), how many better, and the sum of the gains.

The thresholds in calib.calibrate.CalibrationOptions were chosen on seeds 10-19 with this script, on OpenCV's own
corners (before stop 55); benchmarks/bench_calib.py reports seeds 0-5. With the corners at the saddle of the
intensity (calib.subpix) the same seeds determine OpenCV's default model well enough that no rule up to 2.5 / 1 takes
a simpler one (BENCHMARKS.md).

    python benchmarks/bench_calib_models.py --first-seed 10 --seeds 10   # the tuning seeds (240 runs)
    python benchmarks/bench_calib_models.py --quick                      # 2 cases
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_calib import (
    LENSES,
    RESULTS,
    SIZE,
    SPEC,
    Case,
    K,
    cases,
    model_error,
    render_case,
)
from calib.calibrate import (
    CalibrationOptions,
    calibrate_views,
    choose_model,
    model_evidence,
)
from calib.camera import Camera
from calib.detect import BoardDetector
from calib.frames import open_footage
from calib.holdout import holdout_check
from calib.models import OPENCV_DEFAULT, model_by_name
from calib.pipeline import CalibrateSettings, _check_settings, _detect_all
from calib.solve import solve
from calib.views import select_views
from capture.io.atomic import write_text
from tests.calib_synth import Renderer

#: (simpler_sigma_ratio, simpler_agreement); inf ratio = always OpenCV's default among simpler models
RULES = ((float("inf"), 0.0), (3.5, 0.5), (3.5, 1.0), (3.0, 0.5), (3.0, 1.0), (3.0, 1.5), (2.5, 1.0), (2.0, 1.5))


def evidence_of_case(case: Case, renderer: Renderer) -> dict | None:
    """Per-model error, hold-out and evidence on the views `capture calibrate` would use."""
    options = CalibrationOptions()
    with tempfile.TemporaryDirectory() as tmp:
        inp, _images, truth = render_case(case, Path(tmp), renderer)
        settings = CalibrateSettings(input=inp, board=SPEC, out=Path(tmp) / "cam.json", progress=False)
        board = _check_settings(settings)
        footage = open_footage(inp)
        candidates, _dropped, _n, _ = _detect_all(footage, BoardDetector(board, settings.min_corners), board, settings)
        chosen, _ = select_views(candidates, footage.image_size, settings.max_views, settings.max_blur,
                                 settings.duplicate_px)
    if len(chosen) < options.min_views:
        return None
    obj = [c.detection.object_points for c in chosen]
    img = [c.detection.image_points for c in chosen]
    first = calibrate_views(obj, img, [c.label for c in chosen], SIZE, options)  # outlier views out
    obj = [np.ascontiguousarray(o, np.float32) for o in first.object_points]
    img = [np.ascontiguousarray(p, np.float32) for p in first.image_points]
    models = [model_by_name(n) for n in first.model_scores]
    solves = {m.name: solve(obj, img, SIZE, m, options) for m in models}
    cams = {n: Camera(s.K, s.dist, SIZE) for n, s in solves.items()}
    checks = {m.name: holdout_check(obj, img, SIZE, m, options, cams[m.name]) for m in models}
    evidence = model_evidence(models, solves, obj, img, SIZE, OPENCV_DEFAULT, options)
    return {"models": models, "checks": checks, "evidence": evidence,
            "error": {n: model_error(truth, c)[0] for n, c in cams.items()}}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two cases, to check the script runs")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=10)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    todo = ([Case(18, 8, "blur", "strong"), Case(0, 6, "h264", "strong")] if args.quick
            else cases(False, args.seeds, first_seed=args.first_seed))
    renderers = {lens: Renderer(SPEC, K, d, SIZE) for lens, d in LENSES.items()}
    runs = []
    for case in todo:
        t0 = time.perf_counter()
        ev = evidence_of_case(case, renderers[case.lens])
        if ev is None:
            print(f"{case}: too few views, refused", flush=True)
            continue
        picks = {}
        for ratio, agreement in RULES:
            opts = replace(CalibrationOptions(), simpler_sigma_ratio=ratio, simpler_agreement=agreement)
            picks[f"{ratio:g}/{agreement:g}"] = choose_model(ev["models"], ev["checks"], OPENCV_DEFAULT, opts,
                                                             ev["evidence"]).name
        base = ev["error"][OPENCV_DEFAULT.name]
        runs.append({"case": case.__dict__, "error_px": ev["error"], "default_px": base, "picks": picks,
                     "sigma_max_px": {n: e.sigma_max_px for n, e in ev["evidence"].items()},
                     "holdout_rms_px": {n: c.rms_px for n, c in ev["checks"].items()}})
        print(f"{case.lens:6s} {case.condition:5s} {case.views:2d} views seed {case.seed}: default {base:6.2f} px | "
              + " ".join(f"{n} {e:.2f}" for n, e in ev["error"].items())
              + f" | picks {picks} | {time.perf_counter() - t0:.1f} s", flush=True)
    header = ("| simpler_sigma_ratio / simpler_agreement | runs > 0.5 px worse than OpenCV's default | worst | "
              "runs better by > 0.05 px | sum of gains px | runs not on OpenCV's default |")
    table = [header, "|---|---|---|---|---|---|"]
    summary = {}
    for ratio, agreement in RULES:
        key = f"{ratio:g}/{agreement:g}"
        d = np.array([r["error_px"][r["picks"][key]] - r["default_px"] for r in runs])
        summary[key] = {"worse_half_px": int(np.sum(d > 0.5)), "worst_px": float(d.max()),
                        "better": int(np.sum(d < -0.05)), "gain_px": float(-d.sum()),
                        "switched": int(sum(r["picks"][key] != OPENCV_DEFAULT.name for r in runs))}
        s = summary[key]
        table.append(f"| {key} | {s['worse_half_px']} | {s['worst_px']:+.2f} | {s['better']} | {s['gain_px']:.1f} | "
                     f"{s['switched']} |")
    print(f"{len(runs)} runs" + ("" if args.quick else f", seeds {args.first_seed}..{args.first_seed + args.seeds - 1}"))
    print("\n".join(table))
    res = {"runs": runs, "summary": summary, "seeds": [args.first_seed, args.first_seed + args.seeds - 1]}
    if not args.quick:
        args.out.mkdir(parents=True, exist_ok=True)
        write_text(args.out / "calib_models.json", json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
