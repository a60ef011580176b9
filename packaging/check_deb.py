"""Install the Debian package in a clean Debian 12 root and run its service (``make deb-check``).

For each architecture asked (``--arch amd64``, ``--arch arm64``): a minimal bookworm root made
with ``mmdebstrap`` (``python3`` and what the package depends on), the package installed in it
with ``dpkg -i`` (its postinst compiles the numba kernels: an abort there fails the check), then
the unit's ``ExecStart`` line run in the root with the unit's environment, on ``--camera
v4l2-fake`` and on ``--camera sim``, until first lights and ``--frames`` frames; the published
lights are read over HTTP, the service stopped with SIGTERM (exit 0 asserted). Natively, the
package's life follows (:func:`lifecycle`): upgraded over itself, removed, purged, with the
state and an edited conffile kept until the purge. arm64 runs under
QEMU user-mode emulation: binfmt_misc with ``qemu-aarch64`` (Debian's ``qemu-user-static``,
registered with the ``F`` flag, so it runs inside the root); when the machine cannot register it,
the check says so and skips arm64 (exit 0 with ``--allow-skip``, else 77).

The lights of each run on arm64 are compared with the same run's on amd64 (the package
installed the same way): every channel of the lights' total ``rgb`` within ``--tolerance``
(relative) and their luminance-weighted mean direction within 2 degrees (the simulator runs its
static ``room`` scene, so that runs at different frame rates compare). Emulation is not a board's
speed: the wall times printed are the emulator's. Writes a JSON report (``--report``).

Needs root (chroot, mounts), ``mmdebstrap`` and network access to Debian's archive.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DEPENDS = ["python3", "libgomp1", "ca-certificates"]


def log(msg: str) -> None:
    print(f"[check_deb {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def binfmt_ready(arch: str) -> str | None:
    """None when ``arch`` binaries run here (native, or binfmt + qemu), else why not."""
    if arch == "amd64":
        return None if os.uname().machine == "x86_64" else "not an x86-64 machine"
    if os.uname().machine == "aarch64":
        return None
    entry = Path("/proc/sys/fs/binfmt_misc/qemu-aarch64")
    if not Path("/proc/sys/fs/binfmt_misc/register").exists():
        with contextlib.suppress(Exception):
            subprocess.run(["mount", "binfmt_misc", "-t", "binfmt_misc", "/proc/sys/fs/binfmt_misc"],
                           check=True, capture_output=True)
    if not entry.exists() and shutil.which("update-binfmts"):
        subprocess.run(["update-binfmts", "--enable", "qemu-aarch64"], capture_output=True)
    if not entry.exists():
        return "binfmt_misc has no qemu-aarch64 entry (install qemu-user-static and binfmt-support)"
    text = entry.read_text()
    if not text.startswith("enabled"):
        return "binfmt_misc's qemu-aarch64 entry is disabled"
    if not re.search(r"^flags:.*F", text, re.M):
        return "binfmt_misc's qemu-aarch64 entry lacks the F flag (the interpreter is not found inside a root)"
    return None


def make_root(arch: str, dest: Path) -> float:
    t0 = time.monotonic()
    shutil.rmtree(dest, ignore_errors=True)
    dest.parent.mkdir(parents=True, exist_ok=True)
    cmd = ["mmdebstrap", f"--arch={arch}", "--variant=minbase", f"--include={','.join(DEPENDS)}",
           "--quiet", "bookworm", str(dest), "http://deb.debian.org/debian"]
    log(" ".join(cmd))
    subprocess.run(cmd, check=True)
    return time.monotonic() - t0


@contextlib.contextmanager
def mounted(root: Path) -> Iterator[None]:
    done: list[Path] = []
    try:
        for src, rel, args in (("proc", "proc", ["-t", "proc"]), ("sysfs", "sys", ["-t", "sysfs"]),
                               ("/dev", "dev", ["--bind"]), ("/dev/pts", "dev/pts", ["--bind"])):
            target = root / rel
            target.mkdir(parents=True, exist_ok=True)
            subprocess.run(["mount", *args, src, str(target)], check=True)
            done.append(target)
        yield
    finally:
        for target in reversed(done):
            subprocess.run(["umount", "-l", str(target)], check=False)


def install(root: Path, deb: Path) -> float:
    shutil.copy(deb, root / "tmp" / deb.name)
    t0 = time.monotonic()
    r = subprocess.run(["chroot", str(root), "dpkg", "-i", f"/tmp/{deb.name}"], capture_output=True, text=True)
    took = time.monotonic() - t0
    sys.stdout.write(r.stdout[-4000:])
    if r.returncode != 0 or "Concurrent access has been detected" in r.stderr + r.stdout:
        sys.stderr.write(r.stderr[-6000:])
        raise RuntimeError(f"dpkg -i {deb.name} failed (exit {r.returncode})")
    (root / "tmp" / deb.name).unlink()
    return took


def lifecycle(root: Path, deb: Path) -> dict[str, Any]:
    """Upgrade, removal and purge, as an installer meets them: the unit's state (token, config,
    calibrations in ``/var/lib/private/lightprobe``) and an edited ``/etc/default/lightprobe``
    survive an upgrade (the package installed over itself) and a removal; the removal leaves
    nothing of the package's own files (the compiled caches included); a purge deletes the state."""
    state = root / "var/lib/private/lightprobe"
    marks = {"token": "t0ken\n", "config.toml": "[probe]\nname = \"Hall\"\n",
             "calibration/history/0001.json": "{}\n"}
    for rel, text in marks.items():
        (state / rel).parent.mkdir(parents=True, exist_ok=True)
        (state / rel).write_text(text)
    default = root / "etc/default/lightprobe"
    default.write_text(default.read_text().replace("LIGHTPROBE_CAMERA=auto", "LIGHTPROBE_CAMERA=v4l2:/dev/video2"))

    def dpkg(*args: str) -> None:
        r = subprocess.run(["chroot", str(root), "dpkg", "--force-confold", *args], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"dpkg {' '.join(args)} failed: {r.stderr[-3000:]}")

    def kept() -> bool:
        return all((state / rel).is_file() and (state / rel).read_text() == text for rel, text in marks.items())

    out: dict[str, Any] = {}
    shutil.copy(deb, root / "tmp" / deb.name)
    t0 = time.monotonic()
    dpkg("-i", f"/tmp/{deb.name}")  # an upgrade: configure with the old version as $2
    out["upgrade_s"] = round(time.monotonic() - t0, 1)
    out["upgrade_keeps_state"] = kept()
    out["upgrade_keeps_edited_conffile"] = "LIGHTPROBE_CAMERA=v4l2:/dev/video2" in default.read_text()
    dpkg("-r", "lightprobe")
    out["remove_keeps_state"] = kept()
    leftover = sorted(str(p.relative_to(root)) for p in (root / "usr/lib/lightprobe").rglob("*")) \
        if (root / "usr/lib/lightprobe").exists() else []
    out["remove_leaves"] = leftover[:5]
    dpkg("-P", "lightprobe")
    out["purge_deletes_state"] = not state.exists() and not default.exists()
    (root / "tmp" / deb.name).unlink()
    out["ok"] = bool(out["upgrade_keeps_state"] and out["upgrade_keeps_edited_conffile"] and out["remove_keeps_state"]
                     and not leftover and out["purge_deletes_state"])
    return out


def unit_command(root: Path, camera: str, port: int) -> tuple[list[str], dict[str, str]]:
    """The installed unit's ExecStart and Environment, as systemd would run them (``%S`` =
    /var/lib, the camera and the port substituted)."""
    unit = (root / "lib/systemd/system/lightprobe.service").read_text()
    env = {"PATH": "/usr/local/bin:/usr/bin:/bin", "STATE_DIRECTORY": "/var/lib/lightprobe",
           "CONFIGURATION_DIRECTORY": "/etc/lightprobe", "HOME": "/var/lib/lightprobe"}
    for m in re.finditer(r"^Environment=(\w+)=(.*)$", unit, re.M):
        env[m.group(1)] = m.group(2).replace("%S", "/var/lib")
    env["LIGHTPROBE_CAMERA"] = camera
    start = re.search(r"^ExecStart=(.*)$", unit, re.M)
    assert start is not None
    line = start.group(1).replace("${LIGHTPROBE_CAMERA}", camera).replace("--port 8080", f"--port {port}")
    line = line.replace("--host 0.0.0.0", "--host 127.0.0.1")
    cmd = line.split()
    if camera == "sim":  # a static scene: the lights of two runs compare whatever frame each is at
        cmd += ["--scene", "room"]
    return cmd, env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _get(url: str, token: str | None = None, timeout: float = 10.0) -> tuple[int, bytes]:
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return int(r.status), r.read()
    except urllib.error.HTTPError as e:
        return int(e.code), e.read()


def run_service(root: Path, camera: str, frames: int, timeout: float) -> dict[str, Any]:
    port = _free_port()
    cmd, env = unit_command(root, camera, port)
    state = root / "var/lib/lightprobe"
    shutil.rmtree(state, ignore_errors=True)
    state.mkdir(parents=True)
    log(f"{camera}: chroot {root.name} {' '.join(cmd)}")
    t0 = time.monotonic()
    p = subprocess.Popen(["chroot", str(root), "/usr/bin/env", "-i", *[f"{k}={v}" for k, v in env.items()], *cmd],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    base = f"http://127.0.0.1:{port}/api/v1"
    out: dict[str, Any] = {"camera": camera}
    try:
        first = None
        while time.monotonic() - t0 < timeout:
            if p.poll() is not None:
                raise RuntimeError(f"the service exited ({p.returncode}) before first lights: "
                                   f"{(p.stderr.read() if p.stderr else '')[-3000:]}")
            with contextlib.suppress(OSError):
                code, body = _get(base + "/lights", timeout=5)
                if code == 200 and first is None:
                    first = time.monotonic() - t0
                    log(f"{camera}: first lights after {first:.1f} s")
                if first is not None:
                    code, body = _get(base + "/status", timeout=5)
                    st = json.loads(body)
                    if st.get("frames", 0) >= frames:
                        break
            time.sleep(0.5)
        else:
            raise RuntimeError(f"{camera}: no {frames} frames within {timeout:.0f} s")
        code, body = _get(base + "/lights", timeout=10)
        out.update(first_lights_s=round(first or 0.0, 2), frames=st["frames"], lights=json.loads(body),
                   threading_layer=st.get("threading_layer"), model=st.get("probe", {}).get("model"),
                   camera_driver=st.get("camera", {}).get("driver"), fps=st.get("fps"))
    finally:
        t_stop = time.monotonic()
        p.send_signal(signal.SIGTERM)
        try:
            rc = p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            rc = p.wait(10)
        out.update(stop_s=round(time.monotonic() - t_stop, 2), exit=rc)
    if rc != 0:
        raise RuntimeError(f"{camera}: the service exited {rc} on SIGTERM: {(p.stderr.read() if p.stderr else '')[-3000:]}")
    return out


def summary(lights: dict[str, Any]) -> tuple[list[float], list[float]]:
    """The lights' total rgb and their luminance-weighted mean direction (a set's many lights of
    similar power make "the brightest one" a coin toss; their mean is stable)."""
    ls = lights["lights"]
    total = [sum(float(light["rgb"][c]) for light in ls) for c in range(3)]
    lum = [0.2126 * light["rgb"][0] + 0.7152 * light["rgb"][1] + 0.0722 * light["rgb"][2] for light in ls]
    mean = [sum(w * float(light["direction"][k]) for w, light in zip(lum, ls, strict=True)) for k in range(3)]
    return total, mean


def compare(ref: dict[str, Any], got: dict[str, Any], tol: float) -> dict[str, Any]:
    (t0, d0), (t1, d1) = summary(ref["lights"]), summary(got["lights"])
    rel = [abs(a - b) / max(abs(a), 1e-12) for a, b in zip(t0, t1, strict=True)]
    cosang = sum(a * b for a, b in zip(d0, d1, strict=True)) / (math.hypot(*d0) * math.hypot(*d1))
    ang = math.degrees(math.acos(max(-1.0, min(1.0, cosang))))
    return {"total_rgb_ref": t0, "total_rgb": t1, "rel_diff": rel, "mean_direction_angle_deg": ang,
            "ok": max(rel) <= tol and ang <= 2.0}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="check_deb.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--arch", action="append", choices=["amd64", "arm64"])
    p.add_argument("--dist", type=Path, default=ROOT / "dist")
    p.add_argument("--work", type=Path, default=ROOT / "build" / "deb-check")
    p.add_argument("--camera", action="append", default=None, help="cameras to run (default v4l2-fake and sim)")
    p.add_argument("--frames", type=int, default=30, help="frames to run before reading the lights")
    p.add_argument("--tolerance", type=float, default=0.01, help="relative, on each channel of the total rgb")
    p.add_argument("--report", type=Path, default=None)
    p.add_argument("--allow-skip", action="store_true", help="exit 0 when arm64 cannot run here (CI)")
    a = p.parse_args(argv)
    if os.geteuid() != 0:
        print("check_deb.py: error: needs root (chroot, mounts)", file=sys.stderr)
        return 2
    if shutil.which("mmdebstrap") is None:
        print("check_deb.py: error: mmdebstrap not found (apt install mmdebstrap)", file=sys.stderr)
        return 2
    arches = a.arch or ["amd64", "arm64"]
    cameras = a.camera or ["v4l2-fake", "sim"]
    report: dict[str, Any] = {"machine": os.uname().machine, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                              "runs": {}, "skipped": {}}
    failed = False
    for arch in arches:
        why = binfmt_ready(arch)
        if why is not None:
            log(f"{arch}: cannot run here: {why}")
            report["skipped"][arch] = why
            continue
        debs = sorted(a.dist.glob(f"lightprobe_*_{arch}.deb"))
        if not debs:
            print(f"check_deb.py: error: no lightprobe_*_{arch}.deb in {a.dist} (make deb)", file=sys.stderr)
            return 2
        root = a.work / f"root-{arch}"
        t0 = time.monotonic()
        entry: dict[str, Any] = {"deb": debs[-1].name, "emulated": arch != "amd64" and os.uname().machine != "aarch64"}
        try:
            entry["root_s"] = round(make_root(arch, root), 1)
            with mounted(root):
                entry["install_s"] = round(install(root, debs[-1]), 1)
                log(f"{arch}: installed in {entry['install_s']} s (postinst compiled the kernels)")
                entry["services"] = [run_service(root, cam, a.frames, 1800.0) for cam in cameras]
                if not entry["emulated"]:  # a reinstall compiles the kernels again: natively only
                    entry["lifecycle"] = lifecycle(root, debs[-1])
                    log(f"{arch}: upgrade, remove, purge: {entry['lifecycle']}")
                    failed = failed or not entry["lifecycle"]["ok"]
        except Exception as e:  # the report says which step
            entry["error"] = f"{type(e).__name__}: {e}"
            log(f"{arch}: FAILED: {entry['error']}")
            failed = True
        entry["wall_s"] = round(time.monotonic() - t0, 1)
        report["runs"][arch] = entry
    if "amd64" in report["runs"] and "arm64" in report["runs"]:
        ref = {s["camera"]: s for s in report["runs"]["amd64"].get("services", [])}
        cmp = {}
        for s in report["runs"]["arm64"].get("services", []):
            if s["camera"] in ref:
                cmp[s["camera"]] = compare(ref[s["camera"]], s, a.tolerance)
                failed = failed or not cmp[s["camera"]]["ok"]
        report["arm64_vs_amd64"] = cmp
    for run in report["runs"].values():
        for s in run.get("services", []):
            s["lights"] = {"count": len(s["lights"]["lights"]), "total_rgb": summary(s["lights"])[0]}
            failed = failed or s.get("threading_layer") not in ("omp", "tbb")
    text = json.dumps(report, indent=2)
    print(text)
    if a.report is not None:
        a.report.parent.mkdir(parents=True, exist_ok=True)
        a.report.write_text(text + "\n")
    if failed:
        return 1
    if report["skipped"] and not a.allow_skip:
        return 77
    return 0


if __name__ == "__main__":
    sys.exit(main())
