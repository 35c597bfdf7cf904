"""torch threads on a busy machine: the GP fit's steps on 1 and 2 threads, with and without
busy-looping processes beside it, under OpenMP's two ways of waiting.

One run (``python scripts/bench_threads.py``) times ``steps`` full-batch training steps of the
default recipe's fit (the K-lumps chain's 45 one-input GPs side by side, 32 inducing points,
100 bins: :func:`surrogate.gp.training.fit_classifiers`) on synthetic data, each in a fresh
process whose environment the run sets before torch loads its OpenMP runtime (GNU libgomp in
the pip wheel; oneMKL is linked against it and numba's ``omp`` layer reads the same variables):

* ``spin``: neither ``OMP_WAIT_POLICY`` nor ``GOMP_SPINCOUNT`` set, libgomp's default: an idle
  thread spins 300,000 times before it sleeps;
* ``passive``: ``OMP_WAIT_POLICY=PASSIVE`` (what importing :mod:`surrogate` sets, see
  :func:`surrogate.threads.passive_wait`): an idle thread sleeps at once.

Each set-up runs on 1 and 2 torch threads, beside 0 and ``busy`` processes that loop forever
(stopped after), interleaved, ``repeats`` times; the medians and the ratios are reported.
Nothing is asserted; the numbers are printed as a table and written as JSON.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from surrogate.io import write_json
from surrogate.threads import WAIT_KEYS

__all__ = ["POLICIES", "busy_loops", "run_bench", "time_fit"]

#: the environment each set-up adds to one without :data:`~surrogate.threads.WAIT_KEYS`
POLICIES: dict[str, dict[str, str]] = {"spin": {}, "passive": {"OMP_WAIT_POLICY": "PASSIVE"}}

# torch first: libgomp reads the environment once, when torch loads it, and the package sets
# OMP_WAIT_POLICY at its import where nothing has (this child measures the parent's choice)
_CHILD = """
import json, sys
import torch
threads, steps, n_gps = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
torch.set_num_threads(threads)
from surrogate.gp.settings import GPSettings
from surrogate.gp.training import fit_classifiers
gen = torch.Generator().manual_seed(0)
data = []
for i in range(n_gps):
    x = 10 * torch.rand(20_000, 1, generator=gen, dtype=torch.float64)
    p = torch.sigmoid(x[:, 0] - 5 + 0.1 * i)
    data.append((x, p, torch.bernoulli(p, generator=gen)))
settings = GPSettings(kernel="matern52", n_inducing=32, bins=100, epochs=steps)
fitted = fit_classifiers(data, settings, progress=False)
print(json.dumps({"train_s": fitted[0].train_seconds, "threads": torch.get_num_threads()}))
"""


@contextmanager
def busy_loops(n: int) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``n`` processes that loop forever (another job, a browser tab), stopped on exit (and
    ending by themselves once this process is gone: a benchmark killed leaves none)."""
    loop = "import os\nparent = os.getppid()\nwhile os.getppid() == parent: pass"
    procs = [subprocess.Popen([sys.executable, "-c", loop]) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def time_fit(policy: str, threads: int, steps: int, n_gps: int = 45) -> float:
    """Seconds of ``steps`` training steps of ``n_gps`` GPs side by side on ``threads`` torch
    threads, in a fresh process under the wait ``policy`` (a key of :data:`POLICIES`)."""
    env = {k: v for k, v in os.environ.items() if k not in WAIT_KEYS}
    env.update(POLICIES[policy])
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
    result = subprocess.run([sys.executable, "-c", _CHILD, str(threads), str(steps), str(n_gps)],
                            env=env, capture_output=True, text=True, check=True)  # fmt: skip
    return float(json.loads(result.stdout.strip().splitlines()[-1])["train_s"])


def run_bench(
    steps: int = 40,
    repeats: int = 3,
    busy: int = 2,
    policies: Sequence[str] = ("spin", "passive"),
    output: Path | None = None,
) -> dict[str, Any]:
    """Time every (load, policy, threads) set-up ``repeats`` times, interleaved (the machine's
    other work drifts); print the table, write JSON to ``output`` when given."""
    for p in policies:
        if p not in POLICIES:
            raise ValueError(f"policies: unknown policy {p!r}; allowed values are {list(POLICIES)}")
    walls: dict[str, list[float]] = {}
    loads: list[float] = []
    for _ in range(repeats):
        for n in sorted({0, busy}):
            with busy_loops(n):
                for policy in policies:
                    for threads in (1, 2):
                        key = f"busy={n} {policy} threads={threads}"
                        walls.setdefault(key, []).append(time_fit(policy, threads, steps))
                        print(f"{key}: {walls[key][-1]:.2f} s", file=sys.stderr, flush=True)
                loads.append(os.getloadavg()[0])
    result: dict[str, Any] = {
        "machine": {"cores": os.cpu_count(), "load_avg_1_during": loads,
                    "python": sys.version.split()[0]},
        "steps": steps, "repeats": repeats, "busy": busy,
        "median_s": {k: statistics.median(v) for k, v in walls.items()}, "walls_s": walls,
    }  # fmt: skip
    print(format_table(result))
    if output is not None:
        write_json(output, result)
    return result


def format_table(r: dict[str, Any]) -> str:
    """A plain-text table of a :func:`run_bench` result: medians, and 2 threads over 1."""
    med = r["median_s"]
    lines = [f"{r['steps']} training steps, median of {r['repeats']} (s); "
             f"cores {r['machine']['cores']}, 1-min load {r['machine']['load_avg_1_during']}",
             f"{'busy loops':>10s} {'policy':>8s} {'1 thread':>9s} {'2 threads':>9s} {'2 / 1':>6s}"]  # fmt: skip
    for n in sorted({int(k.split()[0].split("=")[1]) for k in med}):
        for policy in POLICIES:
            one, two = (med.get(f"busy={n} {policy} threads={t}") for t in (1, 2))
            if one is not None and two is not None:
                lines.append(f"{n:>10d} {policy:>8s} {one:9.2f} {two:9.2f} {two / one:6.2f}")
    return "\n".join(lines)
