"""The outputs of a ``fly`` folder (``skyroute fly`` and the flight of ``skyroute run``)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["FLY_OUTPUT_MODULES", "fly_folder", "write_fly_folder"]

#: The code a flight folder depends on beyond the stages (the replay, its outputs and pages): part
#: of its memo key, as a stage's code is part of the stage's key.
FLY_OUTPUT_MODULES = ("skyroute.pipeline.fly", "skyroute.pipeline.fly_fw", "skyroute.pipeline.fly_outputs",
                      "skyroute.stages.tactical.replay", "skyroute.stages.tactical.outputs",
                      "skyroute.stages.tactical.fw_local", "skyroute.pipeline.planmap", "skyroute.pipeline.report")


def write_fly_folder(fr, out_dir: Path, command: str = "fly", **extra) -> dict:
    """Write the flight outputs and ``summary.json`` of a ``fly`` folder; return the section
    (with ``extra`` keys, e.g. ``replayed``)."""
    from skyroute.pipeline.outputs import write_folder_summary
    from skyroute.pipeline.report import write_fly_map
    from skyroute.stages.tactical.outputs import flight_section, write_flight

    files = write_flight(fr.log, out_dir)
    fly_map = write_fly_map(out_dir, getattr(fr, "result", None))   # with the buildings and coverage
    if fly_map is not None:
        files["fly.html"] = fly_map
    section = {**flight_section(fr.log), **extra}
    write_folder_summary(out_dir, command, fr.result, [str(p) for p in files.values()], {"fly": section})
    return section


def fly_folder(sc, out_dir: Path, *, cache, scheduler: str = "threads", progress: bool = False,
               command: str = "fly", result=None, **params) -> dict:
    """Fly ``sc`` (:func:`skyroute.pipeline.fly.fly_scenario` with ``params``: ``t_rep_s``,
    ``tick_s``, ``seed``, ``method``) and write its folder (:func:`write_fly_folder`); return the
    ``fly`` section.  The flight is a function of the cached stages, the scenario, ``params`` and
    the replay's code (:data:`FLY_OUTPUT_MODULES`): its files are memoised under that key
    (:mod:`skyroute.pipeline.output_memo`), so flying it again into a new folder copies them
    (the section then says ``"replayed": false``; its compute times are those of the replay
    that made them).  A flight during which a search stopped at its wall-clock safety cap is
    never memoised (its decisions may depend on the machine's load)."""
    from skyroute.pipeline.fly import check_flight, fly_scenario
    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.output_memo import computed_in_run, memo_of
    from skyroute.pipeline.outputs import write_folder_summary
    from skyroute.pipeline.regress import _code_hash
    from skyroute.pipeline.runner import run_scenario
    from skyroute.stages import control

    out_dir = Path(out_dir)
    check_flight(sc, **params)          # before any stage: a bad tick or method is one error line
    if result is None:
        result = run_scenario(sc, cache=cache, targets=["plan"], scheduler=scheduler, progress=progress)
    cached = all(r.path for r in result.records)
    memo = memo_of(result) if cached else None
    key = stable_hash("fly-folder", command, sorted((r.name, r.key) for r in result.records),
                      sc.model_dump(mode="json"), sorted(params.items()), _code_hash(FLY_OUTPUT_MODULES))
    if memo is not None and not computed_in_run(result):      # --force: flown again
        meta = memo.fetch(key, out_dir)
        if meta and isinstance(meta.get("files"), list) and isinstance(meta.get("section"), dict):
            section = {**meta["section"], "replayed": False}
            write_folder_summary(out_dir, command, result, [str(out_dir / f) for f in meta["files"]], {"fly": section})
            return section
    stops = control.clock_stops()
    fr = fly_scenario(sc, cache=cache, scheduler=scheduler, progress=progress, result=result, **params)
    from skyroute.pipeline.progress import phase

    with phase("fly: outputs"):
        section = write_fly_folder(fr, out_dir, command, replayed=True)
    if memo is not None and control.clock_stops() == stops:
        files = sorted(p.relative_to(out_dir).as_posix() for p in out_dir.rglob("*")
                       if p.is_file() and not p.name.startswith(".") and p.name != "summary.json")
        memo.store(key, out_dir, {"files": files, "section": section}, only=files)
    return section
