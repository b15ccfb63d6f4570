"""Every command runs on an AOI whose overlapped dask blocks come out uneven (issue 23).

``skyroute coverage`` of the 6 x 6 km AOI crashed writing its stage because the overlapped
block runner merges blocks narrower than the halo into their neighbours, and zarr cannot store
such blocks (tests/test_cache_chunks.py checks the cache's rechunk on synthetic arrays).  The
coverage stage's automatic blocks now split each axis equally, so a small AOI no longer meets
that layout by itself; here the coverage blocks are forced to one cell wider than the halo (the
last block of an axis then comes out thinner than the halo and is merged into its neighbour,
the layout of the crash), and the real Helsinki tactical scenario at 4 m cells (250 x 430) goes
through each command on a FRESH cache: ``maps``, ``coverage``, ``plan``, ``run``, ``fly`` and
``fleet`` exit 0, and every command that builds the coverage stage met stage outputs with
uneven blocks."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from skyroute.pipeline import cache as cache_mod
from skyroute.pipeline.cli import main

CATALOG = Path(__file__).resolve().parents[1] / "catalogs" / "scenarios"


def _scenario(tmp_path: Path) -> Path:
    sc = yaml.safe_load((CATALOG / "helsinki-tactical.yaml").read_text())
    sc["name"] = "uneven"
    sc["aoi"]["resolution_m"] = 4.0
    sc["gnss"]["window_min"] = 4        # fewer epochs: the chunking is what is tested
    for k, v in list(sc["data"].items()):          # the catalog's relative data paths, made absolute
        if isinstance(v, str) and v.startswith("../"):
            sc["data"][k] = str((CATALOG / v).resolve())
        elif isinstance(v, dict) and str(v.get("path", "")).startswith("../"):
            v["path"] = str((CATALOG / v["path"]).resolve())
        elif isinstance(v, list):
            sc["data"][k] = [str((CATALOG / x).resolve()) if str(x).startswith("../") else x for x in v]
    path = tmp_path / f"{sc['name']}.yaml"
    path.write_text(yaml.safe_dump(sc))
    return path


@pytest.fixture
def uneven_writes(monkeypatch):
    """The block layouts the cache had to rechunk for zarr (non-empty: some output was uneven),
    with the coverage stage's blocks one cell wider than its halo."""
    from skyroute.stages import coverage

    monkeypatch.setattr(coverage, "_auto_block_cells",
                        lambda shape, halo, *a, **k: (int(halo) + 1, int(halo) + 1))
    seen: list = []
    real = cache_mod.zarr_uniform_chunks

    def spy(chunks):
        out = real(chunks)
        if out is not None:
            seen.append(chunks)
        return out

    monkeypatch.setattr(cache_mod, "zarr_uniform_chunks", spy)
    return seen


COMMANDS = {
    "maps": ["maps"],
    "coverage": ["coverage"],
    "plan": ["plan"],
    "run": ["run", "--no-report"],
    "fly": ["fly"],
    "fleet": ["fleet", "--missions", "2", "--seed", "1"],
}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_each_command_on_uneven_overlapped_blocks(tmp_path, uneven_writes, command):
    sc = _scenario(tmp_path)
    args = [*COMMANDS[command][:1], str(sc), *COMMANDS[command][1:], "--cache-dir", str(tmp_path / "cache"), "-q"]
    if command != "maps":
        args += ["--out", str(tmp_path / "out")]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    if command != "maps":   # `maps` has no overlapped-block stage (clearance's halo is a few cells)
        assert uneven_writes, "no stage output came out with uneven blocks: the test does not test them"
