from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
CATALOG_DATA = REPO / "catalogs" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The project's real-data folder (../shared/data); skip when it is absent (fresh installs)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} not present")
    return SHARED_DATA


@pytest.fixture
def cache(tmp_path):
    from skyroute.pipeline.cache import Cache

    return Cache(tmp_path / "cache")


@pytest.fixture(scope="session")
def helsinki():
    from skyroute.pipeline.settings import load_scenario

    return load_scenario("helsinki-medical")


@pytest.fixture(scope="session")
def helsinki_surface(helsinki, tmp_path_factory):
    """The default scenario's surface model (computed once per session)."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario

    res = run_scenario(helsinki, cache=Cache(tmp_path_factory.mktemp("cache")), targets=["surface"])
    return res["surface"].load()


@pytest.fixture(autouse=True)
def _no_clipped_text_in_saved_figures(monkeypatch):
    """Every figure a test makes skyroute save is checked: no title, label, tick label or legend
    text may be cut off by the canvas (skyroute.stages.figures.clipped_texts)."""
    import matplotlib.figure

    from skyroute.stages.figures import clipped_texts

    real = matplotlib.figure.Figure.savefig

    def savefig(self, *args, **kwargs):
        cut = clipped_texts(self)
        assert not cut, f"figure text cut off by the canvas: {', '.join(cut)}"
        return real(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
