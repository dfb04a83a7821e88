"""Many compositions at once: ``rigmix batch CONFIG... --out DIR``.

Each config is one independent job (:func:`run_one`): compose it, write ``<stem>.glb`` and
``<stem>.report.json`` into the output folder. :func:`run_batch` runs the jobs

* in a local process pool (default; ``spawn`` start method, so it is safe with threads and
  on every platform), or
* on a Dask distributed cluster (``scheduler="local-dask"`` starts a ``LocalCluster``, any
  other string is a scheduler address; the optional dependency ``rigmix[dask]``; the output
  folder must then be on a file system the workers share).

Only paths travel between processes (never characters or arrays); each worker reads its
inputs itself. Built-in characters (``builtin:NAME``) are built once per batch on the process
pool: each by one worker at start-up, the workers taking them in different orders so that two
are built at once, and read by the others from a private folder of the batch
(:func:`share_builtins`); building one takes seconds, as long as several compositions.

One failing job does not stop the others: its error is recorded and the batch goes on. Every
finished job appends one JSON line to ``DIR/manifest.jsonl``::

    {"config": "/abs/path/centaur.toml", "config_sha256": "...", "stem": "centaur",
     "status": "ok" | "failed", "outputs": {"glb": "centaur.glb", "report": "centaur.report.json"},
     "timings": {"compose": 3.2, "write": 0.1, "total": 3.3, "cpu": 3.1, "stages": {...}},
     "error": null | "one-line message", "error_kind": null | "input" | "internal",
     "gates_failed": ["junction_self_intersections = 3 (bound <= 0)", ...],
     "finished": "2026-11-22T01:02:03Z"}

``timings`` are wall-clock seconds, except ``cpu``: the CPU seconds of the job's process (all its
threads) over the job. ``error_kind`` is ``"input"`` for a :class:`RigmixError` (a bad config or input file) and
``"internal"`` for anything else (a bug, a worker process that died). ``gates_failed`` lists the
hard gates of the report that failed (:mod:`rigmix.gates`; the job is still ``ok``, its outputs
written). :func:`exit_status` turns the entries into the exit status of ``rigmix batch`` (0, 2
or 1, as ``rigmix compose``; 3 with ``--strict`` when the only failures are gates).

Outputs are named relative to ``DIR``. The batch is resumable: a config whose latest manifest
entry is ``ok``, whose file has not changed since (same SHA-256) and whose outputs all exist is
skipped; failed jobs are run again. A job's outputs are written by
:func:`rigmix.export.write_outputs`, all or none, so an interrupted or failed job leaves no
partial file. No output (nor the manifest) may be a config or an input file of any job:
:func:`plan_batch` refuses the whole batch before running anything.

Process pool: each worker is a pool of one process (a slot), so a worker that dies (a crash
in native code, the out-of-memory killer, SIGKILL) fails its own job only, with an internal
error; its slot gets a new process and the other jobs go on. The workers ignore SIGINT and
turn SIGTERM into :class:`rigmix.safety.Interrupted`, so a stopped job removes its temporary
files. When the calling process is interrupted (``KeyboardInterrupt``, or SIGTERM through
:func:`rigmix.safety.signals_raise` in the command line), the jobs not started are cancelled,
the workers are sent SIGTERM (SIGKILL after :data:`STOP_TIMEOUT` seconds) and waited for, and
the exception propagates: no worker outlives the batch.

Threads: the numerical libraries each start a thread per core (OpenBLAS, OpenMP in torch,
libigl); ``n`` workers on as many cores would run ``n`` times too many threads, which then wait
on each other. Each worker of the pool limits them to its share of the cores,
``cpu_count // n`` (at least 1; :func:`limit_threads`), as joblib does for its workers.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import shutil
import signal
import tempfile
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable

from .errors import InputError, RigmixError, UnsupportedError
from .export import config_inputs, json_default, write_outputs
from .gates import failure_items
from .safety import Interrupted, check_outputs, file_digest

__all__ = ["MANIFEST", "LOCAL_DASK", "STOP_TIMEOUT", "BUILTIN_WAIT", "THREAD_VARIABLES", "run_one", "run_batch",
           "read_manifest", "plan_batch", "exit_status", "builtin_names", "share_builtins", "limit_threads",
           "run_pool"]

logger = logging.getLogger(__name__)

#: Name of the manifest file in the output folder.
MANIFEST = "manifest.jsonl"
#: ``scheduler`` value that starts a local Dask cluster.
LOCAL_DASK = "local-dask"
#: Seconds a worker has to remove its temporary files after SIGTERM before it is killed.
STOP_TIMEOUT = 20.0
#: Seconds a worker waits for a built-in character another worker builds (:func:`share_builtins`)
#: before its jobs build it themselves.
BUILTIN_WAIT = 120.0

#: Environment variables that set the thread count of a library loaded after they are set
#: (OpenMP, which torch's intra-op pool follows; OpenBLAS; MKL; libigl's ``parallel_for``).
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "IGL_NUM_THREADS")

#: ``progress(done, total, entry)``: called in the calling process as each job ends (skipped
#: jobs included); the CLI turns it into a progress bar.
BatchProgress = Callable[[int, int, dict], None]


def _now() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _outputs(stem: str) -> dict:
    return {"glb": f"{stem}.glb", "report": f"{stem}.report.json"}


def run_one(config_path, out_dir) -> dict:
    """Compose one config and write its outputs; never raises for a failing composition.

    Parameters
    ----------
    config_path : str or Path
        A composition config (TOML).
    out_dir : str or Path
        Existing folder receiving ``<stem>.glb`` and ``<stem>.report.json`` (``stem``: the
        config's file name without suffix).

    Returns
    -------
    dict
        The manifest entry (see the module docstring): ``status`` is ``"ok"`` or ``"failed"``
        with ``error`` the one-line message (a :class:`RigmixError`'s text, or ``internal
        error (...)`` for anything else, whose traceback is logged at debug level).
    """
    from .pipeline import compose

    config_path, out_dir = Path(config_path).resolve(), Path(out_dir)
    stem = config_path.stem
    outputs = _outputs(stem)
    entry = {"config": str(config_path), "config_sha256": None, "stem": stem, "status": "failed",
             "outputs": outputs, "timings": {}, "error": None, "error_kind": None, "gates_failed": [],
             "finished": None}
    t_start, cpu_start = time.perf_counter(), time.process_time()
    try:
        try:
            entry["config_sha256"] = file_digest(config_path)
        except OSError as exc:
            raise InputError(f"batch: cannot read config {config_path}: {exc.strerror or exc}") from None
        t0 = time.perf_counter()
        composition = compose(config_path)
        entry["timings"]["compose"] = round(time.perf_counter() - t0, 4)
        entry["timings"]["stages"] = dict(composition.report.get("timings", {}))
        if composition.character is None:
            raise UnsupportedError(
                f"batch: {config_path.name}: compose produced no character (the fusion, weight and "
                "animation stages are not part of this build's pipeline); nothing to write")
        t0 = time.perf_counter()
        result = write_outputs(composition, glb=out_dir / outputs["glb"], report=out_dir / outputs["report"],
                               sort_keys=True)
        entry["timings"]["write"] = round(time.perf_counter() - t0, 4)
        entry["gates_failed"] = failure_items(list(result.gates))
        entry["status"] = "ok"
    except RigmixError as exc:
        entry["error"], entry["error_kind"] = _one_line(exc), "input"
    except Exception as exc:  # a bug in a stage: recorded, the batch goes on
        logger.debug("batch: %s failed:\n%s", config_path, traceback.format_exc())
        entry["error"] = _one_line(f"internal error ({type(exc).__name__}: {exc})")
        entry["error_kind"] = "internal"
    entry["timings"]["total"] = round(time.perf_counter() - t_start, 4)
    entry["timings"]["cpu"] = round(time.process_time() - cpu_start, 4)
    entry["finished"] = _now()
    return entry


def read_manifest(out_dir) -> dict:
    """The latest manifest entry per config.

    Parameters
    ----------
    out_dir : str or Path

    Returns
    -------
    dict of str -> dict
        Absolute config path -> its last entry (later lines win). A missing manifest gives
        ``{}``; a line that is not valid JSON (e.g. cut by a crash) is skipped with a warning.
    """
    path = Path(out_dir) / MANIFEST
    if not path.exists():
        return {}
    out = {}
    with open(path, encoding="utf-8") as fh:
        for k, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                entry = json.loads(line)
                out[entry["config"]] = entry
            except (ValueError, KeyError, TypeError):
                logger.warning("batch: %s line %d is not a manifest entry: ignored", path, k)
    return out


def _is_done(entry: dict | None, digest: str | None, out_dir: Path) -> bool:
    return (entry is not None and entry.get("status") == "ok" and digest is not None
            and entry.get("config_sha256") == digest
            and all((out_dir / name).is_file() for name in entry.get("outputs", {}).values()))


def plan_batch(configs: Iterable, out_dir) -> tuple[list[Path], list[dict]]:
    """Split configs into those to run and the finished ones to skip.

    Parameters
    ----------
    configs : iterable of str or Path
    out_dir : str or Path

    Returns
    -------
    todo : list of Path
        Resolved config paths to run, in the given order.
    skipped : list of dict
        The manifest entries of the configs already done (see the module docstring).

    Raises
    ------
    InputError
        No configs, a config listed twice, two configs with the same file name (their
        outputs would collide), or an output (or the manifest) that is a config or an input
        file of one of the jobs.
    """
    out_dir = Path(out_dir)
    paths = [Path(c).resolve() for c in configs]
    if not paths:
        raise InputError("batch: no config given")
    seen: dict[str, Path] = {}
    for p in paths:
        if p.stem in seen:
            what = "is listed twice" if seen[p.stem] == p else f"and {seen[p.stem]} have the same name"
            raise InputError(f"batch: {p} {what}: outputs are named after the config file "
                             f"({p.stem}.glb); rename one")
        seen[p.stem] = p
    _check_outputs(paths, out_dir)
    manifest = read_manifest(out_dir)
    todo, skipped = [], []
    for p in paths:
        entry = manifest.get(str(p))
        digest = file_digest(p) if p.is_file() else None
        if _is_done(entry, digest, out_dir):
            skipped.append(dict(entry, skipped=True))
        else:
            todo.append(p)
    return todo, skipped


def _check_outputs(paths: list[Path], out_dir: Path) -> None:
    """Refuse a batch whose outputs would overwrite a config or an input file of any job."""
    from .config import load_config

    inputs = []
    for p in paths:
        inputs.append((f"the config {p.name}", p))
        try:
            inputs += [(f"{what} of {p.name}", f) for what, f in config_inputs(load_config(p)) if f != p]
        except Exception:  # noqa: BLE001 - that job fails with this error when it runs
            pass
    outputs = [("the manifest", out_dir / MANIFEST)]
    outputs += [(f"the output of {p.name}", out_dir / name) for p in paths for name in _outputs(p.stem).values()]
    check_outputs(outputs, inputs, stage=f"batch --out {out_dir}")


def exit_status(entries: list[dict], *, strict: bool = False) -> int:
    """The exit status of a batch, as ``rigmix compose``'s: 0 if every job succeeded (or was
    done before), 2 if every failure is a bad input, 1 if any failure is internal; with
    ``strict``, 3 when every job succeeded but some failed a gate (``gates_failed``)."""
    failed = [e for e in entries if e.get("status") != "ok"]
    if not failed:
        return 3 if strict and any(e.get("gates_failed") for e in entries) else 0
    return 2 if all(e.get("error_kind") == "input" for e in failed) else 1


class _Manifest:
    """Appends entries to ``manifest.jsonl`` (one writer: the calling process), flushed per line."""

    def __init__(self, out_dir: Path):
        self.path = out_dir / MANIFEST

    def append(self, entry: dict) -> None:
        line = json.dumps(entry, sort_keys=True, default=json_default)
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(line + "\n")
            fh.flush()
            os.fsync(fh.fileno())


def _failed_entry(config: Path, message: str) -> dict:
    """The entry of a job that failed outside :func:`run_one` (its worker died): internal."""
    return {"config": str(config), "config_sha256": None, "stem": config.stem, "status": "failed",
            "outputs": _outputs(config.stem), "timings": {}, "error": _one_line(message),
            "error_kind": "internal", "gates_failed": [], "finished": _now()}


def run_batch(configs, out_dir, *, workers: int | None = None, scheduler: str | None = None,
              progress: BatchProgress | None = None) -> list[dict]:
    """Run many compositions; failures are recorded, never raised.

    Parameters
    ----------
    configs : iterable of str or Path
        Config files (TOML); outputs are named after their file names, which must differ.
    out_dir : str or Path
        Output folder (created if missing), holding the outputs and ``manifest.jsonl``.
    workers : int, optional
        Worker processes (default: the CPU count, at most the number of jobs). ``0`` runs the
        jobs one after the other in this process (debugging). With ``scheduler="local-dask"``:
        the number of Dask workers (default 2).
    scheduler : str, optional
        ``None``: a local process pool; ``"local-dask"``: a Dask ``LocalCluster`` (processes,
        one thread each); anything else: the address of a running Dask scheduler
        (``tcp://host:8786``).
    progress : callable, optional
        ``progress(done, total, entry)`` after each job (and once per skipped job).

    Returns
    -------
    list of dict
        One entry per config, in the given order: the new manifest entry, or for a skipped job
        its previous entry with ``"skipped": True``.

    Raises
    ------
    InputError
        No config, or colliding config names (see :func:`plan_batch`); an output folder that
        cannot be created.
    UnsupportedError
        A Dask scheduler was asked for but ``dask.distributed`` is not installed.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"batch: cannot create the output folder {out_dir}: {exc.strerror or exc}") from None
    order = [str(Path(c).resolve()) for c in configs]
    todo, skipped = plan_batch(order, out_dir)
    total = len(order)
    results: dict[str, dict] = {}
    done = 0
    for entry in skipped:
        results[entry["config"]] = entry
        done += 1
        if progress is not None:
            progress(done, total, entry)
    if skipped:
        logger.info("batch: %d of %d configs already done: skipped", len(skipped), total)
    manifest = _Manifest(out_dir)

    def finish(entry):
        nonlocal done
        manifest.append(entry)
        results[entry["config"]] = entry
        done += 1
        if entry["status"] != "ok":
            logger.info("batch: %s failed: %s", Path(entry["config"]).name, entry["error"])
        if progress is not None:
            progress(done, total, entry)

    if todo:
        if scheduler is not None:
            _run_dask(todo, out_dir, scheduler, workers, finish)
        elif workers == 0:
            for p in todo:
                finish(run_one(p, out_dir))
        else:
            run_pool(todo, out_dir, workers, finish)
    return [results[c] for c in order]


def builtin_names(configs: Iterable) -> list[str]:
    """The built-in characters (``builtin:NAME`` paths) that the configs use, in order of first use;
    a config that does not load is passed over (its job reports why)."""
    from .config import BUILTIN_PREFIX, load_config

    names = []
    for p in configs:
        try:
            config = load_config(Path(p))
        except Exception:  # noqa: BLE001 - that job fails with this error when it runs
            continue
        for cid in config.characters:
            path = config.character_path(cid)
            if isinstance(path, str) and path.startswith(BUILTIN_PREFIX) and path[len(BUILTIN_PREFIX):] not in names:
                names.append(path[len(BUILTIN_PREFIX):])
    return names


def share_builtins(folder, names) -> None:
    """Worker start-up: build each built-in character of ``names`` in one worker of the batch only,
    and read the ones the others build.

    The first worker to create ``folder/NAME.lock`` builds ``NAME`` (:func:`rigmix.pipeline.builtin_character`)
    and writes ``NAME.pickle`` (renamed into place when complete); a worker that finds the lock taken
    goes on to the next name, then waits for the files it did not build (at most :data:`BUILTIN_WAIT`
    seconds) and reads them (:func:`rigmix.pipeline.keep_builtin`). Given the names in different
    orders, workers build different characters at once. Building is deterministic, so every worker
    composes as if it had built them itself; one that gets no file builds the character when a job
    needs it.

    Parameters
    ----------
    folder : str or Path
        A folder private to the batch (made by the calling process, removed after the batch).
    names : sequence of str
        Built-in character names, e.g. ``("humanoid", "quadruped")``.
    """
    from .pipeline import builtin_character, keep_builtin

    folder = Path(folder)
    waiting = []
    for name in names:
        try:
            os.close(os.open(folder / f"{name}.lock", os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        except FileExistsError:
            waiting.append(name)
            continue
        character = builtin_character(name)
        tmp = folder / f".{name}.{os.getpid()}.tmp"
        with open(tmp, "wb") as fh:
            pickle.dump(character, fh, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, folder / f"{name}.pickle")
    deadline = time.monotonic() + BUILTIN_WAIT
    for name in waiting:
        done = folder / f"{name}.pickle"
        while not done.is_file() and time.monotonic() < deadline:
            time.sleep(0.02)
        if done.is_file():
            with open(done, "rb") as fh:  # written by a worker of this batch into its private folder
                keep_builtin(name, pickle.load(fh))


def limit_threads(threads: int) -> None:
    """Limit this process's numerical thread pools to ``threads`` (a worker's share of the cores).

    Libraries loaded later read :data:`THREAD_VARIABLES`; those loaded already (numpy's and
    scipy's OpenBLAS are, by the time a spawned worker runs its initializer) are limited through
    ``threadpoolctl`` where it is installed. For a worker process only: it sets this process's
    environment.
    """
    threads = max(1, int(threads))
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # an optional dependency: the libraries loaded later are limited all the same
        return
    threadpool_limits(limits=threads)


def _init_worker(builtins: str | None = None, names: tuple = (), threads: int | None = None) -> None:
    """Worker start-up: SIGINT is the calling process's business (it stops the workers); SIGTERM
    raises :class:`Interrupted`, so that the job's temporary files are removed (:func:`_job`).
    With ``threads``, the numerical thread pools are limited to that many (:func:`limit_threads`).
    With ``builtins`` (a folder), the built-in characters ``names`` are shared with the other
    workers (:func:`share_builtins`); a failure there is logged and leaves them to the jobs."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if threads is not None:
        limit_threads(threads)

    def stop(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one clean-up, not two
        if not _in_job:  # waiting for work: nothing to clean
            os._exit(128 + signum)
        raise Interrupted(signum)

    signal.signal(signal.SIGTERM, stop)
    if builtins is not None:
        try:
            share_builtins(builtins, names)
        except Exception as exc:  # noqa: BLE001 - an initializer that raises would fail every job of the slot
            logger.warning("batch: built-in characters not shared (%s: %s); each job builds its own",
                           type(exc).__name__, exc)


_in_job = False


def _job(config: str, out_dir: str) -> dict:
    """:func:`run_one` in a pool worker; a worker stopped by SIGTERM exits once its job has
    cleaned up, instead of going back to the pool for the next job."""
    global _in_job
    _in_job = True
    try:
        return run_one(config, out_dir)
    except Interrupted as exc:
        logging.shutdown()
        os._exit(128 + exc.signum)
    finally:
        _in_job = False


def _new_slot(ctx, initargs: tuple = ()) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_init_worker, initargs=initargs)


def run_pool(todo: list[Path], out_dir: Path, workers: int | None, finish, *, job=_job) -> None:
    """Run ``job(config, out_dir)`` for each config on ``workers`` one-process pools (slots).

    One job at a time per slot, so the job of a worker that dies is known: it alone fails, with
    an internal error, and its slot is rebuilt. ``job`` must be a module-level function (it is
    pickled by name into the workers). With more than one slot, the built-in characters of the
    configs are shared (:func:`share_builtins`, slot ``i`` taking the names rotated by ``i``)
    through a private folder removed afterwards. Each worker's numerical threads are limited to
    its share of the cores (:func:`limit_threads`).
    """
    import multiprocessing

    n = max(1, min(workers or os.cpu_count() or 1, len(todo)))
    ctx = multiprocessing.get_context("spawn")  # no fork of a threaded parent
    names = builtin_names(todo) if n > 1 else []
    shared = tempfile.mkdtemp(prefix="rigmix-builtins-") if names else None  # mode 0700
    threads = max(1, (os.cpu_count() or 1) // n)
    initargs = [(shared, tuple(names[i % len(names):] + names[:i % len(names)]) if names else (), threads)
                for i in range(n)]
    queue = list(reversed(todo))
    slots: list[ProcessPoolExecutor | None] = [None] * n
    running: dict = {}  # future -> (slot index, config)
    try:
        while queue or running:
            for i in range(n):
                if queue and i not in {k for k, _ in running.values()}:
                    if slots[i] is None:
                        slots[i] = _new_slot(ctx, initargs[i])
                    p = queue.pop()
                    running[slots[i].submit(job, str(p), str(out_dir))] = (i, p)
            finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for f in finished:
                i, p = running.pop(f)
                try:
                    entry = f.result()
                except BrokenProcessPool:
                    entry = _failed_entry(p, f"batch: {p.name}: the worker process died while composing it (a crash "
                                             "in native code, out of memory, or killed); the other jobs went on")
                    slots[i].shutdown(wait=True)
                    slots[i] = None
                except Exception as exc:  # e.g. a result that cannot be unpickled
                    entry = _failed_entry(p, f"batch: worker process failed ({type(exc).__name__}: {exc})")
                finish(entry)
    except BaseException:
        _stop_slots([s for s in slots if s is not None])
        raise
    finally:
        for s in slots:
            if s is not None:
                s.shutdown(wait=True)
        if shared is not None:
            shutil.rmtree(shared, ignore_errors=True)


def _stop_slots(pools: list) -> None:
    """Cancel what has not started, SIGTERM the workers (SIGKILL after :data:`STOP_TIMEOUT`),
    wait for them: no worker outlives an interrupted batch."""
    procs, managers = [], []
    for pool in pools:
        procs += list((getattr(pool, "_processes", None) or {}).values())  # the stdlib keeps no public list
        # shutdown(wait=False) forgets the manager thread, so a later shutdown(wait=True) no longer
        # joins it; one still running at exit races the stdlib's exit hook on its wake-up pipe
        managers.append(getattr(pool, "_executor_manager_thread", None))
        pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    deadline = time.monotonic() + STOP_TIMEOUT
    for proc in procs:
        proc.join(max(0.0, deadline - time.monotonic()))
        if proc.is_alive():
            logger.warning("batch: worker %d did not stop within %.0f s of SIGTERM: killed", proc.pid, STOP_TIMEOUT)
            proc.kill()
            proc.join(5)
    for pool in pools:
        pool.shutdown(wait=True)
    for thread in managers:
        if thread is not None:
            thread.join(STOP_TIMEOUT)
    logger.info("batch: interrupted; %d worker process(es) stopped", len(procs))


def _run_dask(todo: list[Path], out_dir: Path, scheduler: str, workers: int | None, finish) -> None:
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise UnsupportedError(
            "batch: --scheduler needs Dask distributed: pip install 'rigmix[dask]'") from None

    cluster = None
    try:
        if scheduler == LOCAL_DASK:
            cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
            client = Client(cluster)
        else:
            try:
                client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise InputError(f"batch: cannot connect to the Dask scheduler {scheduler!r}: {exc}") from None
        with client:
            futures = {client.submit(run_one, str(p), str(out_dir), pure=False, key=f"rigmix-{p.stem}-{i}"): p
                       for i, p in enumerate(todo)}
            try:
                for f in as_completed(list(futures)):
                    try:
                        entry = f.result()
                    except Exception as exc:  # a worker lost mid-job
                        entry = _failed_entry(futures[f], f"batch: Dask job failed ({type(exc).__name__}: {exc})")
                    finish(entry)
            except BaseException:  # interrupted: nothing keeps running on the cluster
                client.cancel(list(futures), force=True)
                raise
    finally:
        if cluster is not None:
            cluster.close()
