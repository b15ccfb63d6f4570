"""The outputs of a ``fly`` folder (``skyroute fly`` and the flight of ``skyroute run``)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["write_fly_folder"]


def write_fly_folder(fr, out_dir: Path, command: str = "fly") -> dict:
    """Write the flight outputs and ``summary.json`` of a ``fly`` folder; return the section."""
    from skyroute.pipeline.outputs import write_folder_summary
    from skyroute.pipeline.report import write_fly_map
    from skyroute.stages.tactical.outputs import flight_section, write_flight

    files = write_flight(fr.log, out_dir)
    fly_map = write_fly_map(out_dir)
    if fly_map is not None:
        files["fly.html"] = fly_map
    section = flight_section(fr.log)
    write_folder_summary(out_dir, command, fr.result, [str(p) for p in files.values()], {"fly": section})
    return section
