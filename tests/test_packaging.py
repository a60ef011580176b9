"""The Debian package's recipe (packaging/build_deb.py) and its check (packaging/check_deb.py),
the parts that need no network or root: the maintainer scripts parse, the unit's command as the
check runs it, the man page lists every command. ``make deb`` builds the packages and ``make
deb-check`` installs them in clean Debian 12 roots (arm64 under QEMU): CI runs both after the suite."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "packaging"))

import build_deb  # noqa: E402
import check_deb  # noqa: E402


@pytest.mark.parametrize("name", ["POSTINST", "PRERM", "POSTRM"])
def test_maintainer_scripts_parse(name: str, tmp_path: Path) -> None:
    script = tmp_path / name.lower()
    script.write_text(getattr(build_deb, name))
    shell = shutil.which("dash") or "/bin/sh"  # Debian runs maintainer scripts with /bin/sh (dash)
    r = subprocess.run([shell, "-n", str(script)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    text = script.read_text()
    assert text.startswith("#!/bin/sh\n")
    assert "set -e" in text


def test_postinst_compiles_the_kernels_and_purge_alone_deletes_the_state() -> None:
    assert "warm-kernels" in build_deb.POSTINST
    assert "env -u NUMBA_CACHE_DIR" in build_deb.POSTINST  # into the install's own cache
    # removal keeps token, config and calibrations; only purge deletes them
    before, purge = build_deb.POSTRM.split('if [ "$1" = purge ]; then', 1)
    block = purge.split("\nfi\n", 1)[0]  # the purge branch, to its own closing fi
    assert "rm -rf /var/lib/private/lightprobe" in block
    assert "/var/lib/private/lightprobe" not in before
    assert "/var/lib" not in build_deb.PRERM


def test_the_check_runs_the_units_own_command(tmp_path: Path) -> None:
    unit = tmp_path / "lib/systemd/system/lightprobe.service"
    unit.parent.mkdir(parents=True)
    shutil.copy(ROOT / "systemd/lightprobe.service", unit)
    cmd, env = check_deb.unit_command(tmp_path, "v4l2-fake", 12345)
    assert cmd[:3] == ["/usr/bin/env", "lightprobe", "serve"]
    assert cmd[cmd.index("--camera") + 1] == "v4l2-fake"
    assert cmd[cmd.index("--port") + 1] == "12345"
    assert cmd[cmd.index("--host") + 1] == "127.0.0.1"
    assert env["NUMBA_CACHE_DIR"] == "/var/lib/lightprobe/cache/numba"  # %S substituted
    assert env["MALLOC_ARENA_MAX"] == "2"


def test_man_page_lists_every_command() -> None:
    from lightprobe.cli import COMMANDS

    page = build_deb._manpage("0.1.0")
    for name in COMMANDS:
        assert f"\\fB{name}\\fR" in page, name
    if shutil.which("groff"):
        r = subprocess.run(["groff", "-man", "-Tutf8", "-ww", "-z"], input=page, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        assert not r.stderr.strip(), r.stderr


def test_lights_comparison_tolerates_rounding_and_catches_a_change() -> None:
    def lights(scale: float, d: tuple[float, float, float]) -> dict[str, object]:
        return {"lights": {"lights": [{"rgb": [1.0 * scale, 2.0, 3.0], "direction": list(d)},
                                      {"rgb": [0.1, 0.1, 0.1], "direction": [1.0, 0.0, 0.0]}]}}

    ref = lights(1.0, (0.0, 1.0, 0.0))
    assert check_deb.compare(ref, lights(1.0 + 1e-6, (0.0, 1.0, 1e-5)), 0.01)["ok"]
    assert not check_deb.compare(ref, lights(1.05, (0.0, 1.0, 0.0)), 0.01)["ok"]
    assert not check_deb.compare(ref, lights(1.0, (0.0, 1.0, 0.12)), 0.01)["ok"]  # the mean turns ~6 degrees
