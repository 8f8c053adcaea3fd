"""Batches and parameter sweeps of solves on a ``dask.distributed`` cluster.

Each job is one task: the worker solves it with :func:`preston.solve` and writes its outputs
(``dwell.csv``, ``residual.csv``, ``report.json``) into a temporary directory beside the final one,
which is then renamed into place, so a job's directory appears whole or not at all. A job that
fails is a row with its error; the other jobs go on.
"""

from __future__ import annotations

import glob
import itertools
import os
import shutil
import time
import uuid
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

from ._preston import PrestonError

PathLike = Union[str, "os.PathLike[str]"]
JobSpec = Union[PathLike, Mapping[str, Any]]


def _is_pathlike(x: Any) -> bool:
    return isinstance(x, (str, os.PathLike))


def _expand_paths(spec: PathLike) -> List[str]:
    s = os.fspath(spec)
    if os.path.isdir(s):
        return sorted(glob.glob(os.path.join(s, "*.toml")))
    if any(c in s for c in "*?["):
        return sorted(glob.glob(s))
    return [s]


def _flatten(d: Mapping[str, Any], prefix: str = "") -> Dict[str, Any]:
    """Scalar leaves of a nested job dict as dotted keys (``machine.v_max_mm_per_min``)."""
    out: Dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        elif v is None or isinstance(v, (str, int, float, bool)):
            out[key] = v
        else:
            out[key] = repr(v)
    return out


def _set_dotted(d: Dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    for p in parts[:-1]:
        if d.get(p) is None:
            d[p] = {}
        d = d[p]
    d[parts[-1]] = value


# Grid keys that choose the dwell source: the engine's overrides set them (a source given
# replaces the job's, as a flag or keyword does), so the rule lives in one place.
_DWELL_SOURCE_KEYS = {"dwell.file": "dwell", "dwell.raster_pitch_mm": "raster_pitch_mm"}


def grid(job: JobSpec, axes: Mapping[str, Sequence[Any]], name: Optional[str] = None) -> List[dict]:
    """Jobs over the cartesian product of ``axes`` applied to one ``job`` (a file or a dict).

    ``axes`` maps dotted job keys to values, e.g. ``{"machine.v_max_mm_per_min": [2000, 3000],
    "dwell.raster_pitch_mm": [0.8, 1.0]}`` (units as in the job file: mm, mm/min, ...). Each job
    is a dict with a ``name`` (``<name>-000``, ...; ``name`` defaults to the job file's stem,
    else ``job``) that :func:`batch` uses for its output directory.
    """
    from . import InputError, load_job

    base = load_job(job)
    stem = name or (os.path.splitext(os.path.basename(os.fspath(job)))[0] if _is_pathlike(job) else "job")
    keys = list(axes)
    for k in keys:
        if isinstance(axes[k], (str, bytes)) or not isinstance(axes[k], Iterable):
            raise InputError(f"grid: axis {k!r} must be a list of values")
    jobs = []
    for i, values in enumerate(itertools.product(*(list(axes[k]) for k in keys))):
        j = _deepcopy(base)
        for k, v in zip(keys, values):
            if k in _DWELL_SOURCE_KEYS:
                j = _override(j, _DWELL_SOURCE_KEYS[k], v, stem)
            else:
                _set_dotted(j, k, v)
        j["name"] = f"{stem}-{i:03d}"
        jobs.append(j)
    return jobs


def _override(job: dict, keyword: str, value: Any, name: str) -> dict:
    """``job`` with one override of :func:`preston.solve` applied by the engine."""
    import json

    from . import _dumps, _preston

    if keyword == "dwell":
        value = os.fspath(value)
    return json.loads(_preston.apply_overrides(_dumps(job), _dumps({keyword: value}), os.getcwd(), name))


def _deepcopy(d: Any) -> Any:
    import copy

    return copy.deepcopy(d)


def _normalise(jobs: Union[JobSpec, Iterable[JobSpec]]) -> List[Tuple[str, Optional[str], dict]]:
    """(name, job file or None, job dict with absolute paths) for each job, in order."""
    from . import InputError, load_job

    if _is_pathlike(jobs) or isinstance(jobs, Mapping):
        jobs = [jobs]
    items: List[Tuple[str, Optional[str], dict]] = []
    for i, spec in enumerate(jobs):  # type: ignore[arg-type]
        if _is_pathlike(spec):
            paths = _expand_paths(spec)
            if not paths:
                raise InputError(f"batch: no job files match {os.fspath(spec)!r}")
            for p in paths:
                stem = os.path.splitext(os.path.basename(p))[0]
                items.append((stem, os.path.abspath(p), load_job(p)))
        elif isinstance(spec, Mapping):
            d = dict(spec)
            name = str(d.pop("name", f"job{i:03d}"))
            items.append((name, None, load_job(d)))
        else:
            raise InputError(f"batch: job {i} is a {type(spec).__name__}, not a dict or a path")
    seen: Dict[str, int] = {}
    out = []
    for name, path, job in items:
        if not name or name in (".", "..") or os.sep in name or (os.altsep and os.altsep in name):
            raise InputError(f"batch: job name {name!r} cannot name a directory")
        n = seen.get(name, 0)
        seen[name] = n + 1
        out.append((name if n == 0 else f"{name}-{n}", path, job))
    return out


def run_job(name: str, job: dict, out_dir: str, threads: Optional[int] = None) -> Dict[str, Any]:
    """Solves one job (on ``threads`` engine threads, None: the process's pool) and writes its
    outputs atomically into ``out_dir/name``; returns its row.

    The task each Dask worker runs. Never raises for a failing job: the row holds ``ok=False``,
    ``error_type`` and ``error`` (Preston's message)."""
    from . import solve

    row: Dict[str, Any] = {"job": name, "ok": False, "error_type": None, "error": None}
    final = os.path.join(out_dir, name)
    tmp = os.path.join(out_dir, f".{name}.tmp-{uuid.uuid4().hex}")
    start, cpu = time.perf_counter(), time.process_time()
    try:
        r = solve(job, threads=threads)
        r.write(tmp)
        _replace_dir(tmp, final)
        row.update(r.report)
        row.update(
            ok=True,
            converged=r.converged,
            out_dir=final,
            dwell_csv=os.path.join(final, "dwell.csv"),
            residual_csv=os.path.join(final, "residual.csv"),
            report_json=os.path.join(final, "report.json"),
        )
    except PrestonError as e:
        row.update(error_type=type(e).__name__, error=str(e))
    except Exception as e:  # a batch reports every job; one bug must not stop the others
        row.update(error_type=type(e).__name__, error=str(e))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    row["wall_s"] = time.perf_counter() - start
    row["cpu_s"] = time.process_time() - cpu
    return row


def _replace_dir(tmp: str, final: str) -> None:
    """Renames the finished ``tmp`` onto ``final`` (an older ``final`` is moved aside first and
    removed after)."""
    old = None
    if os.path.exists(final):
        old = f"{final}.old-{uuid.uuid4().hex}"
        os.rename(final, old)
    os.rename(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def worker_env(n_workers: int) -> Dict[str, str]:
    """Environment of local worker processes: the engine's thread pool (rayon) gets an equal share
    of the cores, so that ``n_workers`` solves at once do not oversubscribe the machine (an
    explicit ``RAYON_NUM_THREADS`` is kept). Results do not depend on the thread count."""
    share = max(1, (os.cpu_count() or 1) // max(1, n_workers))
    return {"RAYON_NUM_THREADS": os.environ.get("RAYON_NUM_THREADS", str(share))}


def _host_cores() -> Tuple[str, int]:
    import socket

    return socket.gethostname(), os.cpu_count() or 1


def threads_per_task(client: Any) -> int:
    """Engine threads for each task so that the cluster's task slots on one host share its cores
    without oversubscription: the smallest, over the hosts, of ``cores // task slots`` (at least
    1). Each worker reports its host and core count (``client.run``)."""
    hosts = client.run(_host_cores)
    slots: Dict[str, int] = {}
    cores: Dict[str, int] = {}
    for addr, n in client.nthreads().items():
        host, c = hosts.get(addr, (addr, 1))
        slots[host] = slots.get(host, 0) + n
        cores[host] = c
    if not slots:
        return 1
    return max(1, min(cores[h] // max(1, slots[h]) for h in slots))


def batch(
    jobs: Union[JobSpec, Iterable[JobSpec]],
    client: Any = None,
    out_dir: PathLike = "preston-batch",
    grid: Optional[Mapping[str, Sequence[Any]]] = None,
    n_workers: int = 2,
    threads_per_job: Optional[int] = None,
) -> Any:
    """Runs many solves on a ``dask.distributed`` cluster, one task per job.

    ``jobs``: a list of job dicts (the job file's structure, optionally with a ``name``) and job
    files, a directory of ``*.toml`` job files, a glob, or one job with ``grid`` (axes of
    :func:`grid`, dotted job keys to lists of values) for a parameter sweep.

    ``client``: a ``dask.distributed.Client``, or a scheduler address; ``None`` starts a
    ``LocalCluster`` of ``n_workers`` single-threaded worker processes for the call, each
    engine's thread pool limited to its share of the cores (:func:`worker_env`).

    ``threads_per_job``: engine threads of each solve. Default: the cores of each host divided
    by the task slots (worker threads) the cluster runs there (:func:`threads_per_task`), so that
    concurrent solves do not oversubscribe a machine. The results do not depend on it.

    Each job's ``dwell.csv``, ``residual.csv`` and ``report.json`` go to ``out_dir/<name>/``,
    written into a temporary directory that is renamed into place once complete. A failing job
    does not stop the others.

    Returns one row per job, in job order, as a pandas ``DataFrame`` when pandas is installed,
    else a list of dicts: ``job``, ``job_file``, the job's inputs (dotted keys such as
    ``machine.v_max_mm_per_min``), ``ok``, ``error_type``/``error`` (Preston's message) for a
    failure, every key of ``report.json``, ``converged``, ``out_dir`` and the three output paths,
    ``wall_s`` (the task's wall time, s) and ``cpu_s`` (its worker process's CPU time, s).
    """
    from . import InputError

    if grid is not None:
        if not (_is_pathlike(jobs) or isinstance(jobs, Mapping)):
            raise InputError("batch: grid= sweeps one job; give one job file or dict")
        from ._batch import grid as make_grid

        jobs = make_grid(jobs, grid)
    items = _normalise(jobs)
    out = os.path.abspath(os.fspath(out_dir))
    os.makedirs(out, exist_ok=True)

    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "preston.batch needs dask.distributed: pip install 'dask[distributed]'"
        ) from e

    own_cluster = own_client = None
    if client is None:
        own_cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            env=worker_env(n_workers),
        )
        client = own_client = Client(own_cluster)
    elif isinstance(client, str):
        client = own_client = Client(client)
    try:
        threads = threads_per_job if threads_per_job is not None else threads_per_task(client)
        if threads < 1:
            raise InputError(f"batch: threads_per_job must be at least 1, got {threads}")
        futures = [
            client.submit(
                run_job, name, job, out, threads, key=f"preston-{name}-{uuid.uuid4().hex}", pure=False
            )
            for name, _, job in items
        ]
        results = []
        for (name, _, _), f in zip(items, futures):
            try:
                results.append(f.result())
            except Exception as e:  # the task itself died (worker lost, ...)
                results.append({"job": name, "ok": False, "error_type": type(e).__name__, "error": str(e)})
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()

    rows = []
    for (name, path, job), res in zip(items, results):
        row: Dict[str, Any] = {"job": name, "job_file": path}
        row.update(_flatten(job))
        row.update(res)
        rows.append(row)
    try:
        import pandas as pd
    except ImportError:
        return rows
    return pd.DataFrame(rows)
