"""Outputs that cannot destroy (issue 34): an output never replaces a file the command reads,
only files skyroute wrote (its manifest, with their checksums) are ever replaced or removed,
never through a symbolic link, and a report embeds only its own PNGs.  The property "no input
makes a command delete or change a file it did not write" is checked over same-name inputs,
symbolic links and crafted manifests by comparing every file's checksum before and after."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.outfolder import MANIFEST_NAME
from skyroute.pipeline.settings import catalog_dir

sys.path.insert(0, str(Path(__file__).parent))
from _dem import dem_scenario, write_dem_window  # noqa: E402

DATA = catalog_dir() / "data"


@pytest.fixture(scope="module")
def dem_src(tmp_path_factory) -> Path:
    """The DEM of the README's bring-your-own-DEM example."""
    return write_dem_window(tmp_path_factory.mktemp("dem") / "dem.tif")


def _scenario(folder: Path, dem_src: Path, dem_name: str = "dem.tif") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(dem_src, folder / dem_name)
    shutil.copy(DATA / "yuma_2020-01-03.txt", folder / "yuma.txt")
    p = folder / "s.yaml"
    p.write_text(dem_scenario(dem_name))
    return p


def _run(args, cache: Path, cwd: Path | None = None):
    old = os.getcwd()
    try:
        if cwd is not None:
            os.chdir(cwd)
        return CliRunner().invoke(main, [*args, "--cache-dir", str(cache)])
    finally:
        os.chdir(old)


def _tree(root: Path) -> dict[str, str]:
    """Every file under ``root`` (links not followed) -> SHA-256 (a link: its target)."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for name in files + [d for d in dirs if os.path.islink(os.path.join(dirpath, d))]:
            p = Path(dirpath) / name
            rel = p.relative_to(root).as_posix()
            out[rel] = ("link:" + os.readlink(p)) if p.is_symlink() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _one_error(r) -> str:
    assert r.exit_code == 2, r.output
    assert r.output.count("error:") == 1 and "Traceback" not in r.output, r.output
    return r.output


SATS = ["run", "s.yaml", "--stage", "satellites", "--no-report", "-q"]


def test_a_dsm_named_like_an_output_is_never_overwritten(tmp_path, dem_src):
    """The issue's reproduction: data.terrain is ``surface.tif`` in the scenario's own folder and
    ``--out .``: refused before any work (exit 2), the user's file unchanged."""
    home = tmp_path / "proj"
    _scenario(home, dem_src, "surface.tif")
    before = _tree(home)
    r = _run(["run", "s.yaml", "--out", "."], tmp_path / "c", cwd=home)
    out = _one_error(r)
    assert "--out ." in out and ("not empty" in out or "input" in out)
    assert _tree(home) == before
    assert not (tmp_path / "c").exists() or not any((tmp_path / "c").rglob("*.zarr"))   # before any stage


def test_an_input_that_skyroute_wrote_in_out_is_refused(tmp_path, dem_src):
    """A skyroute-written surface.tif used as the next run's terrain, with the same --out: the
    run would replace its own input: refused, the file unchanged."""
    home = tmp_path / "proj"
    _scenario(home, dem_src)
    assert _run(["run", "s.yaml", "--stage", "surface", "--no-report", "-q", "--out", "out"], tmp_path / "c",
                cwd=home).exit_code == 0
    assert (home / "out" / "surface.tif").is_file()
    (home / "t.yaml").write_text(dem_scenario("out/surface.tif"))
    before = _tree(home / "out")
    r = _run(["run", "t.yaml", "--stage", "satellites", "--no-report", "--out", "out"], tmp_path / "c", cwd=home)
    out = _one_error(r)
    assert "surface.tif" in out and "input" in out
    assert _tree(home / "out") == before
    # a hard link of the input under an output's name is the same file: refused too
    (home / "out" / "surface.tif").unlink()
    os.link(home / "dem.tif", home / "out" / "surface.tif")
    dem = _tree(home)["dem.tif"]
    r = _run(["run", "s.yaml", "--stage", "surface", "--no-report", "--out", "out"], tmp_path / "c", cwd=home)
    assert "surface.tif" in _one_error(r)
    assert _tree(home)["dem.tif"] == dem and (home / "out" / "surface.tif").stat().st_nlink == 2


def test_a_crafted_summary_is_no_licence_to_delete(tmp_path, dem_src):
    """``crafted/summary.json`` (hand-written) lists mydata.csv, .hidden and sub/precious.txt
    with ``sub`` a link to another folder: a command writing into ``crafted`` deletes none of
    them (refused: skyroute did not write the folder), and nothing outside is touched."""
    home = tmp_path / "proj"
    _scenario(home, dem_src)
    crafted, other = home / "crafted", tmp_path / "other"
    crafted.mkdir()
    other.mkdir()
    (crafted / "mydata.csv").write_text("a,b\n1,2\n")
    (crafted / ".hidden").write_text("secret")
    (other / "precious.txt").write_text("precious")
    os.symlink(other, crafted / "sub")
    (crafted / "summary.json").write_text(json.dumps({
        "schema_version": 3, "command": "run", "warnings": [],
        "files": ["mydata.csv", ".hidden", "sub/precious.txt", "summary.json"]}))
    before, before_other = _tree(crafted), _tree(other)
    out = _one_error(_run([*SATS, "--out", "crafted"], tmp_path / "c", cwd=home))
    assert "skyroute did not write" in out
    assert _tree(crafted) == before and _tree(other) == before_other


def test_a_crafted_manifest_deletes_nothing_it_does_not_own(tmp_path, dem_src):
    """In a real skyroute folder, a hand-edited summary and manifest that claim a user's files
    (with a wrong checksum, or reached through a link with the right one) never remove them."""
    home = tmp_path / "proj"
    _scenario(home, dem_src)
    out, other = home / "out", tmp_path / "other"
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0
    other.mkdir()
    (other / "precious.txt").write_text("precious")
    os.symlink(other, out / "sub")
    (out / "mydata.csv").write_text("mine\n")
    doc = json.loads((out / "summary.json").read_text())
    doc["files"] += ["mydata.csv", "sub/precious.txt"]
    (out / "summary.json").write_text(json.dumps(doc))     # hand-edited: no longer skyroute's
    man = json.loads((out / MANIFEST_NAME).read_text())
    sha = hashlib.sha256(b"precious").hexdigest()
    man["entries"]["mydata.csv"] = {"kind": "file", "size": 5, "sha256": "0" * 64}
    man["entries"]["sub/precious.txt"] = {"kind": "file", "size": 8, "sha256": sha}
    (out / MANIFEST_NAME).write_text(json.dumps(man))
    keep_other = _tree(other)
    r = _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home)
    text = _one_error(r)                                 # the edited summary.json is not skyroute's any more
    assert "summary.json" in text
    (out / "summary.json").unlink()                       # the user removes it: the run goes on
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0
    assert (out / "mydata.csv").read_text() == "mine\n"
    assert _tree(other) == keep_other and (out / "sub").is_symlink()


def test_a_rerun_replaces_only_its_own_files_and_keeps_the_rest(tmp_path, dem_src):
    """A second run into the folder: the user's own file beside the outputs survives, a reused
    store stays the same file (kept in place), the stale files of the first run go, and an
    output through a link to a folder outside is never written."""
    home = tmp_path / "proj"
    _scenario(home, dem_src)
    out = home / "out"
    assert _run(["run", "s.yaml", "--stage", "surface", "--no-report", "-q", "--out", "out"], tmp_path / "c",
                cwd=home).exit_code == 0
    assert (out / "surface.tif").is_file() and (out / "datasets" / "surface.zarr").is_dir()
    (out / "notes.txt").write_text("my notes")
    ino = (out / "datasets" / "surface.zarr" / "zarr.json").stat().st_ino
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0
    assert (out / "notes.txt").read_text() == "my notes"
    assert not (out / "surface.tif").exists()            # stale: written by the first run, not this one
    assert (out / "datasets" / "satellites.zarr").is_dir() and not (out / "datasets" / "surface.zarr").exists()
    assert json.loads((out / "summary.json").read_text())["files"] == sorted(
        json.loads((out / "summary.json").read_text())["files"])
    # warm: the same store is kept (same inode), not copied again
    ino = (out / "datasets" / "satellites.zarr" / "zarr.json").stat().st_ino
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0
    assert (out / "datasets" / "satellites.zarr" / "zarr.json").stat().st_ino == ino
    # a figures/ folder that is a link out of --out: the run refuses, nothing written through it
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.rmtree(out / "figures", ignore_errors=True)
    os.symlink(elsewhere, out / "figures")
    _one_error(_run([*SATS, "--out", "out"], tmp_path / "c", cwd=home))
    assert list(elsewhere.iterdir()) == []


def test_a_foreign_file_in_the_way_keeps_it_and_the_new_outputs(tmp_path, dem_src):
    """A file the user put where the run writes (found only at the end) is not replaced: the
    folder stays as it was, the new outputs wait in a folder the error names."""
    from skyroute.pipeline import outfolder

    home = tmp_path / "proj"
    _scenario(home, dem_src)
    out = home / "out"
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0
    (out / "datasets" / "extra.txt").write_text("mine")
    real = outfolder.OutFolder._units

    def more(self):
        (Path(self.path) / "datasets" / "extra.txt").write_text("skyroute's")
        return real(self)

    before = _tree(out)
    try:
        outfolder.OutFolder._units = more
        text = _one_error(_run([*SATS, "--out", "out"], tmp_path / "c", cwd=home))
    finally:
        outfolder.OutFolder._units = real
    assert "datasets/extra.txt" in text and outfolder.UNPLACED_PREFIX in text
    unplaced = [p for p in out.iterdir() if p.name.startswith(outfolder.UNPLACED_PREFIX)]
    assert len(unplaced) == 1 and (unplaced[0] / "summary.json").is_file()
    assert {k: v for k, v in _tree(out).items() if not k.startswith(outfolder.UNPLACED_PREFIX)} == before


def test_an_interrupted_run_leaves_the_folder_as_it_was(tmp_path, dem_src, monkeypatch):
    """Outputs go into a fresh folder put into place at the end: a run interrupted while writing
    leaves --out exactly as the previous run left it (report still reads it), and no staging
    folder behind."""
    import skyroute.pipeline.outputs as outputs

    home = tmp_path / "proj"
    _scenario(home, dem_src)
    out = home / "out"
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0
    before = _tree(out)

    def interrupted(result, out_dir, **kw):
        (Path(out_dir) / "half-written.csv").write_text("x\n")
        raise KeyboardInterrupt

    monkeypatch.setattr(outputs, "write_run_outputs", interrupted)
    r = _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home)
    assert r.exit_code == 130 and "interrupted" in r.output
    assert _tree(out) == before and sorted(os.listdir(out)) == sorted(os.listdir(out))
    assert not [p for p in out.iterdir() if "staging" in p.name]
    # a first run interrupted leaves no folder at all
    r = _run([*SATS, "--out", "new"], tmp_path / "c", cwd=home)
    assert r.exit_code == 130 and not (home / "new").exists()
    assert not [p for p in home.iterdir() if "staging" in p.name]


def test_out_with_a_control_character_is_one_error(tmp_path, dem_src):
    home = tmp_path / "proj"
    _scenario(home, dem_src)
    text = _one_error(_run([*SATS, "--out", "bad\nname"], tmp_path / "c", cwd=home))
    assert "control character" in text and not (home / "bad\nname").exists()


def test_report_embeds_only_its_own_pngs(tmp_path, dem_src):
    """``figures/*.png`` links to another file (a secret) and a non-PNG named .png are never
    put into report.html; the real figures are."""
    home = tmp_path / "proj"
    _scenario(home, dem_src)
    out = home / "out"
    assert _run(["run", "s.yaml", "--stage", "surface", "--no-report", "-q", "--out", "out"], tmp_path / "c",
                cwd=home).exit_code == 0
    secret = tmp_path / "secret.png"
    secret.write_bytes(b"\x89PNG\r\n\x1a\n" + b"TOP-SECRET-BYTES" * 8)
    os.symlink(secret, out / "figures" / "coverage_evil.png")
    (out / "figures" / "coverage_text.png").write_text("not a png " * 20)
    r = _run(["report", "out"], tmp_path / "c", cwd=home)
    assert r.exit_code == 0, r.output
    import base64

    html = (out / "report.html").read_text()
    assert base64.b64encode(secret.read_bytes()).decode()[:40] not in html
    assert base64.b64encode(b"not a png " * 20).decode()[:40] not in html
    assert "surface.png" in html                     # the real figure is there
    # the page and the summary it updated are skyroute's: the next run may replace them
    from skyroute.pipeline.outfolder import owned_by_skyroute

    assert owned_by_skyroute(out / "report.html") and owned_by_skyroute(out / "summary.json")
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0


def test_cache_clear_while_another_command_reads_the_cache_is_refused(tmp_path):
    """``skyroute cache clear`` during a run (another process holding the cache) used to pull its
    entries away: a lazily read chunk then reads as NaN, a group as a traceback.  It is refused
    with one error line, and works once the other process ended."""
    import subprocess
    import sys

    from skyroute.pipeline.cache import Cache

    root = tmp_path / "c"
    (root / "stages").mkdir(parents=True)
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from pathlib import Path; from skyroute.pipeline.cache import hold_shared; "
        f"hold_shared(Path({str(root)!r})); print('held', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        r = CliRunner().invoke(main, ["cache", "clear", "--cache-dir", str(root)])
        text = _one_error(r)
        assert "in use" in text and (root / "stages").is_dir()
        r = CliRunner().invoke(main, ["cache", "prune", "--max-size", "0", "--cache-dir", str(root)])
        assert "in use" in _one_error(r)
    finally:
        holder.kill()
        holder.wait()
    assert CliRunner().invoke(main, ["cache", "clear", "--cache-dir", str(root)]).exit_code == 0
    # this process's own hold does not stop its own clear (a notebook clearing its cache)
    Cache(root).get("x", "y")
    assert CliRunner().invoke(main, ["cache", "clear", "--cache-dir", str(root)]).exit_code == 0


# ------------------------------------------------------------------ property: nothing not ours changes
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

NAMES = ["summary.json", "surface.tif", "report.html", "figures", "figures/surface.png", "datasets",
         "datasets/x.zarr", "datasets/x.zarr/zarr.json", "plan", "plan/plan.geojson", "mydata.csv", ".hidden",
         "sub", "sub/precious.txt", MANIFEST_NAME]
KINDS = ["file", "link-out-file", "link-out-dir", "hardlink-input", "dir", "crafted-manifest", "crafted-summary"]


@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(layout=st.lists(st.tuples(st.sampled_from(NAMES), st.sampled_from(KINDS)), max_size=6),
       written=st.lists(st.sampled_from([n for n in NAMES if n != MANIFEST_NAME]), min_size=1, max_size=5),
       first=st.booleans())
@example(layout=[("mydata.csv", "file")], written=["mydata.csv"], first=True)      # found only at the commit
@example(layout=[("sub", "link-out-dir")], written=["sub/precious.txt"], first=True)
@example(layout=[("plan", "hardlink-input")], written=["plan"], first=True)
def test_no_folder_makes_a_commit_change_a_file_it_did_not_write(tmp_path_factory, layout, written, first):
    """Over random --out folders (user files, links out of the folder, hard links of an input,
    crafted manifests and summaries) and random sets of output names: a command's commit (or its
    refusal) never changes or removes a file skyroute did not write, inside or outside --out, and
    never writes through a link."""
    from skyroute.pipeline import outfolder
    from skyroute.pipeline.errors import InputError
    from skyroute.stages.base import forget_inputs, note_input

    root = tmp_path_factory.mktemp("prop")
    out, outside = root / "out", root / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("secret")
    (outside / "d").mkdir()
    (outside / "d" / "precious.txt").write_text("precious")
    inp = root / "input.tif"
    inp.write_bytes(b"input-bytes")
    forget_inputs()
    note_input(inp)
    if first:          # a folder skyroute wrote before: its files are skyroute's
        f = outfolder.open_output_folder(out, "run")
        (f.path / "summary.json").write_text("{}")
        (f.path / "surface.tif").write_bytes(b"old")
        outfolder.commit_all()
    out.mkdir(exist_ok=True)
    for name, kind in layout:
        p = out / name
        if os.path.lexists(p) or not p.parent.is_dir() or p.parent.is_symlink():
            continue
        if kind == "file":
            p.write_text(f"user {name}")
        elif kind == "link-out-file":
            os.symlink(outside / "secret.txt", p)
        elif kind == "link-out-dir":
            os.symlink(outside / "d", p)
        elif kind == "hardlink-input":
            os.link(inp, p)
        elif kind == "dir":
            p.mkdir()
        elif kind == "crafted-manifest":
            (out / MANIFEST_NAME).write_text(json.dumps({"schema": 1, "command": "run", "entries": {
                n: {"kind": "file", "size": 6, "sha256": hashlib.sha256(b"secret").hexdigest()} for n in NAMES}}))
        elif kind == "crafted-summary":
            (out / "summary.json").write_text(json.dumps({"command": "run", "files": NAMES}))
    owned = {rel for rel in _tree(out) if outfolder.owned_by_skyroute(out / rel, out)}
    before, before_out = _tree(out), _tree(outside)
    inp_before = inp.read_bytes()
    try:
        f = outfolder.open_output_folder(out, "run")
        for name in written:       # a writer: a name whose folder is a file is skipped
            p = f.path / name
            try:
                if name.endswith(".zarr"):
                    p.mkdir(parents=True, exist_ok=True)
                    (p / "zarr.json").write_text("{}")
                elif not p.exists():
                    p.parent.mkdir(parents=True, exist_ok=True)
                    p.write_text(f"new {name}")
            except OSError:
                continue
        outfolder.commit_all()
    except InputError:
        pass
    finally:
        outfolder.discard_all()
    after = _tree(out)
    assert _tree(outside) == before_out and inp.read_bytes() == inp_before
    for rel, digest in before.items():
        if rel in owned or rel == MANIFEST_NAME or rel.startswith(outfolder.UNPLACED_PREFIX):
            continue
        assert after.get(rel) == digest, (rel, layout, written)
    assert not [n for n in os.listdir(out) if outfolder.STAGING_MARK in n or outfolder.TRASH_MARK in n]


def test_single_file_outputs_never_replace_an_input_or_a_users_file(tmp_path, dem_src):
    """``visibility-height --out`` and ``report --out`` write one file: never the surface the
    command reads, never a file skyroute did not write, never through a link; their own earlier
    file is replaced."""
    home = tmp_path / "proj"
    _scenario(home, dem_src)
    dem = _tree(home)["dem.tif"]
    vh = ["visibility-height", "--surface", "dem.tif", "--az-deg", "10", "--el-deg", "30", "--out"]
    text = _one_error(_run_plain([*vh, "dem.tif"], home))
    assert "dem.tif" in text and _tree(home)["dem.tif"] == dem
    (home / "mine.tif").write_bytes(b"mine")
    os.symlink(home / "dem.tif", home / "link.tif")
    for name in ("mine.tif", "link.tif"):
        _one_error(_run_plain([*vh, name], home))
    assert (home / "mine.tif").read_bytes() == b"mine" and _tree(home)["dem.tif"] == dem
    assert _run_plain([*vh, "vh.tif"], home).exit_code == 0
    assert _run_plain([*vh, "vh.tif"], home).exit_code == 0      # its own file: replaced
    # report --out onto a user's page: refused
    assert _run([*SATS, "--out", "out"], tmp_path / "c", cwd=home).exit_code == 0
    (home / "page.html").write_text("<p>mine</p>")
    _one_error(_run(["report", "out", "--out", "page.html"], tmp_path / "c", cwd=home))
    assert (home / "page.html").read_text() == "<p>mine</p>"
    for _ in range(2):
        assert _run(["report", "out", "--out", "mine.html"], tmp_path / "c", cwd=home).exit_code == 0


def _run_plain(args, cwd: Path):
    old = os.getcwd()
    try:
        os.chdir(cwd)
        return CliRunner().invoke(main, args)
    finally:
        os.chdir(old)
