"""numba's threading layer (device/threads.py): the service runs parallel kernels from several
threads at once, which numba's ``workqueue`` layer answers by aborting the process. Shown here
for real: the same two-thread script aborts under ``workqueue`` and runs under the layer every
``lightprobe`` command asks for; a missing layer is a clear error naming the library."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from lightprobe.device.threads import ThreadingLayerError, require_threadsafe, select

ROOT = Path(__file__).resolve().parents[1]

# two threads launching parallel kernels at once, as the pipeline and the tables' thread do
SCRIPT = """
import sys, threading
import numpy as np
sys.argv = ["x"]
from lightprobe.device.threads import select
if {select!r}:
    select()
import numba

@numba.njit(parallel=True, nogil=True)
def f(a):
    for i in numba.prange(a.shape[0]):
        a[i] = a[i] * 0.5 + i
    return a

f(np.zeros(8))
def run():
    a = np.zeros(20000)
    for _ in range(300):
        f(a)
ts = [threading.Thread(target=run) for _ in range(2)]
[t.start() for t in ts]
[t.join() for t in ts]
print(numba.threading_layer())
"""


def _run(select_layer: bool, env_layer: str | None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    if env_layer is not None:
        env["NUMBA_THREADING_LAYER"] = env_layer
    env["PYTHONPATH"] = str(ROOT)
    return subprocess.run([sys.executable, "-c", SCRIPT.format(select=select_layer)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)


def test_two_threads_launching_kernels_run_under_the_chosen_layer() -> None:
    r = _run(True, None)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() in ("omp", "tbb")
    # an installer's environment saying workqueue is overridden, not obeyed
    r = _run(True, "workqueue")
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() in ("omp", "tbb")


def test_workqueue_aborts_the_same_script() -> None:
    """What the layer choice prevents (and what makes the test above able to fail)."""
    r = _run(False, "workqueue")
    assert r.returncode != 0
    assert "Concurrent access has been detected" in r.stderr


def test_select_keeps_a_safe_choice_and_replaces_an_unsafe_one() -> None:
    for asked in ("omp", "tbb", "threadsafe", "safe"):
        env = {"NUMBA_THREADING_LAYER": asked}
        assert select(env) == asked
        assert env["NUMBA_THREADING_LAYER"] == asked
    for asked in ("workqueue", "default", ""):
        env = {"NUMBA_THREADING_LAYER": asked}
        assert select(env) == "threadsafe"
        assert env["NUMBA_THREADING_LAYER"] == "threadsafe"
    env = {}
    assert select(env) == "threadsafe"


def test_no_layer_is_an_error_naming_the_library() -> None:
    def launch() -> None:  # what numba raises when neither OpenMP nor TBB loads
        raise ValueError("No threading layer could be loaded.\nHINT: ...")

    with pytest.raises(ThreadingLayerError, match="libgomp1") as e:
        require_threadsafe(launch)
    assert "No threading layer could be loaded" in str(e.value)


def test_this_process_runs_a_safe_layer() -> None:
    assert require_threadsafe() in ("omp", "tbb")
