"""Calibration store: versions, checksums, schema validation, rollback, and crash safety
(writers SIGKILLed at random points never leave a torn or invalid current calibration)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lightprobe.calibration.store import CalibrationStore, CorruptCalibration
from lightprobe.core.calibration import Calibration, Photometric, Pose
from lightprobe.core.errors import InputError

ROOT = Path(__file__).resolve().parent.parent


def _cal(k: float) -> Calibration:
    return Calibration(photometric=Photometric(k, "nit"), pose=Pose(np.eye(3), np.array([k, 0.0, 0.0])))


def test_save_load_history_and_rollback(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    with pytest.raises(CorruptCalibration, match="no current calibration"):
        store.load_current()
    assert store.load().calibration is None
    v1 = store.save(_cal(1.0))
    v2 = store.save(_cal(2.0))
    assert (v1.number, v2.number) == (1, 2)
    assert store.load_current().photometric.scale == 2.0
    assert [v.number for v in store.versions()] == [1, 2]
    back = store.rollback()
    assert back.number == 1
    assert store.load_current().photometric.scale == 1.0
    store.rollback(2)
    assert store.load_current().photometric.scale == 2.0
    with pytest.raises(InputError, match="no version 7"):
        store.rollback(7)
    # A save after a rollback gets a new number; history is never rewritten.
    store.rollback(1)
    v3 = store.save(_cal(3.0))
    assert v3.number == 3
    assert len(store.versions()) == 3


def test_corrupt_current_falls_back_to_previous(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.save(_cal(1.0))
    v2 = store.save(_cal(2.0))
    # Flip one byte: checksum mismatch, a clear error naming the file, previous version in use.
    data = bytearray(v2.path.read_bytes())
    i = data.index(b"2.0")
    data[i] = ord("5")
    v2.path.write_bytes(bytes(data))
    with pytest.raises(CorruptCalibration, match=v2.path.name + ".*checksum"):
        store.load_current()
    res = store.load()
    assert res.calibration is not None
    assert res.calibration.photometric.scale == 1.0
    assert res.version.number == 1
    assert any("checksum" in e for e in res.errors)


def test_schema_validation_on_load(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.save(_cal(1.0))
    v = store.save(_cal(2.0))
    bad = json.loads(v.path.read_text())
    bad["photometric"]["scale"] = -1.0  # schema violation; keep a matching checksum pointer
    blob = json.dumps(bad).encode()
    v.path.write_bytes(blob)
    import hashlib

    store.current_path.write_text(f"{v.path.name} {hashlib.sha256(blob).hexdigest()}\n")
    with pytest.raises(CorruptCalibration, match=r"photometric\.scale must be positive"):
        store.load_current()
    assert store.load().calibration.photometric.scale == 1.0
    # A garbage pointer is reported, and the newest valid version is used.
    store.current_path.write_text("not a pointer")
    with pytest.raises(CorruptCalibration, match="malformed pointer"):
        store.load_current()
    assert store.load().calibration.photometric.scale == 1.0


WRITER = """
import sys, time
import numpy as np
sys.path.insert(0, sys.argv[2])
from lightprobe.core.calibration import Calibration, Photometric, Pose
from lightprobe.calibration.store import CalibrationStore
store = CalibrationStore(sys.argv[1])
print("ready", flush=True)
k = 1.0
while True:
    k += 1.0
    store.save(Calibration(photometric=Photometric(k, "nit"), pose=Pose(np.eye(3), np.array([k, 0.0, 0.0]))))
"""


def test_sigkill_writers_never_tear_current(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.save(_cal(1.0))
    rng = np.random.default_rng(5)
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    deadline = time.monotonic() + 120
    last_number = 1
    iterations = 0
    for _ in range(60):
        proc = subprocess.Popen([sys.executable, str(script), str(tmp_path), str(ROOT)],
                                stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == "ready"
            time.sleep(float(rng.uniform(0.0, 0.03)))  # kill anywhere inside the write sequence
            os.kill(proc.pid, signal.SIGKILL)
        finally:
            proc.wait(timeout=10)
        assert proc.returncode == -signal.SIGKILL
        cal = store.load_current()  # must never raise: old or new pointer, never torn
        assert cal.photometric.unit == "nit"
        number = store.current_version().number
        assert number >= last_number  # never goes back to an older version
        last_number = number
        iterations += 1
        assert time.monotonic() < deadline, "SIGKILL test exceeded its time bound"
    assert iterations >= 50
    assert last_number > 1  # the writers did make progress between kills
    store.save(_cal(0.5))  # the next save sweeps leftover temp files
    assert not list(store.root.glob(".*.tmp"))
    assert not list(store.history_dir.glob(".*.tmp"))
    assert all(store.read_version(v) for v in store.versions())
