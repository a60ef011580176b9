# SPDX-License-Identifier: Apache-2.0
"""Everything the add-on does that is not Blender: HTTP to a probe, DNS-SD discovery, the frames.

Nothing here imports ``bpy`` or the lightprobe package (the add-on runs in Blender's own Python,
which has neither the project nor its dependencies): the standard library only, so the add-on
is one folder a user installs.

Frames. The probe's frame is right-handed, +y up, azimuth 0 towards -z (lightprobe's
CONVENTIONS.md, as glTF and three.js); Blender's world is right-handed, +Z up. A probe direction
``(x, y, z)`` is Blender's ``(x, -z, y)``, the conversion Blender's own glTF importer uses
(:data:`PROBE_TO_BLENDER`); the probe's pose (``pose.rotation``, world-from-probe in the same
+y-up frame) comes first. Cycles reads an equirect environment image with ``u = 0.5 - atan2(Y,
X) / 2pi`` and the image's top row at +Z; the probe's map puts azimuth ``p`` at ``u = p / 2pi``
with ``d = (sin t sin p, cos t, -sin t cos p)``: the image as it is shows probe ``(x, y, z)`` at
Blender ``(z, x, y)`` (:data:`IMAGE_AXES`), so the world's Mapping node rotates each lookup by
``IMAGE_AXES @ pose^T @ PROBE_TO_BLENDER^T`` (:func:`environment_rotation`).
"""

from __future__ import annotations

import json
import math
import random
import socket
import struct
import time
import urllib.error
import urllib.parse
import urllib.request

SERVICE_TYPE = "_lightprobe._tcp.local."
MDNS_GROUP, MDNS_PORT = "224.0.0.251", 5353

# probe frame -> Blender world (rows): X = x, Y = -z, Z = y
PROBE_TO_BLENDER = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))
# where Cycles shows the probe's equirect as loaded: Blender (X, Y, Z) = (z, x, y) of the probe
IMAGE_AXES = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))


class ProbeError(Exception):
    """A probe that cannot be reached or answers wrongly (the message says which and why)."""


# ---- small linear algebra (no numpy in the add-on) -------------------------------------------------
def matmul(a, b):
    return tuple(tuple(sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)) for i in range(3))


def transpose(a):
    return tuple(tuple(a[j][i] for j in range(3)) for i in range(3))


def apply(m, v):
    return tuple(sum(m[i][k] * v[k] for k in range(3)) for i in range(3))


def pose_rotation(body):
    """The world-from-probe rotation of an SH / light-set body (identity when absent)."""
    rot = (body.get("pose") or {}).get("rotation")
    if not rot:
        return ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    return tuple(tuple(float(x) for x in row) for row in rot)


def to_blender(direction, body):
    """A probe-frame direction of ``body`` in Blender's world (unit vector)."""
    d = apply(matmul(PROBE_TO_BLENDER, pose_rotation(body)), [float(x) for x in direction])
    n = math.sqrt(sum(x * x for x in d)) or 1.0
    return tuple(x / n for x in d)


def environment_rotation(body):
    """The rotation matrix the world's Mapping node (type POINT) applies to each lookup."""
    return matmul(matmul(IMAGE_AXES, transpose(pose_rotation(body))), transpose(PROBE_TO_BLENDER))


def sun_from_primary(primary):
    """(strength W/m^2 = the largest channel of its irradiance, colour scaled to 1 there, angle
    in radians of a disc of its solid angle) of the probe's primary light."""
    rgb = [max(0.0, float(x)) for x in primary["rgb"]]
    peak = max(rgb)
    colour = tuple(x / peak for x in rgb) if peak > 0 else (1.0, 1.0, 1.0)
    omega = min(max(float(primary.get("solid_angle", 0.0)), 0.0), 2 * math.pi)
    return peak, colour, 2.0 * math.acos(1.0 - omega / (2.0 * math.pi))


# ---- HTTP ---------------------------------------------------------------------------------------
def normalise_url(url):
    """``host``, ``host:port``, ``http://host:port[/api/v1]`` -> ``http://host:port``."""
    url = url.strip().rstrip("/")
    if not url:
        raise ProbeError("no probe URL")
    if "://" not in url:
        url = "http://" + url
    u = urllib.parse.urlsplit(url)
    if u.scheme not in ("http", "https") or not u.hostname:
        raise ProbeError(f"not a probe URL: {url!r}")
    path = u.path[:-len("/api/v1")] if u.path.endswith("/api/v1") else u.path
    return f"{u.scheme}://{u.netloc}{path}"


def get(url, token="", timeout=5.0):
    """(body bytes, headers) of ``GET url``; ProbeError naming the URL on any failure."""
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.read(), dict(r.headers)
    except urllib.error.HTTPError as e:
        hint = " (the token is wrong or missing)" if e.code in (401, 403) else ""
        raise ProbeError(f"{url}: HTTP {e.code}{hint}") from None
    except (urllib.error.URLError, OSError, TimeoutError) as e:
        raise ProbeError(f"{url}: {getattr(e, 'reason', e)}") from None


def fetch_lighting(base, token, timeout=5.0):
    """The probe's current lighting: its SH body (canonical: the primary light, frame, pose,
    capture time) and the ambient map (the HDR map without the primary light) as EXR bytes."""
    body, _ = get(f"{base}/api/v1/sh?convention=canonical", token, timeout)
    try:
        sh = json.loads(body)
    except ValueError:
        raise ProbeError(f"{base}/api/v1/sh: not JSON") from None
    exr, _ = get(f"{base}/api/v1/environment_ambient_latlong.exr", token, timeout)
    if exr[:4] != b"\x76\x2f\x31\x01":
        raise ProbeError(f"{base}/api/v1/environment_ambient_latlong.exr: not an OpenEXR file")
    return sh, exr


# ---- DNS-SD (one-shot mDNS query, RFC 6762 / 6763) ----------------------------------------------
def _qname(name):
    out = b""
    for label in name.rstrip(".").split("."):
        raw = label.encode("utf-8")
        out += bytes([len(raw)]) + raw
    return out + b"\0"


def _read_name(msg, off):
    labels, jumped, end = [], False, off
    for _ in range(128):
        n = msg[off]
        if n & 0xC0 == 0xC0:
            if not jumped:
                end = off + 2
            off, jumped = ((n & 0x3F) << 8) | msg[off + 1], True
            continue
        if n == 0:
            return ".".join(labels) + ".", (end if jumped else off + 1)
        labels.append(msg[off + 1:off + 1 + n].decode("utf-8", "replace"))
        off += 1 + n
    raise ValueError("name loop")


def _records(msg):
    """(name, type, rdata offset, rdata length) of every answer / additional record."""
    qd, an, ns, ar = struct.unpack_from("!4H", msg, 4)
    off = 12
    for _ in range(qd):
        _, off = _read_name(msg, off)
        off += 4
    for _ in range(an + ns + ar):
        name, off = _read_name(msg, off)
        rtype, _cls, _ttl, rdlen = struct.unpack_from("!HHIH", msg, off)
        off += 10
        yield name, rtype, off, rdlen
        off += rdlen


def discover(seconds=1.5, service=SERVICE_TYPE, interface=None):
    """Probes answering on the LAN within ``seconds``: a list of dicts (name, url, id, txt).
    ``interface``: the IPv4 address to query from (default: the system's multicast route)."""
    query = struct.pack("!6H", random.randrange(1 << 16), 0, 1, 0, 0, 0) + _qname(service) + struct.pack("!HH", 12, 1)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 255)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        if interface:
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(interface))
        s.bind(("", 0))  # a one-shot query from another port: answers come back unicast (RFC 6762 6.7)
        s.settimeout(0.2)
        s.sendto(query, (MDNS_GROUP, MDNS_PORT))
        ptr, srv, txt, addr = set(), {}, {}, {}
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                msg, _ = s.recvfrom(9000)
            except TimeoutError:
                continue
            try:
                for name, rtype, off, rdlen in _records(msg):
                    if rtype == 12 and name.lower() == service.lower():
                        ptr.add(_read_name(msg, off)[0])
                    elif rtype == 33:
                        port = struct.unpack_from("!H", msg, off + 4)[0]
                        srv[name] = (_read_name(msg, off + 6)[0], port)
                    elif rtype == 16:
                        items, o = {}, off
                        while o < off + rdlen:
                            n = msg[o]
                            k, _, v = msg[o + 1:o + 1 + n].decode("utf-8", "replace").partition("=")
                            items[k] = v
                            o += 1 + n
                        txt[name] = items
                    elif rtype == 1 and rdlen == 4:
                        addr[name] = socket.inet_ntoa(msg[off:off + 4])
            except (ValueError, IndexError, struct.error):
                continue  # a malformed packet from someone else
    finally:
        s.close()
    found = []
    for inst in sorted(ptr):
        if inst not in srv:
            continue
        host, port = srv[inst]
        ip = addr.get(host) or host.rstrip(".")
        t = txt.get(inst, {})
        label = t.get("name") or inst[:-len(service) - 1]
        found.append({"name": label, "url": f"http://{ip}:{port}", "id": t.get("id", ""), "txt": t})
    return found
