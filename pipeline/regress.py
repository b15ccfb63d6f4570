"""``skyroute regress``: every catalog scenario through the cache, its key figures against
golden values.

For each scenario the key figures are (:func:`scenario_figures`):

* ``plan.*``: the chosen candidate (label, DOP level, f and its four terms [m], 3-D length
  [m], energy [Wh], flight time [s]) and which levels are flyable, from the cached plan stage;
* ``fly.*`` (scenarios with events): outcome, replannings and the level chosen in each, flight
  time [s], length [m], energy [Wh], closest approach to each intruder [m] (``skyroute fly``);
* ``navsim.*`` (scenarios with almanacs and no events): 1/2/3-sigma containment of both
  filters, the share of time the proposed error is the smaller, RMS errors [m]
  (``skyroute navsim`` with the scenario's ``navsim`` settings).

Timings are never figures.  Each figure has a tolerance in its physical unit
(:data:`TOLERANCES`, by name suffix); strings, booleans and integers must be equal.

Caching: the stages come from the stage cache; the ``fly`` and ``navsim`` figures are stored
in ``<cache>/regress/<key>.json`` (atomic write), with ``key`` a stable hash of the stage keys
of the run (inputs, settings and stage code), of the whole scenario's settings and of the
source of every skyroute module the fly / navsim code imports.  A warm regress therefore
recomputes nothing unless an input, a setting or the code changed.

Goldens: ``catalogs/golden/<scenario>.json`` (packaged) or ``--golden-dir``; ``--update``
rewrites them (review the diff before committing).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import InputError
from skyroute.pipeline.settings import Scenario, catalog_dir, load_scenario, scenario_paths

__all__ = ["GOLDEN_SCHEMA", "TOLERANCES", "Check", "RegressResult", "compare_figures", "golden_dir",
           "read_golden", "regress", "scenario_figures", "tolerance_of", "write_golden"]

GOLDEN_SCHEMA = 1

# Tolerance [unit of the figure] by name suffix (the first match wins).  Plans are deterministic
# on one machine; the tolerances absorb floating-point differences between CPUs and libraries
# (a plan that changes its route moves these figures by metres, not centimetres).
TOLERANCES: tuple[tuple[str, float], ...] = (
    ("sigma", 0.02),          # containment fractions (navsim.containment.*.1sigma ...)
    ("_share", 0.02),         # fractions of time
    ("_Wh", 0.05),            # energy [Wh]
    ("_s", 0.5),              # durations [s]
    ("_m", 0.5),              # lengths, costs, distances [m]
    ("dop_threshold", 0.0),
)

FLY_MODULES = ("skyroute.pipeline.fly", "skyroute.stages.tactical.replay", "skyroute.stages.tactical.outputs",
               "skyroute.pipeline.regress")
NAVSIM_MODULES = ("skyroute.pipeline.navsim", "skyroute.stages.navsim", "skyroute.stages.navsim_outputs",
                  "skyroute.pipeline.regress")


def tolerance_of(name: str) -> float | None:
    """The tolerance of figure ``name`` (None: must be equal)."""
    for suffix, tol in TOLERANCES:
        if name.endswith(suffix):
            return tol
    return None


@dataclass
class Check:
    """One figure: ``status`` is ``pass``, ``fail`` or ``new`` (no golden value) or ``gone``
    (a golden figure the run no longer produces: a failure)."""

    scenario: str
    name: str
    value: Any
    golden: Any
    tolerance: float | None
    status: str


@dataclass
class RegressResult:
    checks: list[Check] = field(default_factory=list)
    figures: dict[str, dict[str, Any]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    info: dict[str, dict[str, Any]] = field(default_factory=dict)   # stage cache hits, memo use

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if c.status in ("fail", "gone")]

    def counts(self) -> dict[str, int]:
        out = {"pass": 0, "fail": 0, "new": 0, "gone": 0}
        for c in self.checks:
            out[c.status] += 1
        return out


# ------------------------------------------------------------------ figures
def _num(v: Any) -> float | None:
    if v is None:
        return None
    v = float(v)
    return round(v, 4) if math.isfinite(v) else None


def _plan_figures(result) -> dict[str, Any]:
    from skyroute.pipeline.outputs import plan_section

    ds = result["plan"].load()
    sec = plan_section(ds)
    out: dict[str, Any] = {"plan.status": sec["status"], "plan.label": sec["label"],
                           "plan.dop_threshold": sec["dop_threshold"]}
    for k in ("f_m", "C_l_m", "C_r_m", "C_d_m", "C_e_m", "length_m", "energy_Wh", "flight_time_s",
              "clearance_radius_m"):
        if k in sec:
            out[f"plan.{k}"] = _num(sec[k])
    flyable = [str(ds["label"].values[i]) for i in range(ds.sizes.get("level", 0)) if bool(ds["flyable"].values[i])]
    out["plan.flyable_levels"] = ",".join(flyable)
    return out


def _fly_figures(sc: Scenario, cache: Cache, result) -> dict[str, Any]:
    from skyroute.pipeline.fly import fly_scenario
    from skyroute.stages.tactical.outputs import flight_section

    sec = flight_section(fly_scenario(sc, cache=cache, result=result).log)
    out: dict[str, Any] = {"fly.outcome": sec["outcome"], "fly.n_replannings": int(sec["n_replannings"]),
                           "fly.chosen_levels": ",".join(str(x) for x in sec["chosen_levels"]),
                           "fly.flight_time_s": _num(sec["flight_time_s"]), "fly.length_m": _num(sec["length_m"]),
                           "fly.energy_Wh": _num(sec["energy_Wh"])}
    for rec in sec["min_separation"]:
        out[f"fly.closest.{rec['id']}_m"] = _num(rec["min_distance_m"])
    return out


def _navsim_figures(sc: Scenario, cache: Cache) -> dict[str, Any]:
    from skyroute.pipeline.navsim import navsim_scenario
    from skyroute.stages.navsim_outputs import navsim_section

    r = navsim_scenario(sc, cache=cache)
    sec = navsim_section(r.ds, r.surface_uncertainty_m)
    out: dict[str, Any] = {"navsim.runs": int(sec["runs"]), "navsim.epochs": int(sec["epochs"])}
    for f in ("proposed", "weak"):
        for k, v in sec["containment"][f].items():
            out[f"navsim.containment.{f}.{k}"] = _num(v)
        out[f"navsim.{f}.rms_error_m"] = _num(sec[f]["rms_error_m"])
    out["navsim.proposed_smaller_share"] = _num(sec["proposed_beats_weak"])
    return out


def _code_hash(modules: tuple[str, ...]) -> str:
    import hashlib

    from skyroute.pipeline.graph import _module_source, code_closure

    h = hashlib.sha256()
    for m in sorted(code_closure(set(modules))):
        h.update(m.encode())
        h.update(_module_source(m) or b"")
    return h.hexdigest()[:16]


def _memo(cache: Cache, kind: str, key: str, make) -> tuple[dict[str, Any], bool]:
    """``make()`` once per ``key`` (stored as JSON under ``<cache>/regress``, atomically)."""
    path = cache.root / "regress" / f"{kind}-{key}.json"
    if path.is_file():
        try:
            return json.loads(path.read_text()), True
        except (OSError, ValueError):
            pass                      # damaged: recompute and overwrite
    out = make()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(out, sort_keys=True))
    os.replace(tmp, path)
    return out, False


def scenario_figures(sc: Scenario, cache: Cache | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(figures, info)`` of one scenario (see the module docstring); ``info`` has
    ``stage_hits`` / ``stages`` and which parts came from the regress memo."""
    import warnings

    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.runner import run_scenario

    cache = cache or Cache()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_scenario(sc, cache=cache, targets=["plan"])
        figs = _plan_figures(result)
        info: dict[str, Any] = {"stages": len(result.records), "stage_hits": result.cache_hits}
        run_keys = sorted((r.name, r.key) for r in result.records)
        settings = sc.model_dump(mode="json")
        if figs["plan.status"] == "flyable" and sc.events:
            key = stable_hash("fly", run_keys, settings, _code_hash(FLY_MODULES))
            part, info["fly_memo"] = _memo(cache, "fly", key, lambda: _fly_figures(sc, cache, result))
            figs.update(part)
        if figs["plan.status"] == "flyable" and sc.data.almanacs and not sc.events:
            key = stable_hash("navsim", run_keys, settings, _code_hash(NAVSIM_MODULES))
            part, info["navsim_memo"] = _memo(cache, "navsim", key, lambda: _navsim_figures(sc, cache))
            figs.update(part)
    return figs, info


# ------------------------------------------------------------------ goldens
def golden_dir() -> Path:
    """The packaged goldens: ``catalogs/golden``."""
    return catalog_dir() / "golden"


def read_golden(directory: Path, name: str) -> dict[str, Any] | None:
    path = Path(directory) / f"{name}.json"
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except ValueError as exc:
        raise InputError(f"golden file {path} is not valid JSON ({exc}): fix it or rewrite it with "
                         "`skyroute regress --update`") from None
    if not isinstance(doc, dict) or doc.get("schema_version") != GOLDEN_SCHEMA or "figures" not in doc:
        raise InputError(f"golden file {path} is not a schema-{GOLDEN_SCHEMA} golden: rewrite it with "
                         "`skyroute regress --update`")
    return doc["figures"]


def write_golden(directory: Path, name: str, figures: dict[str, Any]) -> Path:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.json"
    doc = {"schema_version": GOLDEN_SCHEMA, "scenario": name,
           "tolerances": {k: tolerance_of(k) for k in sorted(figures)}, "figures": figures}
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)
    return path


def compare_figures(name: str, figures: dict[str, Any], golden: dict[str, Any] | None) -> list[Check]:
    """One :class:`Check` per figure of the run and per golden figure the run lacks."""
    out = []
    golden = golden or {}
    for k in sorted(set(figures) | set(golden)):
        tol = tolerance_of(k)
        if k not in golden:
            out.append(Check(name, k, figures[k], None, tol, "new"))
            continue
        if k not in figures:
            out.append(Check(name, k, None, golden[k], tol, "gone"))
            continue
        v, g = figures[k], golden[k]
        if isinstance(v, bool) or isinstance(g, bool) or isinstance(v, str) or isinstance(g, str) or tol is None:
            ok = v == g
        elif v is None or g is None:
            ok = v is None and g is None
        else:
            ok = abs(float(v) - float(g)) <= tol + 1e-12
        out.append(Check(name, k, v, g, tol, "pass" if ok else "fail"))
    return out


# ------------------------------------------------------------------ driver
def _one(name: str, cache_root: str | None) -> tuple[str, dict[str, Any], dict[str, Any], float, str]:
    """One scenario (a dask task on a cluster): ``(name, figures, info, seconds, error)``."""
    from skyroute.pipeline.errors import SkyrouteError

    t0 = time.perf_counter()
    try:
        figs, info = scenario_figures(load_scenario(name), Cache(cache_root))
        return name, figs, info, time.perf_counter() - t0, ""
    except SkyrouteError as exc:
        return name, {}, {}, time.perf_counter() - t0, str(exc)


def regress(names: list[str] | None = None, *, cache: Cache | None = None, golden: Path | None = None,
            update: bool = False, scheduler: str = "threads", workers: int | None = None,
            echo=None) -> RegressResult:
    """Run ``names`` (default: the whole catalog) and compare with the goldens in ``golden``
    (default :func:`golden_dir`); ``update`` writes the figures as the new goldens.  With
    ``scheduler`` ``distributed`` or ``tcp://...`` each scenario is one task on the cluster
    (workers must see the same cache folder)."""
    from skyroute.pipeline.graph import scheduler_context

    known = sorted(scenario_paths())
    names = list(names) if names else known
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InputError(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(known)}")
    cache = cache or Cache()
    golden = Path(golden) if golden is not None else golden_dir()
    goldens = {n: read_golden(golden, n) for n in names}       # bad golden files: before any work
    out = RegressResult()
    with scheduler_context(scheduler, workers) as client:
        if client is not None:
            futs = client.map(_one, names, [str(cache.root)] * len(names), pure=False)
            rows = client.gather(futs)
        else:
            rows = []
            for n in names:
                rows.append(_one(n, str(cache.root)))
                if echo is not None:
                    echo(f"regress: {n} ({rows[-1][3]:.1f} s)")
    for name, figs, info, secs, err in rows:
        out.seconds[name] = secs
        out.info[name] = info
        if err:
            out.errors[name] = err
            out.checks.append(Check(name, "error", err, None, None, "fail"))
            continue
        out.figures[name] = figs
        if update:
            write_golden(golden, name, figs)
            out.checks.extend(Check(name, k, v, v, tolerance_of(k), "pass") for k, v in sorted(figs.items()))
        else:
            out.checks.extend(compare_figures(name, figs, goldens[name]))
    return out
