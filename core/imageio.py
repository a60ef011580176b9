"""Reading and writing HDR images: OpenEXR (through the OpenEXR package) and Radiance .hdr.

OpenCV 5's PyPI wheel cannot read EXR, so EXR always goes through ``OpenEXR``. Images are returned
as float32 (H, W, 3) linear RGB. Every failure raises :class:`lightprobe.core.errors.InputError` naming
the file.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError

__all__ = ["read_exr_header", "read_hdr_image", "write_exr", "write_hdr"]


def read_hdr_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read ``.exr`` or ``.hdr`` as float32 (H, W, 3) linear RGB."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file", param=str(p))
    suffix = p.suffix.lower()
    if suffix == ".exr":
        img = _read_exr(p)
    elif suffix in (".hdr", ".pic"):
        import cv2

        bgr = cv2.imread(str(p), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(f"{p}: not a readable Radiance HDR image", param=str(p))
        img = np.ascontiguousarray(bgr[..., ::-1], dtype=np.float32)
    else:
        raise InputError(f"{p}: unsupported HDR format {suffix!r} (use .exr or .hdr)", param=str(p))
    if img.ndim != 3 or img.shape[2] != 3 or img.size == 0:
        raise InputError(f"{p}: expected an RGB image, got shape {img.shape}", param=str(p))
    return img


def _read_exr(p: Path) -> np.ndarray:
    import OpenEXR

    try:
        with OpenEXR.File(str(p), separate_channels=True) as f:
            ch = dict(f.parts[0].channels)
    except Exception as e:
        raise InputError(f"{p}: not a readable OpenEXR file ({e})", param=str(p)) from e
    names = {k.split(".")[-1]: v for k, v in ch.items()}
    if all(k in names for k in "RGB"):
        planes = [names[k].pixels for k in "RGB"]
    elif "Y" in names:
        planes = [names["Y"].pixels] * 3
    else:
        raise InputError(f"{p}: EXR has no R, G, B or Y channels (has {sorted(ch)})", param=str(p))
    return np.ascontiguousarray(np.stack(planes, axis=-1), dtype=np.float32)


def read_exr_header(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The EXR header as a dict (our metadata are string attributes)."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            return dict(f.header())
    except Exception as e:
        raise InputError(f"{path}: not a readable OpenEXR file ({e})", param=str(path)) from e


def _atomic_target(path: Path) -> tuple[int, str]:
    return tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent or ".")


def exr_bytes(image: np.ndarray, metadata: dict[str, str] | None = None, *, half: bool = False) -> bytes:
    """Encode an EXR in memory (for HTTP responses)."""
    fd, tmp = tempfile.mkstemp(suffix=".exr")
    os.close(fd)
    try:
        write_exr(tmp, image, metadata, half=half, atomic=False)
        return Path(tmp).read_bytes()
    finally:
        os.unlink(tmp)


def write_exr(path: str | os.PathLike[str], image: np.ndarray, metadata: dict[str, str] | None = None,
              *, half: bool = False, atomic: bool = True) -> None:
    """Write float RGB (H, W, 3), or RGBA (H, W, 4), as OpenEXR (ZIP compression), with string
    metadata attributes.

    Written to a temporary file in the same folder and renamed, so readers never see a torn file.
    """
    import OpenEXR

    p = Path(path)
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise InputError(f"{p}: image to write must be (H, W, 3) or (H, W, 4), got {img.shape}", param=str(p))
    dtype = np.float16 if half else np.float32
    channels = {c: np.ascontiguousarray(img[..., i], dtype=dtype) for i, c in enumerate("RGBA"[: img.shape[2]])}
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (metadata or {}).items():
        header[k] = str(v)
    if not atomic:
        with OpenEXR.File(header, channels) as f:
            f.write(str(p))
        return
    fd, tmp = _atomic_target(p)
    os.close(fd)
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_hdr(path: str | os.PathLike[str], image: np.ndarray) -> None:
    """Write Radiance RGBE (.hdr) atomically."""
    import cv2

    p = Path(path)
    fd, tmp = _atomic_target(p)
    os.close(fd)
    try:
        bgr = np.ascontiguousarray(np.asarray(image, np.float32)[..., ::-1])
        if not cv2.imwrite(tmp, bgr):
            raise InputError(f"{p}: could not write Radiance HDR", param=str(p))  # noqa: TRY301
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
