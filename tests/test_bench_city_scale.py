"""bench_city_scale's log-log fit and figure (issue 23 item 6) from rows like its JSON output."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def _rows(slope: float) -> list[dict]:
    return [{"side_km": side, "mission_km": m, "cells": int((side * 500) ** 2),
             "multires_s": 2e-7 * (side * 500) ** (2 * slope) * (1 + 0.01 * m),
             "multires_cpu_s": 1e-7 * (side * 500) ** (2 * slope), "full_s": 1.0, "full_cpu_s": 1.0, "full_f": 1.0}
            for side, m in ((2, 1.0), (6, 1.0), (6, 5.0), (12, 5.0))]


def test_loglog_slope_is_the_least_squares_slope():
    from bench_city_scale import loglog_slope

    assert loglog_slope(_rows(1.25), "multires_cpu_s") == pytest.approx(1.25, abs=1e-9)
    assert loglog_slope(_rows(0.5), "full_s") == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(loglog_slope(_rows(1.0)[1:3], "multires_s"))    # one cell count: no slope


def test_figure_is_a_png(tmp_path):
    from bench_city_scale import figure

    for clock in ("cpu", "wall"):
        out = tmp_path / f"city_{clock}.png"
        figure(_rows(1.1), out, clock)
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000
