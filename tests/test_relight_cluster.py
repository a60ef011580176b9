"""The cut precompute on a real Dask cluster (a scheduler and two worker processes on loopback).

Acceptance of #19: the cluster's cut file is byte-identical to the in-process one, also when a
worker is SIGKILLed mid-run; an interrupted run redoes only the chunks that were missing.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("embreex")
distributed = pytest.importorskip("distributed")

from lightprobe.hostlink.relight.cuts import precompute as pre_mod  # noqa: E402
from lightprobe.hostlink.relight.scene import load_scene  # noqa: E402
from tests.test_relight_scene import write_scene  # noqa: E402

PARAMS = {"spheres": 6, "grid": 8}


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("cluster-scene")
    # 41 x 41 ground vertices + the cube: 7 SVC chunks, 6 VCF chunks
    return load_scene(write_scene(d, ground={"y": "auto", "size": 4.0, "resolution": 40, "material": "floor"}))


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory: pytest.TempPathFactory) -> bytes:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("cluster-ref")
    pc = pre_mod.precompute(scene, cache_dir=d, progress=False, **PARAMS)
    assert not pc.cached
    (f,) = d.glob("*.npz")
    return f.read_bytes()


@pytest.fixture(scope="module")
def client() -> Iterator[object]:
    from lightprobe.hostlink.relight.cuts.cluster import connect

    with connect("local", workers=2) as c:  # a real scheduler and 2 worker processes on loopback
        yield c


def _only_file(d: Path) -> bytes:
    (f,) = d.glob("*.npz")
    return f.read_bytes()


def test_the_chunking_covers_every_vertex_and_point(scene) -> None:  # type: ignore[no-untyped-def]
    job = pre_mod.make_job(scene, cfg=(6, 8, 1.2, 10.0))
    chunks = job.chunks()
    svc = sorted((g, lo, hi) for k, g, lo, hi in chunks if k == "svc")
    assert sum(hi - lo for _, lo, hi in svc) == len(job.vertices)
    assert sum(hi - lo for k, _, lo, hi in chunks if k == "vcf") == 6 * 6 * 8 * 8
    assert len(svc) >= 7


def test_the_same_cuts_are_the_same_bytes(scene, reference: bytes, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    again = pre_mod.precompute(scene, cache_dir=tmp_path, progress=False, **PARAMS)
    assert _only_file(tmp_path) == reference
    assert not (tmp_path / f"{pre_mod.make_job(scene, cfg=(6, 8, 1.2, 10.0)).key}.chunks").exists()
    cached = pre_mod.precompute(scene, cache_dir=tmp_path, progress=False, **PARAMS)
    assert cached.cached
    assert cached.seconds == pytest.approx(again.seconds)


def test_two_dask_workers_give_the_in_process_cut_file(scene, reference: bytes, client,  # type: ignore[no-untyped-def]
                                                       tmp_path: Path) -> None:
    pre_mod.precompute(scene, cache_dir=tmp_path, progress=False, cluster=client, **PARAMS)
    assert _only_file(tmp_path) == reference
    assert len(client.scheduler_info()["workers"]) == 2


def test_a_worker_killed_mid_run_changes_nothing(scene, reference: bytes, client,  # type: ignore[no-untyped-def]
                                                 tmp_path: Path) -> None:
    job = pre_mod.make_job(scene, cfg=(6, 8, 1.2, 10.0))
    cdir = pre_mod.chunk_dir(tmp_path, job.key)
    pids = client.run(os.getpid)
    killed: list[int] = []

    def kill_when_started() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # the first chunk is back: the others are running
            if cdir.is_dir() and any(cdir.glob("*.npz")):
                victim = sorted(pids.values())[0]
                os.kill(victim, signal.SIGKILL)
                killed.append(victim)
                return
            time.sleep(0.005)

    t = threading.Thread(target=kill_when_started)
    t.start()
    pre_mod.precompute(scene, cache_dir=tmp_path, progress=False, cluster=client, **PARAMS)
    t.join()
    assert killed, "the run ended before a worker could be killed"
    left = len(list(tmp_path.glob("*.chunks")))
    assert left == 0
    assert _only_file(tmp_path) == reference
    client.wait_for_workers(2, timeout=30)  # the nanny restarts the killed worker


def test_an_interrupted_run_redoes_only_the_missing_chunks(scene, reference: bytes, tmp_path: Path,  # type: ignore[no-untyped-def]
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    real = pre_mod.run_chunk
    calls: list[tuple[str, int, int, int]] = []

    def failing(job, chunk):  # type: ignore[no-untyped-def]
        if len(calls) == 5:
            raise KeyboardInterrupt  # the user's ^C, or the machine going down
        calls.append(chunk)
        return real(job, chunk)

    monkeypatch.setattr(pre_mod, "run_chunk", failing)
    with pytest.raises(KeyboardInterrupt):
        pre_mod.precompute(scene, cache_dir=tmp_path, progress=False, **PARAMS)
    assert not list(tmp_path.glob("*.npz"))
    first = list(calls)
    calls.clear()

    def counting(job, chunk):  # type: ignore[no-untyped-def]
        calls.append(chunk)
        return real(job, chunk)

    monkeypatch.setattr(pre_mod, "run_chunk", counting)
    pre_mod.precompute(scene, cache_dir=tmp_path, progress=False, **PARAMS)
    total = len(pre_mod.make_job(scene, cfg=(6, 8, 1.2, 10.0)).chunks())
    assert len(first) == 5
    assert len(calls) == total - 5
    assert not set(calls) & set(first)
    assert _only_file(tmp_path) == reference


def test_precompute_on_is_checked() -> None:
    from lightprobe.core.errors import InputError
    from lightprobe.hostlink.relight.cuts.cluster import resolve

    assert resolve(None) in (None, os.environ.get("DASK_SCHEDULER_ADDRESS"))
    assert resolve("local") == "local"
    assert resolve("tcp://10.0.0.5:8786") == "tcp://10.0.0.5:8786"
    with pytest.raises(InputError, match="--precompute-on"):
        resolve("10.0.0.5:8786")
