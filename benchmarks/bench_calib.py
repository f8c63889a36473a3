"""`capture calibrate` against plain OpenCV on rendered board footage with a known lens.

Every case renders a ChArUco board (tests/calib_synth.py: exact distorted rendering through a known
camera, supersampled, blurred, noisy) and runs both

- **ours**: `capture calibrate` (calib.pipeline.run_calibrate) with its defaults, and
- **plain**: `cv2.aruco.CharucoDetector.detectBoard` on every image/frame, every view with >= 6
  non-collinear corners, `cv2.calibrateCamera` with default flags (k1, k2, p1, p2, k3)

on the same images, and measures each camera's **whole-image model error** against the true lens:
for a pixel grid (4 px step, edges included) the ray the true camera sees there is projected with
the estimated camera; max and mean of the pixel distance (calib.uncertainty.projection_difference).
Each is given twice: in the camera's fixed frame, and up to the camera's rotation (``..._aligned_px``:
the rays first turned by the rotation that best aligns the two cameras over the image, as mrcal
compares lens models; calib.uncertainty explains why a take cannot see that rotation).

Cases: seeds x views (6, 8, 12, 20) x condition (clean: sigma 0.5 blur + noise 2; blur: sigma 1.8 +
noise 3; h264: a video, 3 frames per view (the view, a near-duplicate, a motion-blurred frame on the
way to the next view), libx264 yuv420p crf 23) x lens (weak, strong distortion).

    python benchmarks/bench_calib.py            # seeds 0-2 x 4 x 3 x 2 = 72 cases, 640x480, 4x4 samples a pixel
    python benchmarks/bench_calib.py --supersample 2   # the same with the 2x2 of the tables before 2026-12-05
    python benchmarks/bench_calib.py --first-seed 10 --seeds 10 --out /tmp/tune   # the seeds the lens
                                                # model choice was tuned on (calib.calibrate.choose_model)
    python benchmarks/bench_calib.py --quick    # 1 case (a 6-view H.264 video)
    python benchmarks/bench_calib.py --issue    # the issue's 1920x1080 case (9x6 board, 20 views, video)
    python benchmarks/bench_calib.py --poses corners   # views that take the whole board into the image's corners
    python benchmarks/bench_calib.py --hd --seeds 3    # 1920x1080, the issue's board, its lens and a wide one
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.board import parse_board  # noqa: E402
from calib.camera import Camera  # noqa: E402
from calib.camera_io import camera_problem, read_camera  # noqa: E402
from calib.pipeline import CalibrateSettings, run_calibrate  # noqa: E402
from calib.uncertainty import pixel_grid, projection_difference  # noqa: E402
from capture.io.atomic import write_text  # noqa: E402
from capture.io.errors import CaptureError  # noqa: E402
from tests.calib_synth import Renderer, corner_poses, operator_poses, write_images  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
SPEC = "charuco:cols=9,rows=7,square=30,marker=22,dict=DICT_5X5_100"
ISSUE_SPEC = "charuco:cols=9,rows=6,square=30,marker=22,dict=DICT_5X5_100"
SIZE = (640, 480)
K = np.array([[600.0, 0.0, 322.3], [0.0, 604.0, 236.8], [0.0, 0.0, 1.0]])
LENSES = {
    "weak": np.array([-0.06, 0.02, 0.0003, -0.0002, 0.0]),
    "strong": np.array([-0.32, 0.14, 0.0008, -0.0006, -0.03]),
}
CONDITIONS = {"clean": dict(blur_sigma=0.5, noise_sigma=2.0), "blur": dict(blur_sigma=1.8, noise_sigma=3.0),
              "h264": dict(blur_sigma=0.6, noise_sigma=2.0)}


VIEWS = (6, 8, 12, 20)
#: ``--hd``: the issue's 1920x1080 camera and board, with the issue's lens and a wide one (about 140 px at the corners)
HD_K = np.array([[1500.0, 0.0, 964.0], [0.0, 1500.0, 538.0], [0.0, 0.0, 1.0]])
HD_SIZE = (1920, 1080)
HD_LENSES = {"issue": np.array([-0.20, 0.08, 0.0, 0.0, 0.0]), "wide": np.array([-0.35, 0.16, 0.0006, -0.0004, -0.04])}
#: Samples per pixel side of the renders. With 2 (the tables before 2026-12-05) the renders' own edge aliasing adds
#: corner error: CharucoDetector's corners on clean views 0.068-0.117 px RMS from the truth against 0.060-0.107 with 4
#: (BENCHMARKS.md); blurred views are the same with either.
SUPERSAMPLE = 4


@dataclass(frozen=True)
class Case:
    seed: int
    views: int
    condition: str
    lens: str
    poses: str = "operator"   # tests.calib_synth's operator_poses, or corner_poses ("corners")


def write_h264(path: Path, frames: list[np.ndarray], fps: float = 10.0, crf: int = 23) -> Path:
    """Grayscale frames to an H.264 (libx264, yuv420p) MP4 through PyAV, as a phone or camera would."""
    import av

    h, w = frames[0].shape
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        stream.options = {"crf": str(crf), "preset": "fast"}
        for f in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(cv2.cvtColor(f, cv2.COLOR_GRAY2RGB), "rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def _between(a, b, t: float):
    from tests.calib_synth import Pose

    return Pose((1 - t) * np.asarray(a.rvec) + t * np.asarray(b.rvec), (1 - t) * np.asarray(a.tvec) + t * np.asarray(b.tvec))


def render_case(case: Case, folder: Path, renderer: Renderer | None = None, spec: str = SPEC,
                K_true: np.ndarray = K, size=SIZE) -> tuple[Path, list[np.ndarray], Camera]:
    """Render one case into ``folder``; returns (input path for capture calibrate, the images, truth)."""
    dist = LENSES[case.lens]
    renderer = renderer or Renderer(spec, K_true, dist, size)
    poses = (corner_poses(renderer.board, K_true, size, case.views, seed=case.seed, dist=dist)
             if case.poses == "corners" else operator_poses(renderer.board, K_true, size, case.views, seed=case.seed))
    rng = np.random.default_rng(100 + case.seed)
    look = CONDITIONS[case.condition]
    truth = Camera(K_true, dist, size)
    if case.condition != "h264":
        images = [renderer.render(p, rng=rng, **look) for p in poses]
        write_images(folder / "views", images)
        return folder / "views", images, truth
    frames = []
    for k, p in enumerate(poses):
        frames.append(renderer.render(p, rng=rng, **look))
        frames.append(renderer.render(_between(p, poses[(k + 1) % len(poses)], 0.01), rng=rng, **look))
        frames.append(renderer.render(_between(p, poses[(k + 1) % len(poses)], 0.5), rng=rng,
                                      motion_blur_px=6.0, **look))
    video = write_h264(folder / "take.mp4", frames)
    cap = cv2.VideoCapture(str(video))
    decoded = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        decoded.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
    cap.release()
    return video, decoded, truth


def plain_opencv(images: list[np.ndarray], spec: str, size) -> tuple[Camera | None, int]:
    """The baseline: CharucoDetector on every image, calibrateCamera (default flags) on every usable view."""
    board = parse_board(spec)
    cv_board = cv2.aruco.CharucoBoard((board.cols, board.rows), board.square_mm, board.marker_mm,
                                      cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)))
    detector = cv2.aruco.CharucoDetector(cv_board)
    obj, img = [], []
    for gray in images:
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < 6 or cv_board.checkCharucoCornersCollinear(ids):
            continue
        o, i = cv_board.matchImagePoints(corners, ids)
        obj.append(o)
        img.append(i)
    if len(obj) < 3:
        return None, len(obj)
    rms, Kp, dp, _r, _t = cv2.calibrateCamera(obj, img, size, None, None)
    return Camera(Kp, dp.reshape(-1)[:5], size, float(rms)), len(obj)


def model_error(truth: Camera, est: Camera | None, step: float = 4.0, align: bool = False) -> tuple[float, float]:
    """(max, mean) px over the whole image (module docstring); inf if there is no camera. With ``align``, up to
    the rotation of the camera frame that best aligns the two cameras over the image (module docstring)."""
    if est is None:
        return float("inf"), float("inf")
    grid, _ = pixel_grid(truth.image_size, step)
    d = projection_difference(truth, est, grid, align=align)
    return float(d.max()), float(d.mean())


def run_case(case: Case, renderer: Renderer | None = None, spec: str = SPEC, K_true=K, size=SIZE) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        inp, images, truth = render_case(case, folder, renderer, spec, K_true, size)
        t1 = time.perf_counter()
        plain, plain_views = plain_opencv(images, spec, size)
        t2 = time.perf_counter()
        try:
            out = run_calibrate(CalibrateSettings(input=inp, board=spec, out=folder / "cam.json", progress=False))
            ours = read_camera(out.camera)
            report = json.loads(out.report.read_text())
        except CaptureError as exc:  # a refusal is recorded, not hidden
            ours, report = None, {"num_views": 0, "model": "refused", "dropped": [], "warnings": [str(exc)],
                                  "uncertainty": {"max_px": float("inf")}, "holdout": {"spread_max_px": float("inf")}}
        t3 = time.perf_counter()
    ours_max, ours_mean = model_error(truth, ours)
    plain_max, plain_mean = model_error(truth, plain)
    ours_max_al, ours_mean_al = model_error(truth, ours, align=True)
    plain_max_al, plain_mean_al = model_error(truth, plain, align=True)
    return {
        "seed": case.seed, "views": case.views, "condition": case.condition, "lens": case.lens, "poses": case.poses,
        "ours_max_px": ours_max, "ours_mean_px": ours_mean, "plain_max_px": plain_max, "plain_mean_px": plain_mean,
        "ours_max_aligned_px": ours_max_al, "ours_mean_aligned_px": ours_mean_al,
        "plain_max_aligned_px": plain_max_al, "plain_mean_aligned_px": plain_mean_al,
        "ours_views": report["num_views"], "plain_views": plain_views, "model": report["model"],
        # plain OpenCV returns whatever its solve gives; `capture run` refuses a camera that is no real lens
        "plain_not_a_lens": (camera_problem(plain) or (None,))[0] if plain is not None else None,
        "ours_not_a_lens": report.get("model_not_a_lens", {}),
        "dropped": [d["reason"] for d in report["dropped"]], "warnings": report["warnings"],
        "uncertainty_max_px": report["uncertainty"]["max_px"], "spread_max_px": report["holdout"]["spread_max_px"],
        "render_s": t1 - t0, "plain_s": t2 - t1, "ours_s": t3 - t2,
    }


def cases(quick: bool, seeds: int, views=VIEWS, first_seed: int = 0, poses: str = "operator") -> list[Case]:
    if quick:
        return [Case(1, 6, "h264", "weak", poses)]
    return [Case(s, v, c, lens, poses) for lens in LENSES for c in CONDITIONS for v in views
            for s in range(first_seed, first_seed + seeds)]


def _print_row(r: dict) -> None:
    print(f"{r['lens']:6s} {r['condition']:5s} {r['views']:3d} views seed {r['seed']}: ours max {r['ours_max_px']:6.3f} "
          f"mean {r['ours_mean_px']:.3f} px ({r['ours_views']} views, {r['model']}) | plain max "
          f"{r['plain_max_px']:6.3f} mean {r['plain_mean_px']:.3f} px ({r['plain_views']} views) | "
          f"up to rotation: ours max {r['ours_max_aligned_px']:.3f}, plain max {r['plain_max_aligned_px']:.3f} px | "
          f"{len(r['warnings'])} warnings | {r['ours_s']:.1f} s", flush=True)


def summarise(rows: list[dict]) -> dict:
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(f"{r['lens']} {r['condition']} {r['views']}", []).append(r)
    out = {}
    for key, rs in groups.items():
        out[key] = {
            "ours_max_px": max(r["ours_max_px"] for r in rs), "plain_max_px": max(r["plain_max_px"] for r in rs),
            "worst_excess_px": max(r["ours_max_px"] - r["plain_max_px"] for r in rs),
            "ours_mean_px": float(np.mean([r["ours_mean_px"] for r in rs])),
            "plain_mean_px": float(np.mean([r["plain_mean_px"] for r in rs])),
            "ours_views": [r["ours_views"] for r in rs], "plain_views": [r["plain_views"] for r in rs],
            "models": [r["model"] for r in rs], "warned": sum(bool(r["warnings"]) for r in rs), "runs": len(rs),
        }
    return out


def markdown_table(rows: list[dict], aligned: bool = False) -> str:
    """One line per (lens, condition, views): ours vs plain, max over the image, per seed; with ``aligned``,
    the errors up to the camera's rotation (``..._aligned_px``)."""
    m = "_aligned" if aligned else ""
    out = ["| lens | input | views | ours max px (per seed) | plain max px (per seed) | ours - plain, worst | "
           "ours mean px | plain mean px | ours <= 1 px | plain <= 1 px | runs warned | model(s) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[dict]] = {}
    mixed = len({r.get("poses", "operator") for r in rows}) > 1   # both pose sets: one line each
    for r in rows:
        lens = f"{r['lens']}, {r.get('poses', 'operator')} poses" if mixed else r["lens"]
        groups.setdefault((lens, r["condition"], r["views"]), []).append(r)
    for (lens, cond, views), rs in groups.items():
        ours = " / ".join(f"{r[f'ours_max{m}_px']:.2f}" for r in rs)
        plain = " / ".join(f"{r[f'plain_max{m}_px']:.2f}" for r in rs)
        out.append(
            f"| {lens} | {cond} | {views} | {ours} | {plain} | "
            f"{max(r[f'ours_max{m}_px'] - r[f'plain_max{m}_px'] for r in rs):+.2f} | "
            f"{np.mean([r[f'ours_mean{m}_px'] for r in rs]):.2f} | "
            f"{np.mean([r[f'plain_mean{m}_px'] for r in rs]):.2f} | "
            f"{sum(r[f'ours_max{m}_px'] <= 1 for r in rs)}/{len(rs)} | "
            f"{sum(r[f'plain_max{m}_px'] <= 1 for r in rs)}/{len(rs)} | "
            f"{sum(bool(r['warnings']) for r in rs)}/{len(rs)} | {', '.join(sorted(set(r['model'] for r in rs)))} |")
    return "\n".join(out)


def before_after_table(before: list[dict], rows: list[dict]) -> str:
    """``markdown_table`` with an earlier run's results (same cases) beside; bold: > 0.5 px worse than plain."""
    key = lambda r: (r["lens"], r["condition"], r["views"], r["seed"])  # noqa: E731
    old = {key(r): r for r in before}
    out = ["| lens | input | views | plain max px (per seed) | before: ours max px | now: ours max px | "
           "now - plain, worst | now mean px | plain mean px | now <= 1 px | runs warned | model(s) now |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["lens"], r["condition"], r["views"]), []).append(r)

    def cell(v: float, plain: float) -> str:
        return f"**{v:.2f}**" if v - plain > 0.5 else f"{v:.2f}"

    for (lens, cond, views), rs in groups.items():
        prev = " / ".join(cell(old[key(r)]["ours_max_px"], r["plain_max_px"]) if key(r) in old else "-" for r in rs)
        plain = " / ".join(f"{r['plain_max_px']:.2f}" for r in rs)
        out.append(
            f"| {lens} | {cond} | {views} | {plain} | {prev} | "
            f"{' / '.join(cell(r['ours_max_px'], r['plain_max_px']) for r in rs)} | "
            f"{max(r['ours_max_px'] - r['plain_max_px'] for r in rs):+.2f} | "
            f"{np.mean([r['ours_mean_px'] for r in rs]):.2f} | {np.mean([r['plain_mean_px'] for r in rs]):.2f} | "
            f"{sum(r['ours_max_px'] <= 1 for r in rs)}/{len(rs)} | {sum(bool(r['warnings']) for r in rs)}/{len(rs)} | "
            f"{', '.join(sorted(set(r['model'] for r in rs)))} |")
    return "\n".join(out)


def headline(rows: list[dict]) -> dict:
    """The sweep's figures against plain OpenCV. A run ``capture calibrate`` refused (too few usable views; no
    lens model that is a lens) is counted apart, beside what plain OpenCV made of the same footage."""
    made = [r for r in rows if r["model"] != "refused"]
    excess = np.array([r["ours_max_px"] - r["plain_max_px"] for r in made])
    excess_al = np.array([r["ours_max_aligned_px"] - r["plain_max_aligned_px"] for r in made])
    return {
        "worst_excess_px": float(excess.max(initial=-np.inf)),
        "worst_ours_max_px": max((r["ours_max_px"] for r in made), default=float("nan")),
        "runs_over_half_px_worse": int(np.sum(excess > 0.5)),
        "runs_better_same_worse": [int(np.sum(excess < -0.05)), int(np.sum(np.abs(excess) <= 0.05)),
                                   int(np.sum(excess > 0.05))],
        "aligned": {"worst_excess_px": float(excess_al.max(initial=-np.inf)),
                    "runs_over_half_px_worse": int(np.sum(excess_al > 0.5)),
                    "ours_within_1px": int(sum(r["ours_max_aligned_px"] <= 1 for r in rows)),
                    "plain_within_1px": int(sum(r["plain_max_aligned_px"] <= 1 for r in rows))},
        "refused": [{"case": f"{r['lens']} {r['condition']} {r['views']} views seed {r['seed']}",
                     "reason": r["warnings"][0], "plain_views": r["plain_views"],
                     "plain_max_aligned_px": r["plain_max_aligned_px"]} for r in rows if r["model"] == "refused"],
        "plain_not_a_lens": int(sum(bool(r.get("plain_not_a_lens")) for r in rows)),
        "opencv_default_set_aside": int(sum("k1-k3+p" in r.get("ours_not_a_lens", {}) for r in rows)),
    }


def print_headline(res: dict, runs: int) -> None:
    made = runs - len(res["refused"])
    print(f"worst: ours max {res['worst_ours_max_px']:.3f} px; ours - plain at most {res['worst_excess_px']:+.3f} px; "
          f"{res['runs_over_half_px_worse']} of {made} runs > 0.5 px worse than plain; better / equal / worse "
          f"(0.05 px): {' / '.join(map(str, res['runs_better_same_worse']))}")
    al = res["aligned"]
    print(f"up to rotation: ours <= 1 px in {al['ours_within_1px']} of {runs} runs, plain in "
          f"{al['plain_within_1px']}; ours - plain at most {al['worst_excess_px']:+.3f} px "
          f"({al['runs_over_half_px_worse']} runs > 0.5 px worse)")
    for r in res["refused"]:
        print(f"refused: {r['case']} ({r['reason'].split(';')[0]}); plain OpenCV from {r['plain_views']} views: "
              f"{r['plain_max_aligned_px']:.2f} px")
    print(f"plain OpenCV's camera is no real lens (capture run would refuse it) in {res['plain_not_a_lens']} runs; "
          f"ours set OpenCV's default model aside as no lens in {res['opencv_default_set_aside']}")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one case, to check the script runs")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--issue", action="store_true", help="the issue's 1920x1080, 9x6-board case instead")
    ap.add_argument("--hd", action="store_true",
                    help="1920x1080 with the issue's board: its lens and a wide one, both pose sets, clean and H.264, "
                         "8 and 20 views, --seeds seeds")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--table", type=Path, help="only print the table of a results JSON written before")
    ap.add_argument("--before", type=Path, help="with --table: an earlier results JSON to show beside it")
    ap.add_argument("--aligned", action="store_true", help="with --table: the errors up to the camera's rotation")
    ap.add_argument("--poses", choices=("operator", "corners"), default="operator",
                    help="operator: views through 9 places of the image, the board's corners rarely reach the "
                         "image's (the tables); corners: 4 of 5 views push the whole board into an image corner, "
                         "as calibration guides ask (tests/calib_synth.py)")
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--lenses", default="weak,strong")
    ap.add_argument("--views", default=",".join(map(str, VIEWS)))
    ap.add_argument("--supersample", type=int, default=SUPERSAMPLE,
                    help="render each pixel from N x N samples (2: the tables before 2026-12-05, results/calib.json; "
                         "4 adds less corner error of its own: results/calib_ss4.json)")
    args = ap.parse_args(argv)
    for c in [c for c in CONDITIONS if c not in args.conditions.split(",")]:
        del CONDITIONS[c]
    lenses = args.lenses.split(",")
    VIEWS_SEL = tuple(int(v) for v in args.views.split(","))
    if args.table:
        res = json.loads(args.table.read_text())
        if args.before:
            print(before_after_table(json.loads(args.before.read_text())["rows"], res["rows"]))
        else:
            print(markdown_table(res["rows"], aligned=args.aligned))
            print_headline(headline(res["rows"]), len(res["rows"]))
        return res
    cv2.setNumThreads(1)
    rows = []
    if args.issue or args.hd:
        LENSES.update(HD_LENSES)
        for lens in ("issue",) if args.issue else HD_LENSES:
            # the issue's case as it was reported (no supersampling); --hd with --supersample (4: 0.5 s a frame)
            ss = 1 if args.issue else args.supersample
            renderer = Renderer(ISSUE_SPEC, HD_K, LENSES[lens], HD_SIZE, supersample=ss,
                                px_per_mm=8.0 if ss == 1 else 5.0 * ss)
            hd_cases = [Case(0, 20, cond, lens) for cond in ("clean", "h264")] if args.issue else [
                Case(s, v, c, lens, poses) for poses in ("operator", "corners") for c in ("clean", "h264")
                for v in (8, 20) for s in range(args.first_seed, args.first_seed + args.seeds)]
            for case in hd_cases:
                r = run_case(case, renderer, ISSUE_SPEC, HD_K, HD_SIZE)
                rows.append(r)
                _print_row(r)
    else:
        renderers = {lens: Renderer(SPEC, K, d, SIZE, supersample=args.supersample, px_per_mm=3.0 * args.supersample)
                     for lens, d in LENSES.items()}
        for case in [c for c in cases(args.quick, args.seeds, VIEWS_SEL, args.first_seed, args.poses)
                     if c.lens in lenses]:
            r = run_case(case, renderers[case.lens])
            rows.append(r)
            _print_row(r)
    res = {"rows": rows, "summary": summarise(rows), "supersample": 1 if args.issue else args.supersample,
           **headline(rows)}
    print("whole-image model error in a fixed camera frame:")
    print(markdown_table(rows))
    print("up to the camera's rotation:")
    print(markdown_table(rows, aligned=True))
    print_headline(res, len(rows))
    if not args.quick:
        args.out.mkdir(parents=True, exist_ok=True)
        name = ("calib_issue.json" if args.issue else "calib_hd.json" if args.hd else
                "calib.json" if args.supersample == 2 else
                f"calib_ss{args.supersample}{'_corner_poses' if args.poses == 'corners' else ''}.json")
        write_text(args.out / name, json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
