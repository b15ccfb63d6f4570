"""Outputs of the navigation Monte Carlo (``skyroute navsim``): ``navsim.csv``, the ``navsim``
section of ``summary.json`` and the figures (seed 003 Figs. 11-13 and 16).

Everything is written from the :func:`skyroute.stages.navsim.simulate` Dataset.  The safety
bubble is ``r_phi = k sigma + surface uncertainty`` (:func:`~skyroute.stages.navsim.bubble_radius_m`);
containment is the share over runs and epochs of ``|error| <= k sigma``
(:func:`~skyroute.stages.navsim.containment`; the surface uncertainty is reported separately,
not added to it).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from skyroute.stages.integrity import pl_containment
from skyroute.stages.navsim import FILTERS, containment, proposed_beats_weak
from skyroute.stages.sboa import bubble_radius_m

__all__ = ["NAVSIM_COLUMNS", "navsim_section", "protection_level_section", "write_navsim"]

NAVSIM_COLUMNS = ("run", "t_s", "err_proposed_m", "sigma_proposed_m", "err_weak_m", "sigma_weak_m", "n_visible",
                  "n_received", "n_nlos_used", "dop_visible", "dop_all")


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _norms(ds: xr.Dataset) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for f in FILTERS:
        err = np.linalg.norm(np.asarray(ds[f"err_{f}_m"].values, float), axis=-1)        # (run, time)
        sig = np.broadcast_to(np.asarray(ds[f"sigma_{f}_m"].values, float), err.shape)
        out[f] = (err, sig)
    return out


def navsim_section(ds: xr.Dataset, surface_uncertainty_m: float) -> dict[str, Any]:
    """The ``navsim`` section of summary.json: ``containment: {proposed: {1sigma, 2sigma,
    3sigma}, weak: {...}}`` (fractions in [0, 1]), ``proposed_beats_weak`` (share of run-epochs
    where the proposed error is smaller), RMS and 95 % errors [m], the 3-sigma bubble radius
    (median / max over the flight, surface uncertainty included) and the settings."""
    n = _norms(ds)
    sec: dict[str, Any] = {
        "runs": int(ds.sizes["run"]), "epochs": int(ds.sizes["time"]), "seed": int(ds.attrs.get("seed", 0)),
        "source": str(ds.attrs.get("source", "")), "containment": containment(ds),
        "proposed_beats_weak": float(proposed_beats_weak(ds)), "surface_uncertainty_m": float(surface_uncertainty_m)}
    for f, (err, sig) in n.items():
        r3 = bubble_radius_m(sig, 3.0, surface_uncertainty_m)
        sec[f] = {"rms_error_m": _num(np.sqrt(np.mean(err ** 2))), "p95_error_m": _num(np.percentile(err, 95)),
                  "bubble_3sigma_median_m": _num(np.median(r3)), "bubble_3sigma_max_m": _num(np.max(r3))}
    sec["nlos_used_share"] = _num(np.mean(np.asarray(ds["n_nlos_used"].values) > 0))
    if "hpl_m" in ds and "vpl_m" in ds:
        sec["protection_level"] = protection_level_section(ds)
    return sec


def protection_level_section(ds: xr.Dataset) -> dict[str, Any]:
    """``protection_level`` of the navsim section (when ``ds`` has ``hpl_m``/``vpl_m``, e.g.
    from :func:`skyroute.stages.integrity.pl_series`): median HPL/VPL [m] over the epochs with
    a PL, their availability, the containment of the proposed filter's errors
    (``|e_h| <= HPL``, ``|e_u| <= VPL``; :func:`~skyroute.stages.integrity.pl_containment`)
    and the budgets.  The PL bounds the snapshot least-squares error; the filter's error is
    typically smaller (it averages over time), so this containment is expected near 1."""
    hpl = np.asarray(ds["hpl_m"].values, float)
    vpl = np.asarray(ds["vpl_m"].values, float)
    c = pl_containment(ds["err_proposed_m"].values, hpl, vpl)
    ok = np.isfinite(hpl) & np.isfinite(vpl)
    budgets = {k[len("budget_"):]: float(v) for k, v in ds["hpl_m"].attrs.items() if k.startswith("budget_")}
    return {"method": "single-fault solution separation (ARAIM ADD v3.1), line-of-sight snapshot least squares",
            "hpl_median_m": _num(np.median(hpl[ok])) if ok.any() else None,
            "vpl_median_m": _num(np.median(vpl[ok])) if ok.any() else None,
            "availability": _num(c["availability"]), "containment_h": _num(c["containment_h"]),
            "containment_v": _num(c["containment_v"]), "budgets": budgets}


def write_navsim(ds: xr.Dataset, out_dir, surface_uncertainty_m: float = 0.0, figures: bool = True
                 ) -> dict[str, Path]:
    """Write ``navsim.csv`` (one row per run and epoch) and the figures; returns the files."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    n = _norms(ds)
    t = np.asarray(ds["time"].values, float)
    per_time = {k: np.asarray(ds[k].values) for k in ("n_visible", "n_received", "dop_visible", "dop_all")}
    nlos = np.asarray(ds["n_nlos_used"].values)
    path = out / "navsim.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(NAVSIM_COLUMNS)
        ep, sp = n["proposed"]
        ew, sw = n["weak"]
        for r in range(ep.shape[0]):
            for i in range(t.size):
                w.writerow([r, f"{t[i]:.3f}", f"{ep[r, i]:.4f}", f"{sp[r, i]:.4f}", f"{ew[r, i]:.4f}", f"{sw[r, i]:.4f}",
                            int(per_time["n_visible"][i]), int(per_time["n_received"][i]), int(nlos[r, i]),
                            f"{per_time['dop_visible'][i]:.4f}", f"{per_time['dop_all'][i]:.4f}"])
    files["navsim.csv"] = path
    if figures:
        files.update(_figures(ds, out, t, n, surface_uncertainty_m))
        if "hpl_m" in ds and "vpl_m" in ds:
            files.update(_pl_figure(ds, out, t, surface_uncertainty_m))
    return files


def _figures(ds, out: Path, t, n, s_unc) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages.figures import grow_until_unclipped

    files = {}
    title = f"{ds.attrs.get('scenario', '')}: navigation Monte Carlo ({ds.sizes['run']} runs)"
    colours = {"proposed": "tab:blue", "weak": "tab:red"}
    # errors of run 0 with their 3-sigma bubbles (seed 003 Fig. 11)
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), dpi=100, sharex=True, layout="constrained")
    for ax, f in zip(axes, ("proposed", "weak"), strict=True):
        err, sig = n[f]
        ax.plot(t, err[0], color=colours[f], lw=1.0, label=f"{f}: |position error|, run 0")
        ax.plot(t, bubble_radius_m(sig[0], 3.0, s_unc), "k-", lw=1.2,
                label=f"bubble r = 3 sigma + {s_unc:g} m (surface uncertainty)")
        ax.plot(t, 3.0 * sig[0], "k--", lw=0.8, label="3 sigma")
        ax.set_ylabel("[m]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
        ax.set_title(f"{f} filter", fontsize=10)
    axes[-1].set_xlabel("mission time [s]")
    fig.suptitle(title + ": errors and safety bubble")
    files["navsim_errors.png"] = out / "navsim_errors.png"
    grow_until_unclipped(fig)
    fig.savefig(files["navsim_errors.png"])
    plt.close(fig)
    # bubble radius vs error percentiles, containment per k (seed 003 Fig. 12)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.6), dpi=100, layout="constrained",
                                 gridspec_kw={"width_ratios": [2.2, 1]})
    for f in FILTERS:
        err, sig = n[f]
        a1.plot(t, np.percentile(err, 95, axis=0), color=colours[f], lw=1.2, label=f"{f}: 95 % of |error| over runs")
        a1.plot(t, np.median(bubble_radius_m(sig, 3.0, s_unc), axis=0), color=colours[f], ls="--", lw=1.2,
                label=f"{f}: 3-sigma bubble (median over runs)")
    a1.set_xlabel("mission time [s]")
    a1.set_ylabel("[m]")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8)
    a1.set_title("bubble radius vs error")
    cont = containment(ds)
    x = np.arange(3)
    for j, f in enumerate(FILTERS):
        vals = [cont[f][f"{k}sigma"] for k in (1, 2, 3)]
        a2.bar(x + (j - 0.5) * 0.38, vals, 0.36, color=colours[f], label=f)
        for xi, v in zip(x, vals, strict=True):
            a2.text(xi + (j - 0.5) * 0.38, v + 0.01, f"{v:.2f}", ha="center", fontsize=7)
    a2.set_xticks(x, ["1 sigma", "2 sigma", "3 sigma"])
    a2.set_ylim(0, 1.12)
    a2.set_ylabel("containment (share of run-epochs)")
    a2.legend(fontsize=8, loc="lower right")
    a2.set_title("|error| <= k sigma")
    fig.suptitle(title + ": containment")
    files["navsim_bubble.png"] = out / "navsim_bubble.png"
    grow_until_unclipped(fig)
    fig.savefig(files["navsim_bubble.png"])
    plt.close(fig)
    # satellites and DOP along the path (seed 003 Figs. 13 and 16)
    fig, (b1, b2) = plt.subplots(2, 1, figsize=(10, 5.8), dpi=100, sharex=True, layout="constrained")
    b1.step(t, ds["n_received"].values, where="post", color="0.3", label="above the mask (total)")
    b1.step(t, ds["n_visible"].values, where="post", color="tab:green", label="in line of sight (maps)")
    b1.set_ylabel("satellites")
    b1.grid(alpha=0.3)
    b1.legend(fontsize=8)
    dv = np.asarray(ds["dop_visible"].values, float)
    da = np.asarray(ds["dop_all"].values, float)
    b2.plot(t, np.where(np.isfinite(dv), dv, np.nan), color="tab:green", label="PDOP, line of sight only")
    b2.plot(t, np.where(np.isfinite(da), da, np.nan), color="0.3", ls="--", label="PDOP, every satellite above the mask")
    if (~np.isfinite(dv)).any():
        b2.plot([], [], " ", label="gaps: no fix (fewer than 4 in line of sight)")
    b2.set_ylabel("PDOP")
    b2.set_xlabel("mission time [s]")
    b2.grid(alpha=0.3)
    b2.legend(fontsize=8)
    fig.suptitle(f"{ds.attrs.get('scenario', '')}: satellites and DOP along the path")
    files["navsim_sats.png"] = out / "navsim_sats.png"
    grow_until_unclipped(fig)
    fig.savefig(files["navsim_sats.png"])
    plt.close(fig)
    return files


def _pl_figure(ds, out: Path, t, s_unc) -> dict[str, Path]:
    """Protection levels vs the proposed filter's horizontal / vertical errors and its 3-sigma
    bubble (``navsim_pl.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages.figures import grow_until_unclipped

    err = np.asarray(ds["err_proposed_m"].values, float)
    parts = (("horizontal", np.hypot(err[..., 0], err[..., 1]), np.asarray(ds["hpl_m"].values, float), "HPL"),
             ("vertical", np.abs(err[..., 2]), np.asarray(ds["vpl_m"].values, float), "VPL"))
    r3 = bubble_radius_m(np.asarray(ds["sigma_proposed_m"].values, float), 3.0, s_unc)
    fig, axes = plt.subplots(2, 1, figsize=(12, 6.5), dpi=100, sharex=True, layout="constrained")
    for ax, (name, e, pl, lab) in zip(axes, parts, strict=True):
        ax.plot(t, np.where(np.isfinite(pl), pl, np.nan), "k-", lw=1.4, label=f"{lab} (solution separation)")
        ax.plot(t, r3, color="tab:purple", ls="--", lw=1.0, label=f"3-sigma bubble + {s_unc:g} m (3-D sigma)")
        ax.plot(t, np.percentile(e, 95, axis=0), color="tab:blue", lw=1.0, label=f"{name} error, 95 % over runs")
        ax.plot(t, e[0], color="tab:blue", lw=0.6, alpha=0.5, label=f"{name} error, run 0")
        if (~np.isfinite(pl)).any():
            ax.plot([], [], " ", label=f"gaps: no {lab} (fewer than 5 in\nline of sight or a critical satellite)")
        ax.set_ylabel("[m]")
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        ax.set_title(f"{name}: proposed filter", fontsize=10)
    axes[-1].set_xlabel("mission time [s]")
    name = ds.attrs.get("scenario", "")
    fig.suptitle(f"{name + ': ' if name else ''}protection levels vs errors ({ds.sizes['run']} runs)")
    path = out / "navsim_pl.png"
    grow_until_unclipped(fig)
    fig.savefig(path)
    plt.close(fig)
    return {"navsim_pl.png": path}
