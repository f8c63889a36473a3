"""Per-shape training error of an existing actor, as a bar chart (no training: reads ``actor.json``).

    python benchmarks/plot_actor.py [--actor capture/data/demo_actor] [--out benchmarks/results]

Writes ``actor_per_shape.png``: mean and max vertex error (mm) of each training shape, as recorded
by ``capture actor train`` in the actor's ``quality.per_shape``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import sys  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages
from benchmarks.takes import DEFAULT_ACTOR, REPO, save_png


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--actor", default=str(DEFAULT_ACTOR))
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"))
    args = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta = json.loads((Path(args.actor) / "actor.json").read_text(encoding="utf-8"))
    q = meta["quality"]
    names = list(q["per_shape"])
    mean = np.array([q["per_shape"][n]["mean_mm"] for n in names])
    mx = np.array([q["per_shape"][n]["max_mm"] for n in names])
    fig, ax = plt.subplots(figsize=(10, 3.8))
    x = np.arange(len(names))
    ax.bar(x, mean, color="C0", label="mean")
    ax.set_ylabel("mean vertex error (mm)")
    ax2 = ax.twinx()
    ax2.plot(x, mx, "o", color="C3", label="max")
    ax2.set_ylabel("max vertex error (mm)", color="C3")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    it = meta.get("training", {}).get("iterations")
    ax.set_title(f"{meta['name']}: training error per shape (mean {q['mean_mm']:.3f} mm, max {q['max_mm']:.1f} mm; "
                 f"{it} iterations)", fontsize=10)
    fig.tight_layout()
    p = save_png(fig, Path(args.out) / "actor_per_shape.png")
    plt.close(fig)
    for n, a, b in zip(names, mean, mx):
        print(f"{n:18s} mean {a:.3f} mm  max {b:.2f} mm")
    print(f"figure: {p}")
    return p


if __name__ == "__main__":
    main()
