"""Which cameras are attached, and ``open_camera(spec)`` for ``--camera``.

Specs (CONVENTIONS.md): ``v4l2:/dev/videoN`` (or a ``/dev/v4l/by-id/...`` path, which is
preferred: it survives replugs; a ``/dev/videoN`` path is swapped for its by-id link when there is
one), ``libcamera`` or ``libcamera:N``, ``uvc`` / ``uvc:VID:PID`` (hex; the UVC camera's V4L2 node,
with UVC-over-USB controls as a fallback), ``replay:FILE`` (a recording played back as a camera,
:mod:`lightprobe.drivers.replay`; options ``pace``, ``loop``, ``speed``) and ``auto`` (libcamera, else the first V4L2 capture
node that opens; the choice is logged). ``auto`` never picks a simulated camera: with no
hardware it raises :class:`NoCameraFound` (a :class:`CameraUnavailable`: a service keeps
retrying and says why in its status; a command line exits 2).

Camera plugins. Any other kind is looked up in the ``lightprobe.cameras`` entry-point group
(``pyproject.toml``): the simulator registers ``sim`` and ``v4l2-fake`` (the fake UVC kernel
behind the real V4L2 driver) there, so production code never imports it; a plugin is
``factory(arg, **options) -> Camera`` and takes the options it knows (``scene``, ``cache_dir``).

:func:`list_cameras` looks at ``/dev/v4l/by-id``, ``/dev/video*`` capture nodes, pyusb's UVC
devices and picamera2 (when importable), probing each (QUERYCAP, modes, exposure range) without
streaming. :func:`open_with_retry` opens a camera with exponential backoff (a service must keep
trying, not exit, when a camera is missing or busy). Nothing here runs at import.
"""

from __future__ import annotations

import asyncio
import glob
import logging
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from lightprobe.core.errors import InputError
from lightprobe.drivers.base import Camera, CameraBusy, CameraError, CameraUnavailable

__all__ = [
    "PLUGIN_GROUP",
    "CameraInfo",
    "NoCameraFound",
    "find_v4l2_node_for_usb",
    "list_cameras",
    "open_camera",
    "open_with_retry",
    "parse_spec",
    "usb_ids_of_node",
]

log = logging.getLogger(__name__)
BY_ID = "/dev/v4l/by-id"
SPEC_HELP = "v4l2:/dev/videoN|libcamera[:N]|uvc[:VID:PID]|replay:FILE|auto, or a plugin: sim|v4l2-fake"
PLUGIN_GROUP = "lightprobe.cameras"
_BUILTIN = ("auto", "v4l2", "libcamera", "uvc", "replay")
# V4L2 nodes that belong to libcamera's pipelines (ISP, CSI receivers): not cameras on their own.
_LIBCAMERA_INTERNAL = ("unicam", "rp1-cfe", "bcm2835-isp", "pispbe", "bcm2835-codec", "rpivid")


class NoCameraFound(CameraUnavailable):
    """``--camera auto`` found no camera hardware (the simulator is never a fallback)."""


def camera_plugins() -> dict[str, Any]:
    """Entry points of the ``lightprobe.cameras`` group by kind (not loaded)."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=PLUGIN_GROUP)}


@dataclass
class CameraInfo:
    """One camera as ``lightprobe cameras`` shows it."""

    kind: str  # "v4l2" | "uvc" | "libcamera" | "sim"
    spec: str  # what to pass to --camera
    name: str
    status: str = "available"  # or "busy", "unavailable: ...", "no manual exposure: ..."
    path: str = ""
    capabilities: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


# ---- specs --------------------------------------------------------------------------------------
def parse_spec(spec: str) -> tuple[str, str]:
    """Split and validate a ``--camera`` value: (kind, argument). InputError when malformed."""
    kind, _, arg = spec.strip().partition(":")
    ok = (
        (kind == "auto" and not arg)
        or (kind == "v4l2" and arg.startswith("/"))  # an absolute path to the node
        or (kind == "libcamera" and (not arg or arg.isdigit()))
        or (kind == "uvc" and (not arg or _parse_vid_pid(arg) is not None))
        or (kind == "replay" and bool(arg))  # a recording file (any path)
        or (kind not in _BUILTIN and not arg and kind in camera_plugins())
    )
    if not ok:
        raise InputError(f"--camera {spec!r}: expected {SPEC_HELP}", param="--camera")
    return kind, arg


def _parse_vid_pid(arg: str) -> tuple[int, int] | None:
    parts = arg.split(":")
    try:
        vid, pid = (int(p, 16) for p in parts)
    except ValueError:
        return None
    return (vid, pid) if len(parts) == 2 and 0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF else None


# ---- sysfs helpers ------------------------------------------------------------------------------
def usb_ids_of_node(node: str, sys_root: str = "/sys") -> tuple[int, int] | None:
    """(idVendor, idProduct) of the USB device behind a video node, from sysfs; None if not USB."""
    name = os.path.basename(os.path.realpath(node))
    dev = Path(sys_root, "class", "video4linux", name, "device")
    try:
        here = dev.resolve(strict=True)
    except OSError:
        return None
    for d in (here, *here.parents):
        v, p = d / "idVendor", d / "idProduct"
        if v.is_file() and p.is_file():
            return int(v.read_text().strip(), 16), int(p.read_text().strip(), 16)
        if d == Path(sys_root) or d.name == "devices":
            break
    return None


def find_v4l2_node_for_usb(vid: int | None, pid: int | None, *, by_id_dir: str = BY_ID,
                           sys_root: str = "/sys") -> str | None:  # fmt: skip
    """The by-id capture node (``-video-index0``) of a USB camera with this VID:PID (any if None)."""
    for link in sorted(glob.glob(os.path.join(by_id_dir, "*-video-index0"))):
        ids = usb_ids_of_node(link, sys_root)
        if ids is not None and (vid is None or ids[0] == vid) and (pid is None or ids[1] == pid):
            return link
    return None


def _stable_path(node: str, by_id_dir: str = BY_ID) -> str:
    real = os.path.realpath(node)
    for link in sorted(glob.glob(os.path.join(by_id_dir, "*"))):
        if os.path.realpath(link) == real:
            return link
    return node


def _v4l2_candidates(by_id_dir: str, dev_glob: str) -> list[str]:
    nodes = sorted(glob.glob(os.path.join(by_id_dir, "*-video-index*")))
    seen = {os.path.realpath(n) for n in nodes}
    nodes += [n for n in sorted(glob.glob(dev_glob)) if os.path.realpath(n) not in seen]
    return nodes


# ---- listing ------------------------------------------------------------------------------------
def probe_v4l2(path: str, opener: Callable[[], Any] | None = None) -> CameraInfo | None:
    """QUERYCAP + modes + exposure controls of one node; None for non-capture / internal nodes."""
    from lightprobe.drivers.v4l2._ioctl import DeviceTransport
    from lightprobe.drivers.v4l2.camera import V4L2Camera, enumerate_modes
    from lightprobe.drivers.v4l2.controls import V4L2Controls

    spec = f"v4l2:{path}"
    try:
        t = (opener or (lambda: DeviceTransport(path)))()
    except CameraBusy:
        return CameraInfo("v4l2", spec, os.path.basename(path), "busy", path)
    except CameraError as e:
        return CameraInfo("v4l2", spec, os.path.basename(path), f"unavailable: {e}", path)
    try:
        cam = V4L2Camera(path)
        cam._querycap(t)
        if any(k in cam.card.lower() for k in _LIBCAMERA_INTERNAL):
            return None
        info = CameraInfo("v4l2", spec, cam.card or os.path.basename(path), "available", path)
        modes = enumerate_modes(t)
        info.capabilities["modes"] = [f"{m.width}x{m.height} {m.format.value} {m.max_fps:g}fps" for m in modes]
        ctl = V4L2Controls(t)
        ctl.probe()
        info.capabilities["exposure_range_s"] = list(ctl.exposure_range)
        info.capabilities["gain_range"] = list(ctl.gain_range)
    except CameraUnavailable as e:  # not a streaming capture node (e.g. a metadata node)
        log.debug("%s: %s", path, e)
        return None
    except CameraError as e:
        info.status = f"no manual exposure: {e}"
    finally:
        t.close()
    return info


def _list_uvc(usb_backend: Any) -> list[CameraInfo]:
    from lightprobe.drivers.uvc import UvcControls, find_uvc_devices

    out = []
    for dev in find_uvc_devices(usb_backend):
        vidpid = f"{dev.idVendor:04x}:{dev.idProduct:04x}"
        info = CameraInfo("uvc", f"uvc:{vidpid}", vidpid, "available", f"usb {dev.bus}:{dev.address}")
        ctl = UvcControls(dev)
        try:
            info.name = f"{dev.product or 'UVC camera'} ({vidpid})"
            ctl.probe()
            info.capabilities = {"exposure_range_s": list(ctl.exposure_range), "gain_range": list(ctl.gain_range)}
        except CameraBusy:
            info.status = "controls via V4L2 (uvcvideo bound)"
        except (CameraError, ValueError) as e:
            info.status = f"unavailable: {e}"
        finally:
            ctl.close()
        out.append(info)
    return out


def _list_libcamera() -> list[CameraInfo]:
    try:
        from picamera2 import Picamera2  # type: ignore[import-not-found]
    except ImportError:
        return []
    out = []
    for i, cam in enumerate(Picamera2.global_camera_info()):
        out.append(CameraInfo("libcamera", f"libcamera:{i}", str(cam.get("Model", "camera")), "available",
                              str(cam.get("Id", ""))))  # fmt: skip
    return out


def list_cameras(*, by_id_dir: str = BY_ID, dev_glob: str = "/dev/video*", usb_backend: Any = None,
                 include_libcamera: bool = True, include_plugins: bool = True) -> list[CameraInfo]:  # fmt: skip
    """Every camera we can see, hardware first; then the installed camera plugins (the
    simulator), which ``auto`` never picks."""
    found: list[CameraInfo] = []
    if include_libcamera:
        found += _list_libcamera()
    for node in _v4l2_candidates(by_id_dir, dev_glob):
        info = probe_v4l2(node)
        if info is not None:
            found.append(info)
    found += _list_uvc(usb_backend)
    if include_plugins:
        for kind, ep in sorted(camera_plugins().items()):
            found.append(CameraInfo(kind, kind, f"camera plugin {ep.value}", "available (plugin)"))
    return found


# ---- opening ------------------------------------------------------------------------------------
def open_camera(spec: str, *, usb_backend: Any = None, frame_source: Any = None,
                by_id_dir: str = BY_ID, sys_root: str = "/sys", **options: Any) -> Camera:  # fmt: skip
    """The one camera factory: a (not yet opened) camera for a ``--camera`` spec.

    InputError for a malformed spec; CameraUnavailable when the spec names hardware that is not
    there (:class:`NoCameraFound` for ``auto``). ``options`` go to a plugin camera (the
    simulator's ``scene``, ``cache_dir``, ...); hardware backends take none."""
    kind, arg = parse_spec(spec)
    if kind == "v4l2":
        from lightprobe.drivers.v4l2.camera import V4L2Camera

        path = _stable_path(arg, by_id_dir)
        if path != arg:
            log.info("using stable path %s for %s", path, arg)
        return V4L2Camera(path)
    if kind == "libcamera":
        from lightprobe.drivers.libcamera import Picamera2Camera

        return Picamera2Camera(int(arg or 0))
    if kind == "uvc":
        return _open_uvc(arg, usb_backend, frame_source, by_id_dir, sys_root)
    if kind == "replay":
        from lightprobe.drivers.replay import ReplayCamera

        return ReplayCamera(arg, **{k: v for k, v in options.items() if k in ("pace", "loop", "speed")})
    if kind == "auto":
        return _auto(by_id_dir)
    factory = camera_plugins()[kind].load()
    return factory(arg, **options)  # type: ignore[no-any-return]


def _open_uvc(arg: str, usb_backend: Any, frame_source: Any, by_id_dir: str, sys_root: str) -> Camera:
    from lightprobe.drivers.uvc import UvcCamera, find_uvc_devices, v4l2_controls_with_uvc_fallback
    from lightprobe.drivers.v4l2.camera import V4L2Camera

    ids = _parse_vid_pid(arg) if arg else None
    vid, pid = ids if ids is not None else (None, None)

    def find_usb() -> Any:
        devs = find_uvc_devices(usb_backend, vid, pid)
        return devs[0] if devs else None

    node = find_v4l2_node_for_usb(vid, pid, by_id_dir=by_id_dir, sys_root=sys_root)
    if node is not None:
        return V4L2Camera(node, controls_factory=v4l2_controls_with_uvc_fallback(find_usb))
    if frame_source is not None:
        return UvcCamera(find_usb, frame_source, name=f"uvc:{arg}" if arg else "uvc")
    raise CameraUnavailable(
        f"no UVC camera{' ' + arg if arg else ''} with a V4L2 node in {by_id_dir} "
        "(attached? uvcvideo loaded?); pyusb alone gives controls, not frames", device=f"uvc:{arg}",
    )  # fmt: skip


def _auto(by_id_dir: str) -> Camera:
    for info in list_cameras(by_id_dir=by_id_dir, include_plugins=False):
        if info.status == "available" and info.kind in ("libcamera", "v4l2"):
            log.info("--camera auto: using %s (%s)", info.spec, info.name)
            return open_camera(info.spec, by_id_dir=by_id_dir)
    raise NoCameraFound("--camera auto: no camera hardware found (libcamera, V4L2 capture nodes in "
                        f"{by_id_dir} and /dev/video*); name the simulator with --camera sim",
                        device="auto")


async def open_with_retry(camera: Camera, *, initial_s: float = 0.5, max_s: float = 30.0,
                          attempts: int | None = None,
                          on_error: Callable[[CameraError, float], None] | None = None) -> None:  # fmt: skip
    """Open, retrying CameraUnavailable/Busy/Disconnected with exponential backoff.

    ``attempts=None`` retries forever (a service). Each failure is logged with the next delay.
    """
    delay, n = initial_s, 0
    while True:
        try:
            await camera.close()
            await camera.open()
        except CameraError as e:
            n += 1
            if attempts is not None and n >= attempts:
                raise
            log.warning("camera %s: %s; retrying in %.1f s", camera.name, e, delay)
            if on_error is not None:
                on_error(e, delay)
            await asyncio.sleep(delay)
            delay = min(delay * 2, max_s)
        else:
            return
