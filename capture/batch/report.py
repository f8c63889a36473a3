"""The batch report of ``capture batch``: one row per take, as JSON, CSV and a table on screen.

Written next to the takes' run folders, in the batch output folder, after every finished take (so a
batch stopped overnight still has its report so far) and at the end:

* ``batch_report.json``: the shoot file, how Ray ran it, the totals (takes done / already done /
  failed, frames fitted, frames per second over the whole shoot) and per take its row, attempts and
  run folder (whose ``report.json`` has the per-frame detail);
* ``batch_summary.csv``: the rows (:data:`CSV_FIELDS`), one per take, for a spreadsheet;
* ``batch_report.html``: the same rows as a page linking each take's ``report.html``
  (:func:`capture.export.report_html.shoot_html`).
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Sequence

from capture.io.atomic import write_json, write_text

REPORT_JSON = "batch_report.json"
SUMMARY_CSV = "batch_summary.csv"
REPORT_HTML = "batch_report.html"
#: Take statuses: ran and finished / skipped because done with the same settings / failed / stopped.
STATUSES = ("done", "already done", "failed", "interrupted", "pending")
CSV_FIELDS = ("take", "status", "frames_requested", "frames_fitted", "frames_skipped", "reprojection_mean_px",
              "reprojection_median_px", "reprojection_max_px", "frames_unexplained", "seconds", "cpu_seconds",
              "attempts", "host", "out", "error")


def take_row(name: str, out: Path, result: dict | None, status: str, attempts: int = 0) -> dict:
    """A summary row from a take's result (``process_take`` or the stored result of a done take)."""
    r = result or {}
    return {"take": name, "status": status, "frames_requested": r.get("frames_requested"),
            "frames_fitted": r.get("frames_fitted"), "frames_skipped": r.get("frames_skipped"),
            "reprojection_mean_px": r.get("reprojection_mean_px"),
            "reprojection_median_px": r.get("reprojection_median_px"),
            "reprojection_max_px": r.get("reprojection_max_px"), "frames_unexplained": r.get("frames_unexplained"),
            "seconds": r.get("seconds"),
            "cpu_seconds": r.get("cpu_seconds"),
            "attempts": attempts, "host": r.get("node") or r.get("host"), "out": str(out), "error": r.get("error")}


def totals(rows: Sequence[dict], seconds: float) -> dict:
    """Counts per status, frames fitted in this batch run and its throughput (frames/s of wall time)."""
    ran = [r for r in rows if r["status"] == "done"]
    frames = sum(r["frames_fitted"] or 0 for r in ran)
    out = {s.replace(" ", "_"): sum(r["status"] == s for r in rows) for s in STATUSES}
    out.update({"takes": len(rows), "frames_fitted": frames, "seconds": seconds,
                "frames_per_second": frames / seconds if seconds > 0 and frames else None})
    return out


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}" if math.isfinite(v) else ""
    return str(v)


def summary_csv(rows: Sequence[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _cell(r.get(k)) for k in CSV_FIELDS})
    return buf.getvalue()


def write_batch_report(out_dir: Path, report: dict) -> Path:
    """``batch_report.json`` and ``batch_summary.csv`` in ``out_dir`` (atomically); the JSON's path."""
    out_dir = Path(out_dir)
    write_text(out_dir / SUMMARY_CSV, summary_csv(report["takes"]))
    from capture.export.report_html import shoot_html

    write_text(out_dir / REPORT_HTML, shoot_html(report, out_dir))
    return write_json(out_dir / REPORT_JSON, report)


def _frames(r: dict) -> str:
    if r.get("frames_requested") is None:
        return "-"
    s = f"{r['frames_fitted']}/{r['frames_requested']}"
    return s + (f" ({r['frames_skipped']} skipped)" if r.get("frames_skipped") else "")


def _seconds(v) -> str:
    if v is None:
        return "-"
    m, s = divmod(int(round(v)), 60)
    return f"{m}m{s:02d}s" if m else f"{v:.1f}s"


def print_summary_table(report: dict, console=None) -> None:
    """The end-of-batch table: take, frames, reprojection error, time, status (and why a take failed)."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    t = Table(title=f"capture batch: {report['name']}", title_justify="left")
    for col, just in (("take", "left"), ("frames", "right"), ("reproj. mean px", "right"), ("unexplained", "right"),
                      ("time", "right"), ("status", "left")):
        t.add_column(col, justify=just)
    style = {"done": "green", "already done": "cyan", "failed": "bold red", "interrupted": "yellow"}
    for r in report["takes"]:
        err = r.get("reprojection_mean_px")
        status = r["status"] + (f" ({r['attempts']} attempts)" if (r.get("attempts") or 0) > 1 else "")
        if r.get("error"):
            status += f": {r['error']}"
        unx = r.get("frames_unexplained")
        t.add_row(r["take"], _frames(r), "-" if err is None else f"{err:.2f}", "-" if unx is None else str(unx),
                  _seconds(r.get("seconds")),
                  f"[{style.get(r['status'], '')}]{status}[/]" if r["status"] in style else status)
    console.print(t)
    tot = report["totals"]
    fps = tot.get("frames_per_second")
    console.print(f"{tot['takes']} takes: {tot['done']} done, {tot['already_done']} already done, "
                  f"{tot['failed']} failed" + (f", {tot['interrupted']} interrupted" if tot["interrupted"] else "")
                  + f"; {tot['frames_fitted']} frames fitted in {_seconds(tot['seconds'])}"
                  + (f" ({fps:.2f} frames/s)" if fps else ""))
    console.print(f"report: {Path(report['out']) / REPORT_JSON} and {SUMMARY_CSV}; per take: <out>/report.json, "
                  f"batch_take.log")
