"""Bounded resources (issue 27): estimate what a request needs before any work and refuse,
with the number and the setting to change, what cannot fit the machine.

The estimate is deliberately simple and on the safe side; it counts

* a fixed :data:`BASE_BYTES` (Python, numpy, dask, numba, GDAL loaded and the vector data read);
* **cells** ``nx * ny`` of the scenario grid (``aoi.bounds`` / ``aoi.resolution_m``): every
  stage keeps a few dozen 2-D layers (surface, terrain, risk, landing, clearance, costs, the
  planner's lattice), :data:`BYTES_PER_CELL` in all; a request without the plan stage (``maps``,
  ``coverage``) :data:`BYTES_PER_CELL_MAPS` per cell and no per-level planner arrays.  On a
  city-scale AOI the plan stage reads only its planning window
  (:mod:`skyroute.stages.planning.window`): the planner's bytes count the window's cells, the
  map stages' the AOI's (the larger of the two).  Measured: the peak resident memory of a
  cold ``skyroute plan helsinki-medical`` is 639 MB at 2 m (460 598 cells) and 1 115 MB at 1 m
  (1 842 392 cells): 344 B per cell over 480 MB; the constants round both up;
* **levels**: the DOP thresholds D_j (``gnss.dop_thresholds``), each one coverage floor and one
  planned candidate: :data:`BYTES_PER_CELL_LEVEL` per cell and level;
* **epochs**: ``gnss.window_min / gnss.step_min + 1`` GNSS epochs, each one row of satellite
  geometry per satellite (:data:`BYTES_PER_EPOCH_SAT`) and, in the coverage stage, one dask task
  per (block, epoch) (:data:`BYTES_PER_TASK`);
* **ticks** of ``skyroute fly``: the flight's duration / ``--tick``, :data:`BYTES_PER_TICK` each;
* **missions** of ``skyroute fleet``: :data:`BYTES_PER_MISSION` each (its accepted attempt: the
  trajectory sampled every 0.05 s, the intent volumes and the F3548 document, its rows of the
  outputs) up to :data:`MISSION_KM` long, in proportion beyond, over the maps' footprint
  (:func:`check_fleet`);
* **run-epochs** of ``skyroute navsim``: runs x epochs of the flight at ``navsim.rate_hz``,
  :data:`BYTES_PER_RUN_EPOCH` each, over the plan's footprint (:func:`check_navsim`).

The limit is ``--max-memory`` (e.g. ``8G``), else ``$SKYROUTE_MAX_MEMORY``, else
:data:`DEFAULT_FRACTION` of the machine's memory (the cgroup limit when lower).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from skyroute.pipeline.errors import InputError

BASE_BYTES = 512 << 20        # measured 480 MB (see the module docstring)
BYTES_PER_CELL = 350           # measured 344 B per cell with 3 DOP levels
#: Map stages only (no plan: ``skyroute maps`` / ``coverage``; their layers are chunked or one
#: stage's numpy arrays at a time): the 20 km mosaic city (1e8 cells, issue 23) peaked at 5.9 GB in
#: its environment stage (59 B per cell), 5.1 GB in its surface stage, 2.4 GB in coverage.
BYTES_PER_CELL_MAPS = 64
#: A plan in a planning window of a city-scale AOI (its maps cached, read window by window): the
#: 20 km mosaic city's 15 km mission peaked at 7.4 GB for 46.3 M window cells and 3 levels
#: (160 B per cell); with BYTES_PER_CELL_LEVEL per level the estimate is 196 B per cell there.
BYTES_PER_WINDOW_CELL = 100
BYTES_PER_CELL_LEVEL = 32      # a float32 floor, a bool mask and the planner's per-level float64 costs
BYTES_PER_EPOCH_SAT = 96       # ECEF x, y, z, az, el, visible, ... per satellite and epoch
BYTES_PER_TASK = 4096          # one dask task of the coverage graph (block x epoch)
BYTES_PER_TICK = 512           # one sample of the flight log and its timeline (positions, checks, costs)
SATS_PER_ALMANAC = 40          # GPS 32, Galileo 36, GLONASS 24, BeiDou up to 60
#: One fleet mission up to MISSION_KM long: its attempt's trajectory (0.05 s samples, 32 B each:
#: 100 KB for 1.5 km at 10 m/s), intent volumes (shapely outlines, obstacles) and F3548 document
#: (~100 KB), the STEP II chain and the output rows, rounded up.
BYTES_PER_MISSION = 512 << 10
MISSION_KM = 1.5
#: navsim: measured (tracemalloc, 400 runs x 600 epochs, 24 satellites) 93 B per run and epoch in
#: simulate(), 147 B in its summary, 266 B writing navsim.csv and the figures.
BYTES_PER_RUN_EPOCH = 320
MAX_NAVSIM_RUNS = 100_000      # navsim.runs / --runs (the schema's bound)
DEFAULT_FRACTION = 0.8
ENV = "SKYROUTE_MAX_MEMORY"

_limit_bytes: int | None = None   # set by the CLI's --max-memory for one command


def _gib(n: float) -> str:
    if not math.isfinite(n):
        return "an unbounded amount"
    if n >= 1 << 40:
        return f"{n / (1 << 40):,.1f} TiB"
    if n >= 1 << 30:
        return f"{n / (1 << 30):,.1f} GiB"
    if n >= 1 << 20:
        return f"{n / (1 << 20):,.0f} MiB"
    return f"{n / (1 << 10):,.0f} KiB" if n >= 1 << 10 else f"{n:,.0f} B"   # --max-memory 1: not "0 MiB"


def machine_memory_bytes() -> int:
    """Physical memory [bytes], or the cgroup (container) limit when lower."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 8 << 30
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = open(path).read().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            total = int(text)
    return int(total)


def set_max_memory(limit_bytes: int | None) -> None:
    """The limit of this process's commands (``--max-memory``); None: the default."""
    global _limit_bytes
    if limit_bytes is not None and limit_bytes <= 0:
        raise InputError(f"--max-memory {limit_bytes} bytes must be > 0 (e.g. 8G)")
    _limit_bytes = limit_bytes


def max_memory_bytes() -> int:
    """``--max-memory``, else ``$SKYROUTE_MAX_MEMORY`` (e.g. ``8G``), else 80 % of the machine."""
    if _limit_bytes is not None:
        return _limit_bytes
    env = os.environ.get(ENV, "").strip()
    if env:

        try:
            return parse_size(env)
        except InputError:
            raise InputError(f"${ENV}={env!r} is not a size: give e.g. 8G or 500M") from None
    return int(machine_memory_bytes() * DEFAULT_FRACTION)


@dataclass(frozen=True)
class Footprint:
    """What a scenario implies: counts and the estimated peak memory [bytes] (floats: a hostile
    scenario may give counts beyond any integer type)."""

    cells: float
    levels: int
    epochs: float
    satellites: int
    bytes_cells: float
    bytes_levels: float
    bytes_epochs: float

    @property
    def bytes(self) -> float:
        return BASE_BYTES + self.bytes_cells + self.bytes_levels + self.bytes_epochs


def _cells(sc) -> float:
    a = sc.aoi
    try:
        g = sc.grid
        return float(g.nx) * float(g.ny)
    except (OverflowError, ValueError, MemoryError, ZeroDivisionError):
        if a.bounds is not None:
            w = (a.bounds[2] - a.bounds[0]) / a.resolution_m
            h = (a.bounds[3] - a.bounds[1]) / a.resolution_m
            return w * h
        return math.inf


def _plan_cells(sc, cells: float) -> float:
    """The cells the plan stage reads: its planning window's on a city-scale AOI
    (:func:`skyroute.stages.planning.window.plan_cells`), else every cell."""
    from skyroute.stages.planning.window import WINDOW_MIN_CELLS, plan_cells

    if not (math.isfinite(cells) and cells >= WINDOW_MIN_CELLS):
        return cells
    try:
        return float(plan_cells(sc.grid, sc.point_xy(sc.mission.start), sc.point_xy(sc.mission.goal)))
    except Exception:  # noqa: BLE001 -- an unusable mission is reported by the scenario checks, not here
        return cells


def scenario_footprint(sc, maps_only: bool = False) -> Footprint:
    """The counts and the memory estimate of ``sc`` (see the module docstring); ``maps_only``: a
    request that does not plan."""
    cells = _cells(sc)
    g = sc.gnss
    ratio = g.window_min / g.step_min
    epochs = (math.floor(ratio) + 1.0 if math.isfinite(ratio) else math.inf) if sc.data.almanacs else 0.0
    sats = SATS_PER_ALMANAC * max(1, len(sc.data.almanacs)) if sc.data.almanacs else 0
    levels = len(g.dop_thresholds)
    chunk = float(sc.aoi.chunk_cells) ** 2
    blocks = max(1.0, math.ceil(cells / chunk)) if math.isfinite(cells) else math.inf
    pcells = cells if maps_only else _plan_cells(sc, cells)
    per_plan_cell = BYTES_PER_WINDOW_CELL if pcells < cells else BYTES_PER_CELL
    return Footprint(
        cells=cells, levels=levels, epochs=epochs, satellites=sats,
        bytes_cells=(cells * BYTES_PER_CELL_MAPS if maps_only
                     else max(cells * BYTES_PER_CELL_MAPS, pcells * per_plan_cell)),
        bytes_levels=0.0 if maps_only else pcells * levels * BYTES_PER_CELL_LEVEL,
        bytes_epochs=epochs * (sats * BYTES_PER_EPOCH_SAT + min(blocks, 8.0) * BYTES_PER_TASK),
    )


def check_scenario(sc, limit_bytes: int | None = None, maps_only: bool = False) -> Footprint:
    """InputError (exit 2) naming the number and the key to change when ``sc`` needs more than
    the limit; else the footprint (``maps_only``: a request without the plan stage).  Cheap:
    nothing is allocated."""
    limit = max_memory_bytes() if limit_bytes is None else limit_bytes
    fp = scenario_footprint(sc, maps_only)
    if fp.bytes <= limit:
        return fp
    fix = f"or raise --max-memory (now {_gib(limit)})"
    if limit <= BASE_BYTES:     # no resolution, bounds or window could fit: say so, not "to inf m"
        raise InputError(
            f"scenario {sc.name!r} needs about {_gib(fp.bytes)} of memory ({fp.cells:,.0f} cells, {fp.epochs:,.0f} "
            f"GNSS epochs), and --max-memory (now {_gib(limit)}) is below the {_gib(BASE_BYTES)} any run takes "
            f"before its maps: no scenario setting fits such a limit; raise --max-memory (to at least "
            f"{_gib(fp.bytes)} for this scenario)")
    parts = sorted([(fp.bytes_cells + fp.bytes_levels, "cells"), (fp.bytes_epochs, "epochs")], reverse=True)
    if parts[0][1] == "cells":
        res = sc.aoi.resolution_m
        room = limit - BASE_BYTES - fp.bytes_epochs
        if room <= 0:   # the GNSS epochs alone fill the limit: no resolution fits
            raise InputError(
                f"scenario {sc.name!r} needs about {_gib(fp.bytes)} of memory: {fp.cells:,.0f} cells and "
                f"{fp.epochs:,.0f} GNSS epochs, whose {_gib(fp.bytes_epochs)} alone leave no room for any map "
                f"within --max-memory; shorten gnss.window_min or raise gnss.step_min, and raise aoi.resolution_m "
                f"or shrink aoi.bounds, {fix}")
        need = res * math.sqrt((fp.bytes_cells + fp.bytes_levels) / room)
        raise InputError(
            f"scenario {sc.name!r} needs about {_gib(fp.bytes)} of memory: {fp.cells:,.0f} cells "
            f"(aoi.resolution_m {res:g} m over aoi.bounds) x {fp.levels} DOP levels; raise aoi.resolution_m "
            f"(to {need:.3g} m or more) or shrink aoi.bounds, {fix}")
    raise InputError(
        f"scenario {sc.name!r} needs about {_gib(fp.bytes)} of memory: {fp.epochs:,.0f} GNSS epochs "
        f"(gnss.window_min {sc.gnss.window_min:g} / gnss.step_min {sc.gnss.step_min:g}) x about "
        f"{fp.satellites} satellites; shorten gnss.window_min or raise gnss.step_min, {fix}")


def check_ticks(duration_s: float, tick_s: float, limit_bytes: int | None = None, key: str = "--tick") -> float:
    """InputError when a flight of ``duration_s`` [s] sampled every ``tick_s`` [s] needs more
    than the limit; returns the number of ticks."""
    limit = max_memory_bytes() if limit_bytes is None else limit_bytes
    n = duration_s / tick_s if tick_s > 0 else math.inf
    need = n * BYTES_PER_TICK
    if need > limit:
        lo = duration_s * BYTES_PER_TICK / limit
        if not lo <= max(duration_s, tick_s):   # a tick longer than the flight: no --tick fits
            raise InputError(f"a {duration_s:,.0f} s flight sampled every {tick_s:g} s is {n:,.0f} ticks, about "
                             f"{_gib(need)} of memory, more than --max-memory (now {_gib(limit)}) holds: no {key} "
                             f"(tactical.tick_s) fits such a limit; raise --max-memory (to at least {_gib(need)} "
                             "for this tick)")
        raise InputError(f"a {duration_s:,.0f} s flight sampled every {tick_s:g} s is {n:,.0f} ticks, about "
                         f"{_gib(need)} of memory: raise {key} (tactical.tick_s) to {lo:.3g} s or more, or raise "
                         f"--max-memory (now {_gib(limit)})")
    return n


def check_fleet(sc, missions: int, max_km: float = MISSION_KM, limit_bytes: int | None = None,
                key: str = "--missions") -> float:
    """InputError (exit 2) when a fleet of ``missions`` missions up to ``max_km`` [km] long in
    ``sc`` needs more than the limit (the maps' footprint + :data:`BYTES_PER_MISSION` per
    mission, in proportion beyond :data:`MISSION_KM`); returns the estimate [bytes].  Cheap:
    call it before the maps are built."""
    limit = max_memory_bytes() if limit_bytes is None else limit_bytes
    maps = scenario_footprint(sc).bytes
    km = max_km if math.isfinite(max_km) else math.inf
    per = BYTES_PER_MISSION * max(1.0, km / MISSION_KM)
    need = maps + float(missions) * per
    if need > limit:
        fit = max(0, math.floor((limit - maps) / per)) if math.isfinite(per) else 0
        raise InputError(
            f"a fleet of {missions:,} missions needs about {_gib(need)} of memory ({per / 1024:,.0f} KiB per mission up to "
            f"{max(km, MISSION_KM):g} km, over {_gib(maps)} for the maps of scenario {sc.name!r}): give fewer "
            f"missions ({key}; {fit:,} fit) or raise --max-memory (now {_gib(limit)})")
    return need


def check_navsim(sc, runs: int, epochs: float, limit_bytes: int | None = None, at_least: bool = False) -> float:
    """InputError (exit 2) when ``runs`` Monte Carlo runs of a flight of ``epochs`` epochs
    (``at_least``: a lower bound, before the plan exists) need more than the limit (the plan's
    footprint + :data:`BYTES_PER_RUN_EPOCH` per run and epoch); returns the estimate [bytes]."""
    limit = max_memory_bytes() if limit_bytes is None else limit_bytes
    base = scenario_footprint(sc).bytes
    need = base + float(runs) * float(epochs) * BYTES_PER_RUN_EPOCH
    if need > limit:
        per_run = float(epochs) * BYTES_PER_RUN_EPOCH
        fit = max(0, math.floor((limit - base) / per_run)) if per_run > 0 else 0
        rate = sc.navsim.rate_hz
        raise InputError(
            f"navsim of {runs:,} runs x {'at least ' if at_least else ''}{epochs:,.0f} epochs (the flight at "
            f"navsim.rate_hz {rate:g} Hz) needs about {_gib(need)} of memory ({BYTES_PER_RUN_EPOCH} B per run and "
            f"epoch, over {_gib(base)} for the plan of scenario {sc.name!r}): give fewer --runs ({fit:,} fit) or "
            f"lower navsim.rate_hz, or raise --max-memory (now {_gib(limit)})")
    return need


_SIZE_UNITS = {"": 1, "B": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def parse_size(text: str, option: str = "--max-size") -> int:
    """``"10G"``, ``"500M"``, ``"1.5T"``, ``"1024"`` -> bytes (binary units; a trailing B or iB is allowed)."""
    import re

    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMGT]?)(?:i?B)?\s*", text, flags=re.IGNORECASE)
    if not m:
        raise InputError(f"{option} {text!r} is not a size: give e.g. 10G, 500M or a number of bytes")
    return int(float(m.group(1)) * _SIZE_UNITS[m.group(2).upper()])


# the readers of stages size their allocations from a file's header against this limit
# (stages never import the pipeline: the limit is handed down through stages.base)
from skyroute.stages import base as _stages_base  # noqa: E402

_stages_base.memory_limit_hook = max_memory_bytes
