"""Degenerate cost terms: a term of eq. 11 whose cost per metre is the same for every cell,
altitude and heading carries no information (seed 000 III-A-2).

Such a term is a constant multiple of the length, ``C_k = c_k C_l``: with ``c_k > 0`` its
weight only adds to ``w_l``; with ``c_k = 0`` it contributes nothing.  Weights whose non-zero
terms are all degenerate (``w_l = 0``) would then rank every path by length or not at all,
which is not what the user asked for: that is an error (:class:`DegenerateCostError`) that names
the data source making the term meaningful.  Any degenerate term is reported as a warning.

Detection is from the rasters the planner integrates (:mod:`skyroute.stages.planning.problem`),
never from the scenario's settings:

* ``C_r``: ``risk_cost`` takes one value (within ``atol``) over the flyable cells (finite
  cost, not ``nofly`` from the ground up without ceiling; altitude-limited zones stay flyable).  Typical cause: no land use, so every cell is at the default level 4
  and the min-max normalised cost is 0;
* ``C_d``: ``landing_cost`` likewise (no landing site: cost 1 everywhere, so ``C_d = C_l``);
* ``C_e``: the wind is zero everywhere (or there is no wind map): the energy ratio
  ``E_w / E_0`` of eq. 12 is 1 for every heading and climb, so ``C_e = C_l``.  A uniform
  non-zero wind is *not* degenerate (head and tail wind cost differently).
* ``C_l`` (length) is the reference and never degenerate.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from skyroute.stages.base import DegenerateCostError
from skyroute.stages.planning.problem import check_weights

ATOL = 1e-12

#: term -> (weight name, what it measures, the data source that makes it meaningful)
TERMS: dict[str, tuple[str, str, str]] = {
    "C_r": ("w_r", "risk", "data.landuse (an OSM extract with land use) or CityJSON data.buildings"),
    "C_d": ("w_d", "landing", "data.landing_sites (a GeoJSON of landing sites) or an OSM extract with helipads "
                              "or parks in data.landuse (with data.osm_landing_sites: true)"),
    "C_e": ("w_e", "energy", "data.wind (a GFS NetCDF) or data.uniform_wind with a speed > 0"),
}


def _uniform_range(lo: float, hi: float, atol: float) -> float | None:
    """``lo`` when [lo, hi] is at most ``atol`` wide, None when wider or NaN (no value)."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return None
    return lo if hi - lo <= atol else None


def _wind_is_zero(wind, atol: float) -> bool:
    if wind is None:
        return True
    if isinstance(wind, xr.Dataset):
        comps = [np.asarray(wind[k].values, dtype=float) for k in ("u", "v", "w") if k in wind]
        return all(np.all(np.abs(c) <= atol) for c in comps)
    if hasattr(wind, "components") and callable(wind.components):
        wind = wind.components()
    return bool(np.all(np.abs(np.asarray(wind, dtype=float)) <= atol))


def degenerate_cost_terms(environment: xr.Dataset | None, wind=None, *, atol: float = ATOL) -> dict[str, str]:
    """The degenerate terms of eq. 11 among ``C_r``, ``C_d``, ``C_e`` -> why (a clause that
    completes "...because ..."; module docstring).

    ``environment``: the environment stage dataset (``risk_cost``, ``landing_cost``, optional
    ``nofly``, ``risk_level``; None = no maps: risk and landing cost 0, as the planner takes
    them); ``wind``: the wind stage dataset (``u``, ``v``, ``w``), a UniformWind, a (3,) vector
    [m/s] or None (no wind); ``atol``: tolerance of "the same value" [-] (cost per metre).
    """
    out: dict[str, str] = {}
    if environment is None:
        out["C_r"] = "there is no risk map (risk cost 0 everywhere)"
        out["C_d"] = "there is no landing-site map (landing cost 0 everywhere)"
    else:
        # chunk by chunk (a zarr-backed dataset is never loaded whole: 1e8 cells of a city), in
        # the rasters' own dtype: the min and max of float32 values are exact
        risk = environment["risk_cost"]
        fly = np.isfinite(risk)
        if "nofly" in environment:   # cells forbidden at every altitude (not altitude-limited zones)
            nofly = environment["nofly"].astype(bool)
            if "nofly_floor_m" in environment and "nofly_ceiling_m" in environment:
                nofly = nofly & ~(environment["nofly_floor_m"] > 0) & np.isinf(environment["nofly_ceiling_m"])
            fly = fly & ~nofly
        red = {"r_lo": risk.where(fly).min(), "r_hi": risk.where(fly).max(),
               "d_lo": environment["landing_cost"].where(fly).min(), "d_hi": environment["landing_cost"].where(fly).max()}
        got = {k: float(v) for k, v in xr.Dataset(red).compute().data_vars.items()}
        r = _uniform_range(got["r_lo"], got["r_hi"], atol)
        if r is not None:
            levels = ""
            if "risk_level" in environment:
                lv = np.unique(np.asarray(environment["risk_level"].where(fly).values)).tolist()
                lv = [int(v) for v in lv if np.isfinite(v)]
                levels = f", every flyable cell at level {lv[0]}" if len(lv) == 1 else f", levels {lv}"
            src = str(environment.attrs.get("risk_sources", "")) or "unknown"
            why = "no land use" if src.startswith("none") else f"risk sources: {src}"
            out["C_r"] = (f"the risk map is uniform ({why}{levels}: risk cost {r:g} on every flyable cell, "
                          f"so C_r = {r:g} x C_l)")
        d = _uniform_range(got["d_lo"], got["d_hi"], atol)
        if d is not None:
            n = int(environment.attrs.get("n_landing_sites", -1))
            why = "there are no landing sites" if n == 0 else "the landing-site map is uniform"
            out["C_d"] = f"{why} (landing cost {d:g} on every flyable cell, so C_d = {d:g} x C_l)"
    if _wind_is_zero(wind, atol):
        out["C_e"] = ("there is no wind" if wind is None else "the wind is zero everywhere") + \
            " (E_w / E_0 = 1 for every heading, so C_e = C_l)"
    return out


def _join(items: list[str], word: str = "and") -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + f" {word} " + items[-1]


def check_cost_terms(weights, degenerate: dict[str, str]) -> list[str]:
    """Warnings (one per degenerate term with a non-zero weight: a term weighted 0 does not
    enter f, so its map is not worth a warning) for eq. 11 weights
    ``(w_l, w_r, w_d, w_e)``; raises :class:`DegenerateCostError` when every non-zero weight
    is on a degenerate term (``w_l = 0``); bad weights raise InputError first."""
    w = dict(zip(("C_l", "C_r", "C_d", "C_e"), check_weights(weights), strict=True))
    selected = [k for k, v in w.items() if v > 0]
    if selected and all(k in degenerate for k in selected):
        names = [TERMS[k][1] for k in selected]
        useful = ["w_l"] + [TERMS[k][0] for k in TERMS if k not in degenerate]
        wtxt = ", ".join(f"{w[k]:g}" for k in w)
        raise DegenerateCostError(
            f"weights (w_l, w_r, w_d, w_e) = ({wtxt}) select only the {_join(names)} term"
            f"{'s' if len(names) > 1 else ''}, but {_join([degenerate[k] for k in selected])}: every path "
            f"would be ranked by its length alone (or not at all); add {_join([TERMS[k][2] for k in selected])}, "
            f"or set {'/'.join(useful)}")
    warnings = []
    for k in ("C_r", "C_d", "C_e"):
        if k in degenerate and w[k] > 0:
            wname, what, source = TERMS[k]
            warnings.append(f"plan: the {what} cost {k} ({wname} = {w[k]:g}) carries no information: "
                            f"{degenerate[k]}; add {source} to make it meaningful")
    return warnings


__all__ = ["ATOL", "TERMS", "check_cost_terms", "degenerate_cost_terms"]
