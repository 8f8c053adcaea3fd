"""Timings of the Python package (run with the wheel installed, from the repository root):

    .venv/bin/python python/bench.py solve [repeats]   # preston.solve vs `preston solve` on data/job.toml
    .venv/bin/python python/bench.py threads [repeats] # one solve on 1 thread vs every core
    .venv/bin/python python/bench.py batch [workers]    # 16-job sweep: sequential vs LocalCluster

Wall-clock times on whatever the machine is doing; quote them with the load.
"""

import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

# The installed wheel, not the source package beside this script.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]

import preston  # noqa: E402
from preston._batch import run_job  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
JOB = os.path.join(ROOT, "data", "job.toml")
BIN = os.environ.get("PRESTON_BIN", os.path.join(ROOT, "target", "release", "preston"))


def bench_solve(repeats: int) -> None:
    cli, py, py_write = [], [], []
    with tempfile.TemporaryDirectory() as d:
        for k in range(repeats):
            t = time.perf_counter()
            subprocess.run([BIN, "solve", "--job", JOB, "--out", os.path.join(d, "cli")], check=True, capture_output=True)
            cli.append(time.perf_counter() - t)
            t = time.perf_counter()
            r = preston.solve(JOB)
            py.append(time.perf_counter() - t)
            r.write(os.path.join(d, "py"))
            py_write.append(time.perf_counter() - t)
    med = statistics.median
    print(f"CLI `preston solve --job data/job.toml`: median {med(cli):.3f} s  {['%.2f' % x for x in cli]}")
    print(f"preston.solve(job):                    median {med(py):.3f} s  {['%.2f' % x for x in py]}")
    print(f"  + r.write(dir):                      median {med(py_write):.3f} s")
    print(f"ratio python/CLI (medians): {med(py) / med(cli):.3f}")


def _load() -> str:
    return "load average %.1f %.1f %.1f" % os.getloadavg()


def _thread_cpu() -> dict:
    """CPU seconds (user + system) of each live thread of this process, by thread id (Linux)."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[tid] = (int(fields[11]) + int(fields[12])) / tick
    return out


def bench_threads(repeats: int) -> None:
    """Parallel efficiency of one solve of the sample job: wall and CPU time on 1 and on every
    core (the engine's pool), interleaved."""
    cores = os.cpu_count() or 1
    t = {1: [], cores: []}
    cpu = {1: [], cores: []}
    print(_load())
    for _ in range(repeats):
        for n in (1, cores):
            w, c = time.perf_counter(), time.process_time()
            preston.solve(JOB, threads=n)
            t[n].append(time.perf_counter() - w)
            cpu[n].append(time.process_time() - c)
    med = statistics.median
    for n in (1, cores):
        print(f"threads={n}: wall median {med(t[n]):.3f} s {['%.2f' % x for x in t[n]]}, "
              f"CPU median {med(cpu[n]):.3f} s")
    # How the work of one solve splits: the calling thread does the serial parts (it waits while
    # the global pool runs a parallel loop), the pool's threads the rest. On `cores` free cores
    # the solve takes at least serial + max(pool / cores, busiest pool thread), at most
    # serial + pool.
    preston.solve(JOB)  # starts the global pool
    me = str(threading.get_native_id())
    before = _thread_cpu()
    w = time.perf_counter()
    preston.solve(JOB)
    wall = time.perf_counter() - w
    after = _thread_cpu()
    serial = after[me] - before.get(me, 0.0)
    pool = sorted((after[k] - before.get(k, 0.0) for k in after if k != me), reverse=True)
    parallel = sum(pool)
    fast = serial + max(parallel / cores, pool[0] if pool else 0.0)
    print(f"one solve on the global pool: {wall:.2f} s wall; CPU {serial:.2f} s in the calling thread (serial), "
          f"{parallel:.2f} s in the pool's threads {['%.2f' % x for x in pool if x > 0.005]}")
    print(f"on {cores} free cores: one solve {fast:.2f} to {serial + parallel:.2f} s; {cores} single-thread "
          f"workers take {(serial + parallel) / cores:.2f} s per job: a sweep ratio between "
          f"{1 / cores:.2f} and {(serial + parallel) / cores / fast:.2f}")
    s = med(t[1]) / med(t[cores])
    print(f"speed-up on {cores} threads: {s:.2f} (parallel efficiency {s / cores:.2f}); "
          f"a {cores}-worker sweep can at best take {1 / s:.2f}x the sequential time")
    print(_load())


def bench_batch(workers: int) -> None:
    from dask.distributed import Client, LocalCluster

    axes = {"machine.v_max_mm_per_min": [2000.0, 2500.0, 3000.0, 3500.0],
            "dwell.raster_pitch_mm": [1.0, 1.1, 1.2, 1.3]}
    jobs = preston.grid(JOB, axes, name="sweep")
    print(_load())
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        c = time.process_time()
        seq = []
        for j in jobs:
            name = j["name"]
            seq.append(run_job(name, {k: v for k, v in j.items() if k != "name"}, os.path.join(d, "seq")))
        t_seq = time.perf_counter() - t
        c_seq = time.process_time() - c
        t = time.perf_counter()
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
        client = Client(cluster)
        client.run(lambda: __import__("preston"))  # workers import the package before the clock starts
        t_start = time.perf_counter() - t
        t = time.perf_counter()
        table = preston.batch(jobs, client=client, out_dir=os.path.join(d, "par"))
        t_par = time.perf_counter() - t
        client.close()
        cluster.close()
        t = time.perf_counter()
        preston.batch(jobs, out_dir=os.path.join(d, "own"), n_workers=workers)
        t_own = time.perf_counter() - t
        rows = table.to_dict("records") if hasattr(table, "to_dict") else table
        same = all(
            r["ok"] and np.array_equal(np.loadtxt(r["dwell_csv"], delimiter=",", skiprows=1)[:, 3],
                                       np.loadtxt(s["dwell_csv"], delimiter=",", skiprows=1)[:, 3])
            for r, s in zip(rows, seq)
        )
    task_wall = sum(r["wall_s"] for r in rows)
    task_cpu = sum(r["cpu_s"] for r in rows)
    n = len(jobs)
    print(f"{n}-job sweep of data/job.toml (v_max x raster pitch)")
    print(f"sequential (preston.solve + write, one process, default threads): {t_seq:.1f} s wall, "
          f"{c_seq:.1f} s CPU (mean {t_seq / n:.2f} s per job)")
    print(f"preston.batch on a running {workers}-worker LocalCluster (started in {t_start:.1f} s, not counted): "
          f"{t_par:.1f} s  ratio {t_par / t_seq:.3f}; tasks {task_wall:.1f} s wall, {task_cpu:.1f} s CPU in all")
    print(f"preston.batch starting its own cluster (start-up counted): {t_own:.1f} s  ratio {t_own / t_seq:.3f}")
    print(f"dwell identical to sequential: {same}")
    print(_load())


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "solve"
    arg = int(sys.argv[2]) if len(sys.argv) > 2 else (2 if what == "batch" else 3)
    if what == "solve":
        bench_solve(arg)
    elif what == "threads":
        bench_threads(arg)
    else:
        bench_batch(arg)
