"""The stage graph: registry, cache keys and the runner.

Every stage has one signature::

    func(*inputs: xr.Dataset, settings: S) -> xr.Dataset

where ``inputs`` are the outputs of the stages it names (in order) and ``settings`` is a frozen
object chosen from the scenario by the stage's ``select`` function.  The returned Dataset may be
lazy (dask); the runner writes it to the zarr cache with the chosen dask scheduler (that is where
the heavy graph executes, chunk by chunk, with a progress bar) and hands the *cached* dataset,
opened lazily, to the stages that depend on it.

Cache key of a stage = stable hash of (stage name, code version, settings, keys of its inputs);
the code version hashes the source of the stage function and its settings selector and of every
``skyroute`` module in their import closure (:func:`code_closure`: imports at any depth, inside
function bodies too, found by reading the sources with :mod:`ast`, never by importing them), so
editing any code a stage runs recomputes it and its dependants only.
"""

from __future__ import annotations

import ast
import contextlib
import functools
import gc
import hashlib
import importlib
import importlib.util
import inspect
import json
import logging
import os
import time
import warnings
from collections.abc import Callable, Iterator, MutableMapping, Sequence
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

from skyroute.pipeline import control
from skyroute.pipeline.cache import Cache, CacheEntry
from skyroute.pipeline.errors import InputError, UnknownNameError
from skyroute.pipeline.model import stable_hash
from skyroute.pipeline.progress import stage_phases
from skyroute.pipeline.settings import Scenario

# dask and xarray are imported where a stage computes or a dataset is read: a warm run that
# reads no dataset imports neither
if TYPE_CHECKING:
    import xarray as xr

log = logging.getLogger("skyroute.pipeline")

try:
    SKYROUTE_VERSION = version("skyroute")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    SKYROUTE_VERSION = "0+unknown"


@dataclass(frozen=True)
class Stage:
    """A pipeline stage (see module docstring)."""

    name: str
    func: Callable[..., xr.Dataset]
    select: Callable[[Scenario], Any]
    inputs: tuple[str, ...] = ()
    optional_inputs: tuple[str, ...] = ()  # passed as None when that stage does not apply
    applies: Callable[[Scenario], bool] = lambda sc: True
    code_modules: tuple[str, ...] = ()
    version: str = "1"
    description: str = ""
    # cheap check of the stage's settings against early outputs, run as soon as the stages of
    # ``precheck_after`` that run have finished (before the long ones): fail fast on bad input
    precheck: Callable[[Scenario, dict[str, xr.Dataset]], None] | None = None
    precheck_after: tuple[str, ...] = ()

    def code_version(self) -> str:
        """Hash of the stage function's and selector's source and of every ``skyroute`` module
        they (transitively) import; ``code_modules`` adds modules reached only dynamically."""
        return code_version_of(self.func, self.select, modules=self.code_modules, salt=f"{self.name}:{self.version}")


def code_version_of(*fns: Callable[..., Any], modules: Sequence[str] = (), salt: str = "") -> str:
    """Hash of the source of ``fns`` and of every ``skyroute`` module they (transitively)
    import, plus ``modules`` (and theirs): the code part of a cache key (:meth:`Stage.code_version`)."""
    h = hashlib.sha256(salt.encode())
    mods: set[str] = set(modules)
    for fn in fns:
        src, mods_fn = _function_imports(fn)
        h.update(src.encode())
        mods |= mods_fn
    for m in sorted(code_closure(mods)):
        h.update(m.encode())
        h.update(_module_source(m) or SKYROUTE_VERSION.encode())
    return h.hexdigest()[:16]


_PACKAGE = "skyroute"


@functools.cache
def _package_dirs(name: str) -> tuple[str, ...]:
    """Search folders of the package ``name`` (empty when it is not a package), found without
    importing anything below the top-level ``skyroute.*`` packages (whose ``__init__`` is light)."""
    parent, _, last = name.rpartition(".")
    if parent in ("", _PACKAGE):
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            return ()
        return tuple(spec.submodule_search_locations or ()) if spec is not None else ()
    out = []
    for loc in _package_dirs(parent):
        if os.path.isfile(os.path.join(loc, last, "__init__.py")):
            out.append(os.path.join(loc, last))
    return tuple(out)


@functools.cache
def _module_file(name: str) -> str | None:
    """Path of a ``skyroute`` module's source, found without importing it (a cache hit needs no
    heavy imports)."""
    parent, _, last = name.rpartition(".")
    if parent in ("", _PACKAGE):
        dirs = _package_dirs(name)
        init = os.path.join(dirs[0], "__init__.py") if dirs else None
        return init if init and os.path.isfile(init) else None
    for loc in _package_dirs(parent):
        for cand in (os.path.join(loc, last + ".py"), os.path.join(loc, last, "__init__.py")):
            if os.path.isfile(cand):
                return cand
    return None


def _module_source(name: str) -> bytes | None:
    path = _module_file(name)
    if path is None:
        return None
    with open(path, "rb") as f:
        return f.read()


def _raw_imports(tree: ast.AST, module: str, is_package: bool) -> list[tuple[str, tuple[str, ...]]]:
    """``(module, names)`` of every ``skyroute`` import anywhere in ``tree`` (``import a.b``:
    ``("a.b", ())``; ``from a import x, y``: ``("a", ("x", "y"))``; relative imports resolved
    against ``module``)."""
    out: list[tuple[str, tuple[str, ...]]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, ()) for a in node.names if a.name.split(".")[0] == _PACKAGE]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".")
                parts = parts if is_package else parts[:-1]
                parts = parts[:len(parts) - (node.level - 1)]
                base = ".".join([*parts, *([base] if base else [])])
            if base.split(".")[0] == _PACKAGE:
                out.append((base, tuple(a.name for a in node.names)))
    return out


def _resolve(raw: Sequence[tuple[str, Sequence[str]]]) -> set[str]:
    """The modules of :func:`_raw_imports`' pairs (``from pkg import sub`` counts ``sub`` when it
    is a module)."""
    out: set[str] = set()
    for base, names in raw:
        out.add(base)
        out |= {f"{base}.{n}" for n in names if _module_file(f"{base}.{n}")}
    return out


def _imports_in(tree: ast.AST, module: str, is_package: bool) -> set[str]:
    """``skyroute`` modules imported anywhere in ``tree`` (``from pkg import sub`` counts ``sub``
    when it is a module; relative imports resolved against ``module``)."""
    return _resolve(_raw_imports(tree, module, is_package))


# Parsing every module of a closure costs about a second: the raw imports of each source text
# are memoised by its SHA-256 in ``<cache root>/code_imports.json`` (a warm run parses nothing;
# an edited module has a new digest, so it is parsed again).
_IMPORT_MEMO: dict[str, list] = {}
_IMPORT_MEMO_STATE: dict[str, Any] = {"path": None, "dirty": False}


def _import_memo_path() -> str:
    env = os.environ.get("SKYROUTE_CACHE_DIR")
    root = os.path.expanduser(env) if env else os.path.join(os.path.expanduser("~"), ".cache", "skyroute")
    return os.path.join(root, "code_imports.json")


def _load_import_memo() -> None:
    path = _import_memo_path()
    if _IMPORT_MEMO_STATE["path"] == path:
        return
    _IMPORT_MEMO_STATE["path"] = path
    try:
        with open(path, encoding="utf-8") as f:
            memo = json.load(f)
        if isinstance(memo, dict):
            _IMPORT_MEMO.update(memo)
    except (OSError, ValueError):
        pass


def _save_import_memo() -> None:
    if not _IMPORT_MEMO_STATE["dirty"]:
        return
    _IMPORT_MEMO_STATE["dirty"] = False
    path = _import_memo_path()
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(_IMPORT_MEMO, f)
        os.replace(tmp, path)  # atomic: a reader sees the old or the new memo, never half of one
    except OSError:
        pass  # a read-only cache folder only costs parsing again


@functools.cache
def _module_imports(name: str) -> frozenset[str]:
    """The ``skyroute`` modules one module imports (read once per process; parsed only when its
    source is not in the import memo)."""
    path = _module_file(name)
    if path is None:
        return frozenset()
    with open(path, "rb") as f:
        src = f.read()
    if b"skyroute" not in src and b"from ." not in src:
        return frozenset()
    is_package = path.endswith("__init__.py")
    memo_key = f"{name}|{int(is_package)}|{hashlib.sha256(src).hexdigest()}"
    _load_import_memo()
    raw = _IMPORT_MEMO.get(memo_key)
    if not isinstance(raw, list):
        raw = [[b, list(n)] for b, n in _raw_imports(ast.parse(src, filename=path), name, is_package)]
        for k in [k for k in _IMPORT_MEMO if k.startswith(f"{name}|")]:
            del _IMPORT_MEMO[k]  # one version per module: the memo does not grow with every edit
        _IMPORT_MEMO[memo_key] = raw
        _IMPORT_MEMO_STATE["dirty"] = True
    return frozenset(_resolve(raw))


def code_closure(modules: set[str] | Sequence[str]) -> set[str]:
    """Every ``skyroute`` module reachable from ``modules`` by imports (any depth, function
    bodies included), read from the sources with :mod:`ast`."""
    seen: set[str] = set()
    todo = [m for m in modules if m.split(".")[0] == _PACKAGE]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(_module_imports(m) - seen)
    _save_import_memo()
    return {m for m in seen if _module_file(m) is not None}


def _function_imports(fn: Callable[..., Any]) -> tuple[str, set[str]]:
    """(source of ``fn``, the ``skyroute`` modules it uses): imports inside its body, and the
    names it reads that its module bound by a top-level ``skyroute`` import."""
    try:
        src = inspect.getsource(fn)
    except (OSError, TypeError):  # pragma: no cover - built without sources
        return repr(fn), set()
    mod = inspect.getmodule(fn)
    modname = mod.__name__ if mod else ""
    tree = ast.parse(inspect.cleandoc("\n" + src) if src[:1].isspace() else src)
    used = _imports_in(tree, modname, False)
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    if mod is not None:
        for name in names:
            obj = getattr(mod, name, None)
            owner = obj.__name__ if inspect.ismodule(obj) else getattr(obj, "__module__", None)
            if isinstance(owner, str) and owner.split(".")[0] == _PACKAGE and owner != modname:
                used.add(owner)
    return src, used


REGISTRY: dict[str, Stage] = {}


def register(stage: Stage) -> Stage:
    REGISTRY[stage.name] = stage
    return stage


def _load_registry() -> None:
    # importing the module registers the built-in stages
    importlib.import_module("skyroute.pipeline.stages_builtin")


def stages_for(scenario: Scenario, targets: Sequence[str] | None = None) -> list[Stage]:
    """The stages that apply to ``scenario`` in dependency order (only those needed for
    ``targets`` when given)."""
    _load_registry()
    if targets:
        for t in targets:
            if t not in REGISTRY:
                raise UnknownNameError("stage", t, list(REGISTRY))
    order: list[Stage] = []
    seen: set[str] = set()

    def visit(name: str, stack: tuple[str, ...] = ()) -> None:
        if name in seen:
            return
        if name in stack:
            raise InputError(f"stage graph has a cycle: {' -> '.join(stack + (name,))}")
        st = REGISTRY[name]
        for dep in (*st.inputs, *st.optional_inputs):
            visit(dep, stack + (name,))
        seen.add(name)
        order.append(st)

    for name in (targets or list(REGISTRY)):
        visit(name)
    applicable = {s.name for s in order if s.applies(scenario)}
    # a stage runs only if it and all its inputs apply
    out = []
    for s in order:
        if s.name in applicable and all(d in {o.name for o in out} for d in s.inputs):
            out.append(s)
    if targets:
        missing = [t for t in targets if t not in {s.name for s in out}]
        if missing:
            raise InputError(f"stage(s) {', '.join(missing)} do not apply to scenario {scenario.name!r} "
                             "(missing data sources, e.g. data.almanacs for GNSS stages)")
    return out


# --------------------------------------------------------------------------- schedulers
LOCAL_SCHEDULERS = ("threads", "processes", "synchronous", "sync")


PROBE_TIMEOUT_S = 5.0        # [s] connecting to a --scheduler address and reading its greeting
PROBE_MAX_GREETING = 1 << 16  # [bytes] a dask scheduler's handshake is ~60 bytes


def check_scheduler_address(address: str, timeout_s: float | None = None) -> None:
    """InputError (one line) unless ``address`` (``tcp://HOST:PORT``) answers like a dask
    scheduler, checked with a plain socket before dask sees it: dask's own handshake reads the
    first 8 bytes as the length of a message and allocates it (3 EiB from an HTTP server's
    bytes), and a server that never answers would make dask wait.  A scheduler sends its
    handshake when a connection opens: 8 bytes (the length of the rest, native uint64), a
    frame header and a msgpack map with the keys ``compression``, ``python`` and
    ``pickle-protocol``.  At most :data:`PROBE_MAX_GREETING` bytes are read, within
    ``timeout_s`` [s] (default :data:`PROBE_TIMEOUT_S`) in all.  Other schemes (``tls://``,
    ``inproc://``) are left to dask."""
    import socket
    import struct

    if not address.startswith("tcp://"):
        return
    timeout_s = PROBE_TIMEOUT_S if timeout_s is None else float(timeout_s)
    fix = "start one with `dask scheduler` (it prints its tcp:// address) or drop --scheduler"
    hostport = address[len("tcp://"):].rstrip("/")
    host, sep, port_s = hostport.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port_s.isdigit() or not 0 < int(port_s) < 65536:
        raise InputError(f"--scheduler {address!r} is not a dask scheduler address; give tcp://HOST:PORT "
                         f"(e.g. tcp://127.0.0.1:8786): {fix}")
    deadline = time.monotonic() + timeout_s

    def recv_exactly(sock, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            sock.settimeout(left)
            b = sock.recv(n - len(buf))
            if not b:
                raise ValueError("the server closed the connection without a dask handshake")
            buf += b
        return buf

    try:
        with socket.create_connection((host, int(port_s)), timeout=timeout_s) as sock:
            (n,) = struct.unpack("Q", recv_exactly(sock, 8))
            if not 16 <= n <= PROBE_MAX_GREETING:
                raise ValueError(f"its first bytes announce a message of {n:,} bytes")
            body = recv_exactly(sock, n)
            if not all(k in body for k in (b"compression", b"python", b"pickle-protocol")):
                raise ValueError("its greeting is not a dask handshake")
    except TimeoutError:
        raise InputError(f"--scheduler {address}: no dask handshake within {timeout_s:g} s (the server accepts "
                         f"connections but does not answer like a dask scheduler): {fix}") from None
    except ValueError as exc:
        raise InputError(f"--scheduler {address} is not a dask scheduler ({exc}): {fix}") from None
    except OSError as exc:
        raise InputError(f"cannot connect to the dask scheduler at {address}: {exc.strerror or exc}; {fix}") from None


@contextlib.contextmanager
def scheduler_context(scheduler: str = "threads", workers: int | None = None) -> Iterator[Any]:
    """Configure dask for ``scheduler``: ``threads`` (default), ``processes``, ``synchronous``,
    ``distributed`` (a new LocalCluster of ``workers`` processes) or ``tcp://host:port``."""
    if scheduler in LOCAL_SCHEDULERS:
        import dask

        kw = {"num_workers": workers} if workers else {}
        with dask.config.set(scheduler=scheduler, **kw):
            yield None
    elif scheduler == "distributed" or scheduler.startswith(("tcp://", "tls://", "inproc://")):
        from distributed import Client, LocalCluster

        if scheduler == "distributed":
            cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
            client = Client(cluster)
        else:
            cluster = None
            check_scheduler_address(scheduler)     # not a dask scheduler: one line, never a 3 EiB read
            try:
                client = Client(scheduler, timeout="10s")
            except OSError as exc:
                raise InputError(f"cannot connect to the dask scheduler at {scheduler}: {exc}; "
                                 "start one with `dask scheduler` or use --scheduler distributed") from exc
        import logging

        log = logging.getLogger("asyncio")
        if not any(isinstance(f, _DroppedWaits) for f in log.filters):
            log.addFilter(_DroppedWaits())     # for the process: the dropped task may be collected later
        try:
            yield client
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    else:
        raise UnknownNameError("scheduler", scheduler,
                               ["threads", "processes", "synchronous", "distributed", "tcp://host:port"])


class _DroppedWaits:
    """A filter of the ``asyncio`` logger: the ``AllExit`` of a ``fut.result(timeout=...)``
    wait that :func:`cluster_result` gave up on (the client closing ends it) is not a problem,
    and its "Task exception was never retrieved" traceback must not precede the command's one
    ``error:`` line."""

    def filter(self, record) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        text = record.getMessage() if exc is None else ""
        return not (type(exc).__name__ == "AllExit" or "AllExit" in text)


@contextlib.contextmanager
def _check_scheduler(scheduler: str) -> Iterator[None]:
    """A local ``scheduler`` name checked, nothing configured (no stage computes)."""
    if scheduler not in LOCAL_SCHEDULERS:   # pragma: no cover - run_pipeline connects to clusters
        raise UnknownNameError("scheduler", scheduler, list(LOCAL_SCHEDULERS))
    yield None


WORKER_LOSS_S = 20.0   # with no worker left for this long, a distributed command fails (never hangs)


def cluster_result(client: Any, fut: Any, what: str = "the computation", poll_s: float = 2.0,
                   worker_loss_s: float | None = None) -> Any:
    """``fut.result()`` of a distributed future that fails loudly: a :class:`ClusterError` once
    the cluster has had no worker for ``worker_loss_s`` [s] (default :data:`WORKER_LOSS_S`), or
    its scheduler is gone, instead of waiting forever; a lost worker among others is survived
    (dask re-runs its tasks)."""
    from distributed import TimeoutError as DTimeout

    from skyroute.stages.base import ClusterError

    limit = WORKER_LOSS_S if worker_loss_s is None else float(worker_loss_s)
    empty_since = None
    while True:
        control.check()
        try:
            return fut.result(timeout=poll_s)
        except (DTimeout, TimeoutError):
            pass
        try:
            n = len(client.scheduler_info().get("workers", {}))
        except Exception as exc:           # the scheduler itself is unreachable
            raise ClusterError(f"{what}: lost the dask scheduler ({exc}); restart it and the workers, or run "
                               "without --scheduler") from None
        if n:
            empty_since = None
            continue
        now = time.monotonic()
        empty_since = empty_since or now
        if now - empty_since >= limit:
            raise ClusterError(f"{what}: every dask worker was lost (none for {limit:g} s); restart the workers "
                               "(`dask worker ADDRESS`) or run without --scheduler")


def _computer(client: Any, progress: bool) -> Callable[[Any], Any]:
    def compute(obj: Any) -> Any:
        if client is not None:
            fut = client.compute(obj)
            if progress:
                from distributed.diagnostics.progressbar import progress as dprogress

                dprogress(fut)
            return cluster_result(client, fut, "the stage computation")
        import dask

        if progress:      # the tasks done, in the running stage's progress line
            from skyroute.pipeline.progress import dask_tasks

            with dask_tasks():
                return dask.compute(obj)[0]
        return dask.compute(obj)[0]

    return compute


# --------------------------------------------------------------------------- runner
@dataclass
class StageRecord:
    name: str
    key: str
    cache_hit: bool
    seconds: float
    path: str


class StageDatasets(MutableMapping):
    """Stage name -> dataset, in stage order.  A cached stage's dataset is opened from its zarr
    store (lazily, :meth:`Cache.open`) on first access: a warm run that reads no dataset opens
    none and imports no xarray.  :meth:`attrs` reads a stage's attributes without opening it."""

    def __init__(self, items: dict[str, Any] | None = None):
        self._items: dict[str, Any] = {}
        self._openers: dict[str, tuple[Cache, CacheEntry]] = {}
        self.update(items or {})

    def defer(self, name: str, cache: Cache, entry: CacheEntry) -> None:
        """``name``'s dataset is ``cache.open(entry)``, opened when first read."""
        self._items[name] = None
        self._openers[name] = (cache, entry)

    def get(self, name: str, default: Any = None) -> Any:
        return self[name] if name in self._items else default

    def __getitem__(self, name: str) -> xr.Dataset:
        ds = self._items[name]
        if ds is None and name in self._openers:
            cache, entry = self._openers.pop(name)
            ds = self._items[name] = cache.open(entry)
        return ds

    def __setitem__(self, name: str, ds: xr.Dataset) -> None:
        self._openers.pop(name, None)
        self._items[name] = ds

    def __delitem__(self, name: str) -> None:
        self._openers.pop(name, None)
        del self._items[name]

    def __contains__(self, name: object) -> bool:   # (Mapping's would open the dataset)
        return name in self._items

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __repr__(self) -> str:
        return f"StageDatasets({list(self._items)})"

    def is_open(self, name: str) -> bool:
        """Whether ``name``'s dataset is in memory or was opened (False: cached, not read yet)."""
        return name in self._items and name not in self._openers

    def attrs(self, name: str) -> dict[str, Any]:
        """The attributes of ``name``'s dataset (as ``ds.attrs``); read from the store's metadata,
        without opening it, while it is not open yet."""
        if name in self._openers:
            cache, entry = self._openers[name]
            return cache.attrs(entry)
        return dict(self[name].attrs)


@dataclass
class RunResult:
    scenario: Scenario
    datasets: StageDatasets = field(default_factory=StageDatasets)
    records: list[StageRecord] = field(default_factory=list)
    seconds: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.datasets, StageDatasets):
            self.datasets = StageDatasets(dict(self.datasets))

    def __getitem__(self, name: str) -> xr.Dataset:
        return self.datasets[name]

    @property
    def cache_hits(self) -> int:
        return sum(r.cache_hit for r in self.records)


def stage_attrs(result: Any, name: str) -> dict[str, Any]:
    """The attributes of stage ``name``'s dataset in ``result`` (a :class:`RunResult`, or any
    object with a ``datasets`` mapping), without opening a cached dataset."""
    datasets = result.datasets
    return datasets.attrs(name) if isinstance(datasets, StageDatasets) else dict(datasets[name].attrs)


def stage_key(stage: Stage, scenario: Scenario, input_keys: Sequence[str], code_version: str | None = None) -> str:
    """Cache key of ``stage`` (``code_version``: :meth:`Stage.code_version`, when already known)."""
    cv = stage.code_version() if code_version is None else code_version
    return stable_hash(stage.name, cv, stage.select(scenario), list(input_keys))


def _versions_and_keys(todo: Sequence[Stage], scenario: Scenario) -> tuple[dict[str, str], dict[str, str]]:
    """Code version and cache key of every stage of ``todo`` (in graph order)."""
    versions: dict[str, str] = {}
    keys: dict[str, str] = {}
    for st in todo:
        versions[st.name] = st.code_version()
        keys[st.name] = stage_key(st, scenario, [keys[d] for d in st.inputs]
                                  + [keys.get(d, "absent") for d in st.optional_inputs], versions[st.name])
    return versions, keys


def stage_keys(scenario: Scenario, targets: Sequence[str] | None = None) -> dict[str, str]:
    """The cache key of every stage needed for ``targets`` (all stages: None), as
    :func:`run_pipeline` derives them, without running anything.  Data files contribute their
    content (size and digest), never their path (:func:`skyroute.pipeline.model.stable_hash`):
    the same bytes in another folder give the same keys."""
    return _versions_and_keys(stages_for(scenario, targets), scenario)[1]


def _run_prechecks(pending: list[Stage], todo: list[Stage], scenario: Scenario,
                   datasets: dict[str, xr.Dataset]) -> None:
    """Run (once) every pending precheck whose ``precheck_after`` stages are done."""
    names = {s.name for s in todo}
    for s in list(pending):
        if all(d in datasets for d in s.precheck_after if d in names):
            pending.remove(s)
            s.precheck(scenario, datasets)  # type: ignore[misc]


def run_pipeline(scenario: Scenario, *, cache: Cache | None = None, targets: Sequence[str] | None = None,
                 scheduler: str = "threads", workers: int | None = None, progress: bool = False,
                 force: Sequence[str] = ()) -> RunResult:
    """Run (or read from the cache) every stage of ``scenario`` needed for ``targets``."""
    from skyroute.pipeline.budget import check_scenario

    # cells x levels x epochs over --max-memory: InputError before any work (map stages alone are
    # chunked: a lower estimate per cell)
    check_scenario(scenario, maps_only="plan" not in {s.name for s in stages_for(scenario, targets)})
    cache = cache or Cache()
    cache.clean_tmp()
    t_all = time.perf_counter()
    result = RunResult(scenario)
    todo = stages_for(scenario, targets)
    # a key needs no data: every key, and whether the cache holds it, is known before any
    # stage runs, so the prechecks of stages read from the cache are skipped (they read
    # whole maps, and their stage passed them when it was computed)
    versions, keys = _versions_and_keys(todo, scenario)
    entries: dict[str, CacheEntry | None] = {}
    for st in todo:
        entries[st.name] = None if st.name in force else cache.get(st.name, keys[st.name])
    computes = any(e is None for e in entries.values())
    if computes:
        cache.check_writable()   # a read-only or unusable cache: one error before any stage computes
    # a local scheduler is configured (and dask imported) only when a stage computes; a
    # cluster is always connected to (a wrong address is an error, cached or not)
    with (scheduler_context(scheduler, workers) if computes or scheduler not in LOCAL_SCHEDULERS
          else _check_scheduler(scheduler)) as client, stage_phases(progress, len(todo)) as phases:
        compute = _computer(client, progress)
        # a precheck saves the work of the OTHER stages computed before its stage: with every other
        # stage cached it would only repeat the stage's own check (the plan stage's degenerate-cost
        # check reads the maps of its planning window: seconds on a city)
        prechecks = [s for s in todo if s.precheck is not None and entries[s.name] is None
                     and any(entries[t.name] is None for t in todo if t is not s)]
        _run_prechecks(prechecks, todo, scenario, result.datasets)
        for i, st in enumerate(todo, 1):
            control.check()
            t0 = time.perf_counter()
            code_version, key, entry = versions[st.name], keys[st.name], entries[st.name]
            hit = entry is not None
            if entry is None:
                import xarray as xr

                from skyroute.pipeline.verify import DatasetError, verify_dataset

                log.info("stage=%s key=%s status=compute", st.name, key)
                phases.start(i, st.name, st.description)
                args = [result.datasets[d] for d in st.inputs] + [result.datasets.get(d) for d in st.optional_inputs]
                with control.progress(progress):
                    out = st.func(*args, settings=st.select(scenario))
                if not isinstance(out, xr.Dataset):
                    raise TypeError(f"stage {st.name} returned {type(out).__name__}, not an xarray.Dataset")
                problems = verify_dataset(out)
                if problems:  # never cache (and so never trust) a malformed output
                    raise DatasetError(f"output of stage {st.name!r}", problems)
                out.attrs.update({"skyroute_stage": st.name, "skyroute_key": key,
                                  "skyroute_version": SKYROUTE_VERSION})
                not_cacheable = out.attrs.get("skyroute_not_cacheable")
                if not_cacheable:     # e.g. a planner stopped by its wall-clock safety net: load-dependent
                    log.warning("stage=%s key=%s not cached: %s", st.name, key, not_cacheable)
                    warnings.warn(f"stage {st.name}: not cached: {not_cacheable} (the result depends on the "
                                  "machine's load; a later run computes it again)", RuntimeWarning, stacklevel=2)
                    result.datasets[st.name] = out
                    result.records.append(StageRecord(st.name, key, False, time.perf_counter() - t0, ""))
                    _run_prechecks(prechecks, todo, scenario, result.datasets)
                    continue
                entry = cache.write(st.name, key, out, {
                    "scenario": scenario.name, "code_version": code_version,
                    "inputs": {d: keys.get(d, "absent") for d in (*st.inputs, *st.optional_inputs)},
                    "skyroute_version": SKYROUTE_VERSION,
                }, compute=compute, replace=st.name in force)   # --force: the new result replaces it
                # the stage's output and inputs are read back from the cache when needed; large arrays
                # often sit in reference cycles (xarray / dask objects) that the collector, counting
                # objects rather than bytes, would keep until much later: on the 20 km city the
                # surface stage left 1.6 GB and the map stages together 4.1 GB behind for the next
                # stage in the same process (README, "City-scale planning")
                out = args = None
                gc.collect()
                phases.end()
            else:
                log.info("stage=%s key=%s status=cache-hit", st.name, key)
            result.datasets.defer(st.name, cache, entry)     # opened when first read
            result.records.append(StageRecord(st.name, key, hit, time.perf_counter() - t0, str(entry.path)))
            _run_prechecks(prechecks, todo, scenario, result.datasets)
    result.seconds = time.perf_counter() - t_all
    return result
