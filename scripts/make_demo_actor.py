"""Train the bundled sample actor with the default preset and store it as the demo actor.

    python scripts/make_demo_actor.py [--from ACTOR_DIR]

``capture demo`` must finish in minutes, so it ships a pretrained actor instead of training one
(training takes about 8 minutes on 2 CPU cores with AMX, longer without). This script makes it
the way a user would: ``capture actor train <tmp> --sample`` with the default preset (or takes an
actor trained that way with ``--from``), then copies the package to ``capture/data/demo_actor/``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEST = REPO / "capture" / "data" / "demo_actor"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--from", dest="source", type=Path, default=None,
                    help="an actor already trained with 'capture actor train A --sample' (default preset)")
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    from capture.cli import main as cli

    source = args.source
    if source is None:
        source = Path(tempfile.mkdtemp(prefix="demo_actor_")) / "sample"
        if cli(["actor", "train", str(source), "--sample", "--no-progress"]) != 0:
            sys.exit("training the sample actor failed")
    meta = json.loads((source / "actor.json").read_text())
    if meta["training"]["preset"] != "default" or meta["source"]["bones_estimated"]:
        sys.exit(f"{source} was not trained with the default preset on the bundled sample")
    if DEST.exists():
        shutil.rmtree(DEST)
    shutil.copytree(source, DEST, ignore=shutil.ignore_patterns("training", "training_log.jsonl"))
    meta["name"] = "demo_actor"
    (DEST / "actor.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"demo actor written to {DEST} (mean training error {meta['quality']['mean_mm']:.3f} mm)")


if __name__ == "__main__":
    main()
