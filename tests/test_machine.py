"""What a timing was measured on (``capture.io.machine``), read from a cpuinfo like Linux's."""

from __future__ import annotations

import os

from capture.io.machine import machine

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
model name\t: Intel(R) Xeon(R) Platinum 8480+
flags\t\t: fpu sse2 avx2 avx512f avx512_bf16 amx_bf16 amx_tile

processor\t: 1
vendor_id\t: GenuineIntel
model name\t: Intel(R) Xeon(R) Platinum 8480+
flags\t\t: fpu sse2 avx2 avx512f avx512_bf16 amx_bf16 amx_tile
"""


def test_the_model_and_the_flags_that_decide_the_products_speed(tmp_path):
    (tmp_path / "cpuinfo").write_text(CPUINFO)
    m = machine(tmp_path / "cpuinfo")
    assert m == {"cpu": "Intel(R) Xeon(R) Platinum 8480+", "cores": os.cpu_count(),
                 "features": ["avx2", "avx512f", "avx512_bf16", "amx_bf16"]}
    (tmp_path / "plain").write_text("processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx2\n")
    assert machine(tmp_path / "plain")["features"] == ["avx2"]
    assert machine(tmp_path / "missing")["features"] == []   # not Linux: no flags, no error
