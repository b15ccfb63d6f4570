"""Rewriting an output folder never leaves a mix that `report` / `diff` accept (issues 27, 34): a
command writes into a staging folder put into place at its end, setting the folder's
summary.json aside while its files move and writing the new one last."""

from __future__ import annotations

import pytest

from skyroute.pipeline.errors import InputError
from skyroute.pipeline.outputs import (
    RETIRED_SUMMARY,
    ensure_writable_dir,
    previous_summary,
    write_summary,
)


def _first_run(out):
    out = ensure_writable_dir(out)
    (out / "candidates.csv").write_text("level,f\n0,1\n")
    (out / "plan.geojson").write_text("{}")
    write_summary(out, "plan", ["candidates.csv", "plan.geojson"], [], {})
    return out


def _readers():
    from skyroute.pipeline.diff import read_summary as diff_read
    from skyroute.pipeline.report import read_summary as report_read

    return report_read, diff_read


def test_a_commit_caught_half_way_is_refused_by_report_and_diff(tmp_path):
    """While a command puts its outputs into place (skyroute.pipeline.outfolder), the folder's
    summary.json is set aside: a folder caught in between (the process killed) is refused by
    report and diff until the command runs again."""
    out = _first_run(tmp_path / "X")
    report_read, diff_read = _readers()
    assert report_read(out)["command"] == "plan" and diff_read(out)["command"] == "plan"
    (out / "summary.json").replace(out / RETIRED_SUMMARY)      # the state of a commit killed half-way
    (out / "candidates.csv").write_text("level,f\n0,2\n")
    for read in _readers():
        with pytest.raises(InputError, match="did not finish"):
            read(out)
    # running the command again finishes the folder
    write_summary(out, "plan", ["candidates.csv", "plan.geojson"], [], {})
    assert all(read(out)["command"] == "plan" for read in _readers())


def test_the_api_writes_a_manifest_that_the_next_run_trusts(tmp_path):
    """Writing a folder from the Python API lists its files in the manifest, with checksums: a
    later rewrite removes its stale files, never a file that changed or that it did not write."""
    from skyroute.pipeline.outputs import remove_stale

    out = _first_run(tmp_path / "X")
    (out / "mine.txt").write_text("mine")
    prev = previous_summary(out)
    assert prev["files"] == [".skyroute-manifest.json", "candidates.csv", "plan.geojson", "summary.json"]
    (out / "candidates.csv").write_text("edited by hand\n")
    remove_stale(out, {**prev, "files": [*prev["files"], "mine.txt"]}, ["summary.json"], "plan")
    assert (out / "candidates.csv").is_file() and (out / "mine.txt").is_file()   # changed / not ours: kept
    assert not (out / "plan.geojson").exists()                                    # ours and stale: removed


def test_a_missing_listed_file_is_refused(tmp_path):
    out = _first_run(tmp_path / "X")
    (out / "plan.geojson").unlink()
    for read in _readers():
        with pytest.raises(InputError, match="plan.geojson, which is missing"):
            read(out)


def test_cli_read_only_and_empty_out_are_refused_before_work(tmp_path):
    import os

    from click.testing import CliRunner

    from skyroute.pipeline.cli import main

    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user that can write anywhere (root)")
        r = CliRunner().invoke(main, ["plan", "--out", str(ro / "x"), "--cache-dir", str(tmp_path / "c")])
        assert r.exit_code == 2 and r.output.startswith("error: cannot write to --out")
        assert not (tmp_path / "c").exists()
    finally:
        os.chmod(ro, 0o700)


def test_an_unusable_cache_is_one_error_before_any_stage(tmp_path):
    from click.testing import CliRunner

    from skyroute.pipeline.cli import main

    root = tmp_path / "c"
    (root / "stages").mkdir(parents=True)
    (root / "tmp").write_text("not a folder")          # as unusable as a read-only folder (tests run as root)
    r = CliRunner().invoke(main, ["plan", "--cache-dir", str(root), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and r.output.count("error:") == 1 and "cache" in r.output, r.output
    assert list((root / "stages").iterdir()) == []


def test_a_full_disk_is_one_error_line(tmp_path, monkeypatch):
    import errno

    from click.testing import CliRunner

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.cli import main

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.root / "tmp" / "x"))

    monkeypatch.setattr(Cache, "check_writable", full)
    r = CliRunner().invoke(main, ["plan", "--cache-dir", str(tmp_path / "c"), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and r.output.count("error:") == 1, r.output
    assert "No space left on device" in r.output and "Traceback" not in r.output


def test_an_interrupted_run_over_an_earlier_folder_keeps_it(tmp_path, monkeypatch):
    """The issue's reproduction end to end: a command interrupted while rewriting --out X
    leaves X as the earlier run wrote it (the new outputs were staged, never put into place):
    report and diff read it, and running again replaces it."""
    import json

    import yaml
    from click.testing import CliRunner

    import skyroute.pipeline.outputs as outputs
    from skyroute.pipeline.cli import main
    from skyroute.pipeline.settings import scenario_paths

    src = scenario_paths()["helsinki-medical"]
    raw = json.loads(json.dumps(yaml.safe_load(src.read_text()), default=str).replace(
        "../data/", str(src.parent.parent / "data") + "/"))
    (tmp_path / "H.yaml").write_text(yaml.safe_dump(raw))
    sc, out = str(tmp_path / "H.yaml"), tmp_path / "X"
    argv = ["run", sc, "--stage", "satellites", "--no-report", "--out", str(out), "--cache-dir", str(tmp_path / "c")]
    assert CliRunner().invoke(main, argv).exit_code == 0
    first = (out / "summary.json").read_bytes()
    real = outputs.write_run_outputs

    def interrupted(result, out_dir, **kw):
        (out_dir / "half-written.csv").write_text("x\n")
        raise KeyboardInterrupt

    monkeypatch.setattr(outputs, "write_run_outputs", interrupted)
    r = CliRunner().invoke(main, argv)
    assert r.exit_code == 130 and "interrupted" in r.output
    assert (out / "summary.json").read_bytes() == first and not (out / "half-written.csv").exists()
    for cmd in (["report", str(out)], ["diff", str(out), str(out)]):
        r = CliRunner().invoke(main, cmd)
        assert r.exit_code == 0, (cmd, r.output)
    monkeypatch.setattr(outputs, "write_run_outputs", real)
    assert CliRunner().invoke(main, argv).exit_code == 0
    assert CliRunner().invoke(main, ["report", str(out)]).exit_code == 0
