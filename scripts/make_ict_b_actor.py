"""Build the test fixture tests/data/ict_b_actor: a second ICT FaceKit identity ("B") learnt at small settings.

B's shapes are the bundled sample identity's 19 expressions (plus neutral; training adds their 5 mirrored
shapes, as for the demo actor) with the identity difference added: the sample identity's coefficients
negated on the 100 ICT identity modes (``_ict_identity_b`` in benchmarks/bench_retarget.py; ICT is linear,
so every expression is the sample's plus the same offset).
B is trained once with ``capture actor train`` (SIREN width 64, 600 iterations, estimated bones) and the
package is committed, so tests/test_retarget_ict.py needs neither the ICT source data nor training time.

Needs the ICT FaceKit source at /work/shared/assets/ict_facekit/derived/ict_facekit_light.npz.

    python scripts/make_ict_b_actor.py                     # ~4-8 min on 2 shared cores
    python scripts/make_ict_b_actor.py --out DIR --iterations 60   # a quick look
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_retarget import _ict_identity_b  # noqa: E402
from capture.io.atomic import write_json  # noqa: E402
from capture.cli import main as cli  # noqa: E402

LICENCE = ROOT / "capture" / "data" / "sample_actor" / "LICENSES" / "ICT-FaceKit-MIT.txt"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "tests" / "data" / "ict_b_actor", help="package folder")
    ap.add_argument("--width", type=int, default=64, help="SIREN hidden width")
    ap.add_argument("--iterations", type=int, default=600, help="Adam iterations")
    ap.add_argument("--points-per-step", type=int, default=2000, help="template points per step")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        shapes = _ict_identity_b(Path(tmp))
        work = Path(tmp) / "ict_b_actor"
        rc = cli(["actor", "train", str(work), "--shapes", str(shapes), "--width", str(args.width),
                  "--iterations", str(args.iterations), "--points-per-step", str(args.points_per_step),
                  "--no-progress"])
        if rc != 0:
            raise SystemExit(f"capture actor train failed with status {rc}")
        readme = args.out / "README.md"          # the fixture's description is kept across rebuilds
        kept = readme.read_text() if readme.is_file() else None
        if args.out.exists():
            shutil.rmtree(args.out)
        shutil.copytree(work, args.out)
        if kept is not None:
            readme.write_text(kept)
        # The shapes were temporary: record where they came from instead of a dead path.
        meta_path = args.out / "actor.json"
        text = meta_path.read_text().replace(str(Path(tmp) / "ict_b_shapes"), "<scripts/make_ict_b_actor.py>")
        write_json(meta_path, json.loads(text))
    (args.out / "LICENSES").mkdir(exist_ok=True)
    shutil.copy(LICENCE, args.out / "LICENSES" / LICENCE.name)
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(f"wrote {args.out} ({size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
