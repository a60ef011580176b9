"""Build the Debian package of the probe service: ``lightprobe_<version>_<arch>.deb`` (``make deb``).

What the package holds (the same recipe for amd64 and arm64):

- ``/usr/lib/lightprobe``: a virtual environment of its own over Debian's ``python3`` (3.11,
  bookworm): ``pyvenv.cfg``, ``bin/python3`` -> ``/usr/bin/python3.11``, and in
  ``lib/python3.11/site-packages`` the service (``lightprobe[probe]``, built from this
  repository as a wheel) with every dependency as the package index's wheel *for the target
  architecture* (``pip install --platform ... --only-binary=:all:``): the unit needs no compiler
  and no network at install.
- ``/usr/bin/lightprobe``: the command (a two-line script in the package, not made by a
  maintainer script).
- ``/lib/systemd/system/lightprobe.service``: the unit (``systemd/lightprobe.service``),
  enabled and started at install; ``/etc/default/lightprobe`` (a conffile: the camera).
- ``postinst``: compiles the bytecode and every numba kernel once (``lightprobe warm-kernels``,
  into the install's own cache, which the unit copies into its state directory at start); the
  state (token, config, calibrations: ``/var/lib/private/lightprobe`` under the unit's dynamic
  user) is never touched by an upgrade or a removal, only by a purge.
- ``Depends``: ``python3 (>= 3.11), python3 (<< 3.12)``, ``libgomp1`` (numba's thread-safe
  OpenMP layer: without it numba falls back to ``workqueue``, which aborts the process:
  :mod:`lightprobe.device.threads`), ``libc6 (>= 2.28)`` (the wheels' manylinux floor).

Usage: ``python packaging/build_deb.py --arch amd64|arm64 [--out dist] [--work build/deb]``.
Needs ``dpkg-deb`` and network access to the package index (wheels are cached in
``<work>/wheels-<arch>``). Exit 2 on a bad argument, 1 when a step fails (its output says which).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARCHES = {"amd64": "x86_64", "arm64": "aarch64"}
PYVER = "3.11"  # Debian 12's python3
# the wheels' platform tags a Debian 12 system (glibc 2.36) runs
GLIBC_TAGS = [f"manylinux_2_{m}" for m in range(17, 37)]
PREFIX = "/usr/lib/lightprobe"  # not /opt: Debian policy (lintian dir-or-file-in-opt)


def version() -> str:
    return str(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"])


def _run(cmd: list[str], **kw: object) -> None:
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, **kw)  # type: ignore[call-overload]


def build_wheel(work: Path) -> Path:
    """The service's wheel (pure Python), built from this checkout."""
    out = work / "wheel"
    shutil.rmtree(out, ignore_errors=True)
    _run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(out), str(ROOT)])
    wheels = sorted(out.glob("lightprobe-*.whl"))
    if len(wheels) != 1:
        raise RuntimeError(f"expected one lightprobe wheel in {out}, found {wheels}")
    return wheels[0]


def install_site(wheel: Path, arch: str, site: Path, cache: Path) -> None:
    """``lightprobe[probe]`` and its dependencies, the target architecture's wheels, into ``site``."""
    machine = ARCHES[arch]
    plats = [f"{t}_{machine}" for t in GLIBC_TAGS] + [f"manylinux2014_{machine}", "any"]
    cmd = [sys.executable, "-m", "pip", "install", "--quiet", "--no-compile", "--target", str(site),
           "--only-binary=:all:", "--python-version", PYVER, "--implementation", "cp", "--abi", "cp311",
           "--abi", "abi3", "--abi", "none", "--cache-dir", str(cache)]
    for p in plats:
        cmd += ["--platform", p]
    _run([*cmd, f"{wheel}[probe]"])
    # console scripts pip wrote name the build machine's Python: the package has its own command
    shutil.rmtree(site / "bin", ignore_errors=True)
    for lib in site.rglob("*.so*"):  # shared objects are not programs (lintian shared-library-is-executable)
        if lib.is_file() and not lib.is_symlink():
            lib.chmod(0o644)


def _write(path: Path, text: str, mode: int = 0o644) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(mode)


def stage(arch: str, work: Path) -> Path:
    ver = version()
    root = work / f"lightprobe_{ver}_{arch}"
    shutil.rmtree(root, ignore_errors=True)
    venv = root / PREFIX.lstrip("/")
    site = venv / "lib" / f"python{PYVER}" / "site-packages"
    install_site(build_wheel(work), arch, site, work / "pip-cache")
    _write(venv / "pyvenv.cfg", f"home = /usr/bin\ninclude-system-site-packages = false\nversion = {PYVER}\n"
                                f"executable = /usr/bin/python{PYVER}\n")
    (venv / "bin").mkdir(parents=True, exist_ok=True)
    # relative inside /usr (Debian policy; lintian absolute-symlink-in-top-level-folder)
    os.symlink(os.path.relpath(f"/usr/bin/python{PYVER}", f"{PREFIX}/bin"), venv / "bin" / "python3")
    os.symlink("python3", venv / "bin" / "python")
    _write(root / "usr/bin/lightprobe",
           f"#!/bin/sh\n# lightprobe (Debian package): the service's own environment in {PREFIX}\n"
           f"exec {PREFIX}/bin/python3 -m lightprobe.cli \"$@\"\n", 0o755)
    unit = (ROOT / "systemd/lightprobe.service").read_text()
    _head, sep, body = unit.partition("# Token:")  # the repository's install notes, not the package's
    if sep:
        unit = "# lightprobe probe service (the Debian package's unit; override with systemctl edit).\n" + sep + body
    _write(root / "lib/systemd/system/lightprobe.service", unit)
    _write(root / "etc/default/lightprobe",
           "# lightprobe service options (read by lightprobe.service; kept across upgrades)\n"
           "# The camera: auto (the first UVC/V4L2 or libcamera camera found), libcamera, v4l2:/dev/videoN,\n"
           "# uvc, or v4l2-fake / sim to try the service without a camera. `lightprobe cameras --check` lists them.\n"
           "LIGHTPROBE_CAMERA=auto\n")
    doc = root / "usr/share/doc/lightprobe"
    _write(doc / "README.md", (ROOT / "README.md").read_text())
    _gzip(doc / "changelog.gz", _debian_changelog(ver).encode())  # a native package's: Debian's format
    _gzip(doc / "CHANGELOG.md.gz", (ROOT / "CHANGELOG.md").read_bytes())  # the project's own
    _gzip(root / "usr/share/man/man1/lightprobe.1.gz", _manpage(ver).encode())
    _write(root / "usr/share/lintian/overrides/lightprobe", OVERRIDES.replace("@PREFIX@", PREFIX.lstrip("/")))
    _write(doc / "copyright",
           "Format: https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/\n"
           "Upstream-Name: lightprobe\n\nFiles: *\nCopyright: 2026 lightprobe developers\nLicense: Apache-2.0\n"
           " On Debian systems the full text is in /usr/share/common-licenses/Apache-2.0.\n\n"
           f"Files: {PREFIX}/lib/python{PYVER}/site-packages/*\nCopyright: their authors\n"
           "License: various (each package's dist-info holds its license; none is GPL)\n")
    _control(root, arch, ver)
    return root


def _gzip(path: Path, data: bytes) -> None:
    """gzip -9n: no name, no timestamp (reproducible; lintian package-contains-timestamped-gzip)."""
    import gzip

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f, gzip.GzipFile(filename="", mode="wb", compresslevel=9, fileobj=f, mtime=0) as z:
        z.write(data)
    path.chmod(0o644)


def _manpage(ver: str) -> str:
    """lightprobe(1): the commands, from the CLI's own table."""
    from lightprobe.cli import COMMANDS  # the build runs in the project's environment

    rows = [(name, help_) for name, (_m, help_) in COMMANDS.items()]
    out = [f'.TH LIGHTPROBE 1 "" "lightprobe {ver}" "User Commands"', ".SH NAME",
           "lightprobe \\- live HDR light probe: service, calibration and tools",
           ".SH SYNOPSIS", ".B lightprobe", "\\fICOMMAND\\fR [\\fIOPTIONS\\fR]", ".SH DESCRIPTION",
           "The probe service and its tools. Every command takes \\fB\\-\\-help\\fR.",
           "Exit status: 0 success, 1 failure, 2 bad input (the message names the file or parameter).",
           ".SH COMMANDS"]
    for name, help_ in rows:
        out += [".TP", f"\\fB{name}\\fR", help_.replace("-", "\\-")]
    out += [".SH FILES", ".TP", "/var/lib/private/lightprobe", "the service's state: token, config.toml, calibrations",
            ".TP", "/etc/default/lightprobe", "the camera the unit opens (LIGHTPROBE_CAMERA)",
            ".SH SEE ALSO", "/usr/share/doc/lightprobe/README.md"]
    return "\n".join(out) + "\n"


def _debian_changelog(ver: str) -> str:
    """The package's changelog entry, dated by the commit it is built from (reproducible)."""
    r = subprocess.run(["git", "log", "-1", "--date=format:%a, %d %b %Y %H:%M:%S %z", "--format=%ad %h"], cwd=ROOT, capture_output=True, text=True)
    date, _, commit = (r.stdout.strip().rpartition(" ") if r.returncode == 0 and r.stdout.strip()
                       else (time.strftime("%a, %d %b %Y %H:%M:%S +0000", time.gmtime()), "", "unknown"))
    return (f"lightprobe ({ver}) unstable; urgency=medium\n\n"
            f"  * Built from the repository at commit {commit}; the project's changes are in\n"
            "    /usr/share/doc/lightprobe/CHANGELOG.md.gz.\n\n"
            f" -- lightprobe developers <maintainers@lightprobe.dev>  {date}\n")


def _installed_kib(root: Path) -> int:
    total = 0
    for p in root.rglob("*"):
        if p.is_file() and not p.is_symlink() and "DEBIAN" not in p.parts:
            total += p.stat().st_size
    return (total + 1023) // 1024


def _control(root: Path, arch: str, ver: str) -> None:
    deb = root / "DEBIAN"
    deb.mkdir(parents=True, exist_ok=True)
    _write(deb / "control",
           f"Package: lightprobe\nVersion: {ver}\nArchitecture: {arch}\n"
           "Maintainer: lightprobe developers <maintainers@lightprobe.dev>\n"
           f"Installed-Size: {_installed_kib(root)}\n"
           "Depends: python3 (>= 3.11), python3 (<< 3.12), libgomp1, libc6 (>= 2.28)\n"
           "Recommends: avahi-daemon\n"
           "Suggests: python3-libcamera, python3-picamera2\n"
           "Section: video\nPriority: optional\n"
           "Homepage: https://github.com/lightprobe/lightprobe\n"
           "Description: live HDR light probe service for a fisheye camera\n"
           " Drives exposure brackets on a UVC or libcamera camera, fuses HDR, maps the\n"
           " fisheye image to the sphere and publishes the room's lighting as directional\n"
           " light sets (and SH, cube maps, glTF, USD, spherical Gaussians) over\n"
           " HTTP/WebSocket, MQTT and OSC, advertised with mDNS. The service runs in its\n"
           f" own Python environment in {PREFIX}.\n")
    _write(deb / "conffiles", "/etc/default/lightprobe\n")
    _write(deb / "postinst", POSTINST, 0o755)
    _write(deb / "prerm", PRERM, 0o755)
    _write(deb / "postrm", POSTRM, 0o755)


# Each lintian tag the package keeps, and why. The service's environment holds the package
# index's wheels for the target architecture as published (numpy, numba/llvmlite, OpenCV,
# OpenEXR, SciPy, matplotlib, ...): their shared objects, bundled libraries and build paths are
# the wheels' own; rebuilding them against Debian's libraries is what the wheels spare a unit.
OVERRIDES = """\
# third-party wheels as published: their binaries are not stripped (their debug sections aid reports)
lightprobe: unstripped-binary-or-object [@PREFIX@/lib/python3.11/site-packages/*]
# wheels bundle their libraries (manylinux: OpenCV's FFmpeg and libjpeg, Pillow's codecs)
lightprobe: embedded-library * [@PREFIX@/lib/python3.11/site-packages/*]
# build-time RUNPATHs recorded in the wheels; they point nowhere on a unit and are not used
lightprobe: custom-library-search-path * [@PREFIX@/lib/python3.11/site-packages/*]
# Fortran/LAPACK objects in numpy and SciPy resolve libc through the extension's loader
lightprobe: library-not-linked-against-libc [@PREFIX@/lib/python3.11/site-packages/*]
lightprobe: shared-library-lacks-prerequisites [@PREFIX@/lib/python3.11/site-packages/*]
# modules with a shebang inside packages, imported, never executed
lightprobe: script-not-executable [@PREFIX@/lib/python3.11/site-packages/*]
lightprobe: unusual-interpreter * [@PREFIX@/lib/python3.11/site-packages/*]
# matplotlib's own copies of its fonts (it reads them from its data directory)
lightprobe: duplicate-font-file * [@PREFIX@/lib/python3.11/site-packages/*]
# test data inside the wheels
lightprobe: package-contains-timestamped-gzip * [@PREFIX@/lib/python3.11/site-packages/*]
"""


POSTINST = f"""#!/bin/sh
# lightprobe postinst: bytecode and the numba kernels compiled once, then the unit enabled
set -e
if [ "$1" = configure ]; then
    {PREFIX}/bin/python3 -m compileall -q {PREFIX}/lib/python{PYVER}/site-packages/lightprobe >/dev/null || true
    # every kernel the service runs, compiled into the install's cache (the unit copies it
    # into its state directory at start); a failure here is the install's failure
    env -u NUMBA_CACHE_DIR {PREFIX}/bin/python3 -m lightprobe.cli warm-kernels
    if [ -d /run/systemd/system ]; then
        systemctl --system daemon-reload >/dev/null || true
    fi
    if command -v deb-systemd-helper >/dev/null 2>&1; then
        deb-systemd-helper enable lightprobe.service >/dev/null || true
    elif [ -d /etc/systemd/system ]; then
        mkdir -p /etc/systemd/system/multi-user.target.wants
        ln -sf /lib/systemd/system/lightprobe.service /etc/systemd/system/multi-user.target.wants/lightprobe.service
    fi
    if [ -d /run/systemd/system ]; then
        if [ -n "$2" ]; then
            deb-systemd-invoke restart lightprobe.service >/dev/null || true
        else
            deb-systemd-invoke start lightprobe.service >/dev/null || true
        fi
    fi
fi
exit 0
"""

PRERM = f"""#!/bin/sh
# lightprobe prerm: stop the service; the compiled caches go with the files they belong to
set -e
if [ -d /run/systemd/system ] && [ "$1" = remove ]; then
    deb-systemd-invoke stop lightprobe.service >/dev/null || true
fi
if [ "$1" = remove ] || [ "$1" = upgrade ]; then
    find {PREFIX} -depth -type d -name __pycache__ -exec rm -rf {{}} + 2>/dev/null || true
fi
exit 0
"""

POSTRM = """#!/bin/sh
# lightprobe postrm: removal keeps the state (token, config, calibrations); purge deletes it
set -e
if [ "$1" = purge ]; then
    if command -v deb-systemd-helper >/dev/null 2>&1; then
        deb-systemd-helper purge lightprobe.service >/dev/null || true
    fi
    rm -f /etc/systemd/system/multi-user.target.wants/lightprobe.service
    rm -rf /var/lib/private/lightprobe /var/lib/lightprobe /etc/lightprobe
fi
if [ -d /run/systemd/system ]; then
    systemctl --system daemon-reload >/dev/null || true
fi
exit 0
"""


def build(arch: str, out: Path, work: Path) -> Path:
    root = stage(arch, work)
    out.mkdir(parents=True, exist_ok=True)
    deb = out / f"{root.name}.deb"
    # data as root:root whatever the builder; xz like Debian's own packages
    _run(["dpkg-deb", "--root-owner-group", "-Zxz", "-z6", "--build", str(root), str(deb)])
    return deb


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="build_deb.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--arch", action="append", choices=sorted(ARCHES), help="amd64 or arm64 (repeat for both)")
    p.add_argument("--out", type=Path, default=ROOT / "dist")
    p.add_argument("--work", type=Path, default=ROOT / "build" / "deb")
    a = p.parse_args(argv)
    if shutil.which("dpkg-deb") is None:
        print("build_deb.py: error: dpkg-deb not found (Debian: apt install dpkg-dev)", file=sys.stderr)
        return 2
    for arch in a.arch or ["amd64", "arm64"]:
        deb = build(arch, a.out, a.work)
        print(f"{deb} ({deb.stat().st_size / 2**20:.1f} MiB)")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except subprocess.CalledProcessError as e:
        print(f"build_deb.py: error: {' '.join(map(str, e.cmd))} failed with exit {e.returncode}", file=sys.stderr)
        sys.exit(1)
