"""Timings of the Python package (run with the wheel installed, from the repository root):

    .venv/bin/python python/bench.py solve [repeats]   # preston.solve vs `preston solve` on data/job.toml
    .venv/bin/python python/bench.py batch [workers]   # 16-job sweep: sequential vs LocalCluster

Wall-clock times on whatever the machine is doing; quote them with the load.
"""

import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

# The installed wheel, not the source package beside this script.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]

import preston  # noqa: E402
from preston._batch import run_job, worker_env  # noqa: E402

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


def bench_batch(workers: int) -> None:
    from dask.distributed import Client, LocalCluster

    jobs = preston.grid(JOB, {"machine.v_max_mm_per_min": [2000.0, 2500.0, 3000.0, 3500.0],
                              "dwell.raster_pitch_mm": [1.0, 1.1, 1.2, 1.3]}, name="sweep")
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        seq = []
        for j in jobs:
            name = j["name"]
            seq.append(run_job(name, {k: v for k, v in j.items() if k != "name"}, os.path.join(d, "seq")))
        t_seq = time.perf_counter() - t
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                               env=worker_env(workers))
        client = Client(cluster)
        client.run(lambda: __import__("preston"))  # workers import the package before the clock starts
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
    print(f"16 jobs sequential (preston.solve + write, one process): {t_seq:.1f} s")
    print(f"16 jobs preston.batch on a running {workers}-worker LocalCluster: {t_par:.1f} s  ratio {t_par / t_seq:.3f}")
    print(f"16 jobs preston.batch starting its own cluster: {t_own:.1f} s  ratio {t_own / t_seq:.3f}")
    print(f"dwell identical to sequential: {same}")


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "solve"
    arg = int(sys.argv[2]) if len(sys.argv) > 2 else (3 if what == "solve" else 2)
    bench_solve(arg) if what == "solve" else bench_batch(arg)
