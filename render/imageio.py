"""Image output chosen by extension (OpenEXR float with layers, PFM, Radiance HDR, tone-mapped
sRGB PNG), written atomically with the umask's mode; EXR/PFM/NPY input."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import OpenEXR

from vastray.processes import running
from vastray.scene.errors import InputError
from vastray.scene.filemode import publish_mode
from vastray.scene.manifest import NPY_HEADERS

log = logging.getLogger(__name__)

#: Output formats by extension: what ``write_image`` writes for ``-o``.
IMAGE_FORMATS = {
    ".exr": "OpenEXR, float32 RGB plus depth.Z and normal.X/Y/Z layers",
    ".pfm": "Portable Float Map, float32 RGB",
    ".hdr": "Radiance RGBE",
    ".png": "8-bit sRGB, clamped (see --exposure)",
}


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it into place only on success.

    The temporary name carries the writer's process id (``.NAME.PID.RANDOM.EXT``): a writer
    killed before it could clean up (SIGKILL, a native crash) leaves its file behind, and the
    next write of the same ``path`` removes it once that process is gone (issue 20: crashed
    renders left hidden partial images), as does ``remove_orphans``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_orphans(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=path.suffix,
                               dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        publish_mode(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def remove_orphans(path: str | os.PathLike) -> None:
    """Delete the temporary files of ``path`` (``atomic_path``'s names, also nested: the
    temporary of a temporary, ``..NAME.PID.RANDOM.EXT.PID.RANDOM.EXT``) whose writers are all
    gone; a running process's temporary file is left alone."""
    path = Path(path)
    suffix = re.escape(path.suffix)
    whole = re.compile(rf"(\.+){re.escape(path.name)}((?:\.\d+\.[a-z0-9_]{{8}}{suffix})+)")
    level = re.compile(rf"\.(\d+)\.[a-z0-9_]{{8}}{suffix}")
    with contextlib.suppress(OSError):
        for entry in os.scandir(path.parent):
            match = whole.fullmatch(entry.name)
            if not match or not entry.is_file(follow_symlinks=False):
                continue
            pids = [int(pid) for pid in level.findall(match.group(2))]
            if len(pids) == len(match.group(1)) and not any(map(running, pids)):
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)


def os_error(exc: Exception, path: str | os.PathLike) -> OSError:
    """``exc``, a library's failure to write ``path``, as an ``OSError`` with the errno its
    message names (OpenEXR raises a plain RuntimeError ending in the C library's strerror)."""
    if isinstance(exc, OSError):
        return exc
    text = str(exc)
    code = next((code for code in sorted(errno.errorcode) if os.strerror(code) in text), None)
    return OSError(code, os.strerror(code) if code else text, os.fspath(path))


def write_exr(path, rgb: np.ndarray, depth: np.ndarray | None = None,
              normal: np.ndarray | None = None) -> None:
    """Write RGB float32 plus optional ``depth.Z`` and ``normal.X/Y/Z`` layers.

    Parameters
    ----------
    rgb : (H, W, 3); depth : (H, W); normal : (H, W, 3)
    """
    channels = {"RGB": np.ascontiguousarray(rgb, dtype=np.float32)}
    if depth is not None:
        channels["depth.Z"] = np.ascontiguousarray(depth, dtype=np.float32)
    if normal is not None:
        for i, axis in enumerate("XYZ"):
            channels[f"normal.{axis}"] = np.ascontiguousarray(normal[..., i], dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    # written through a Python file: OpenEXR's own file output loses the error of a small
    # image's last write on a full disk (an empty file, "written"); Python's raises it
    with atomic_path(path) as tmp, open(tmp, "wb") as fh, OpenEXR.File(header, channels) as f:
        try:
            f.write(fh)
        except RuntimeError as exc:  # a full disk is an OSError, as for every other format
            raise os_error(exc, path) from None


def write_pfm(path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) radiance as a little-endian Portable Float Map (rows bottom to top)."""
    rgb = np.ascontiguousarray(np.asarray(rgb, dtype="<f4")[::-1])
    height, width = rgb.shape[:2]
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(f"PF\n{width} {height}\n-1.0\n".encode("ascii"))
        fh.write(rgb.tobytes())


def write_hdr(path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) radiance as an uncompressed Radiance RGBE (.hdr) file."""
    rgb = np.nan_to_num(np.maximum(np.asarray(rgb, np.float64), 0.0), posinf=0.0)
    height, width = rgb.shape[:2]
    peak = rgb.max(axis=2)
    mantissa, exponent = np.frexp(peak)
    scale = np.where(peak > 1e-32, mantissa * 256.0 / np.where(peak > 0, peak, 1.0), 0.0)
    rgbe = np.zeros((height, width, 4), np.uint8)
    rgbe[..., :3] = np.minimum(rgb * scale[..., None], 255).astype(np.uint8)
    rgbe[..., 3] = np.where(peak > 1e-32, exponent + 128, 0).astype(np.uint8)
    header = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n"
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rgbe.tobytes())


def check_image_path(path, option: str = "-o") -> Path:
    """Refuse, before any work, an output whose extension names no format or that is a folder.

    Raises
    ------
    InputError
        Naming the path and what to do instead.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(path, f"{option} is a folder; give a file name such as "
                               f"{path / 'render.exr'}")
    if path.suffix.lower() not in IMAGE_FORMATS:
        raise InputError(path, f"{option}: unknown image format {path.suffix or '(none)'!r}; "
                               f"use one of {', '.join(IMAGE_FORMATS)}")
    return path


def write_image(path, rgb: np.ndarray, depth: np.ndarray | None = None,
                normal: np.ndarray | None = None, exposure: float = 1.0, legend=None) -> None:
    """Write ``rgb`` (H, W, 3) in the format the extension names (see ``IMAGE_FORMATS``);
    only OpenEXR keeps the ``depth`` (H, W) and ``normal`` (H, W, 3) layers, and only a PNG
    gets the ``legend`` (a ``render.colormaps.Legend`` colour bar)."""
    suffix = check_image_path(path).suffix.lower()
    if suffix == ".exr":
        write_exr(path, rgb, depth, normal)
    elif suffix == ".pfm":
        write_pfm(path, rgb)
    elif suffix == ".hdr":
        write_hdr(path, rgb)
    else:
        write_png(path, rgb, exposure, legend)


def read_pfm(path) -> np.ndarray:
    """(H, W, 3) float32 from a colour Portable Float Map."""
    data = Path(path).read_bytes()
    try:
        magic, size, scale, body = data.split(b"\n", 3)
        width, height = (int(v) for v in size.split())
        order = "<" if float(scale) < 0 else ">"
        if magic != b"PF":
            raise ValueError("not a colour PFM")
        rgb = np.frombuffer(body, dtype=f"{order}f4", count=width * height * 3)
    except ValueError as exc:
        raise InputError(path, f"not a readable PFM image ({exc})") from None
    return rgb.reshape(height, width, 3)[::-1].astype(np.float32)


_native_output_lock = threading.Lock()


@contextmanager
def _library_output_kept(path: Path):
    """Hold what OpenEXR's C++ code prints to the standard output and error while it reads
    ``path`` (a damaged file made it print 4-5 lines of its own before our one-line error),
    then log it: the error raised says what is wrong. The file descriptors themselves are
    redirected, so only a short read is wrapped, under a lock."""
    with _native_output_lock, tempfile.TemporaryFile() as held:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(AttributeError, ValueError, OSError):
                stream.flush()
        saved = []
        try:
            for fd in (1, 2):
                saved.append((fd, os.dup(fd)))
                os.dup2(held.fileno(), fd)
        except OSError:  # no such descriptor (a daemon): nothing to hold
            pass
        try:
            yield
        finally:
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            held.seek(0)
            text = held.read().decode(errors="replace").strip()
            if text:
                log.debug("OpenEXR reading %s said: %s", path, text)


def read_exr(path) -> np.ndarray:
    """Read the RGB layer of an EXR file as (H, W, 3) float32."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image not found")
    try:
        with _library_output_kept(path), OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if "RGB" in channels:
                return np.asarray(channels["RGB"].pixels, dtype=np.float32)
            if all(c in channels for c in "RGB"):
                return np.stack([channels[c].pixels for c in "RGB"], axis=-1).astype(np.float32)
    except Exception as exc:  # OpenEXR raises plain RuntimeError/Exception for bad files
        raise InputError(path, f"not a readable OpenEXR image ({exc})") from None
    raise InputError(path, "has no RGB channels")


def read_image(path) -> np.ndarray:
    """(H, W, 3) float32 from ``.exr``, ``.pfm`` or ``.npy``."""
    path = Path(path)
    if path.suffix.lower() == ".pfm":
        if not path.is_file():
            raise InputError(path, "image not found")
        return read_pfm(path)
    if path.suffix.lower() == ".npy":
        if not path.is_file():
            raise InputError(path, "image not found")
        try:
            with NPY_HEADERS:
                arr = np.load(path, allow_pickle=False)
        except (ValueError, EOFError, OSError) as exc:  # truncated, object arrays, not .npy
            raise InputError(path, f"not a readable .npy image ({exc})") from None
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise InputError(path, f"expected an (H, W, 3) array, found {arr.shape}")
        if arr.dtype.kind not in "fiu":
            raise InputError(path, f"expected a real-valued image, found {arr.dtype} values")
        return arr.astype(np.float32)
    if path.suffix.lower() != ".exr":
        what = ("a PNG is an 8-bit preview, not radiance" if path.suffix.lower() == ".png"
                else f"cannot read a {path.suffix or 'file without extension'}")
        raise InputError(path, f"{what}: give the .exr, .pfm or .npy image")
    return read_exr(path)


def to_srgb8(rgb: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Clamp and encode linear radiance as 8-bit sRGB. (H, W, 3) float -> (H, W, 3) uint8."""
    x = np.clip(np.nan_to_num(rgb * exposure, nan=0.0, posinf=1.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png(path, rgb: np.ndarray, exposure: float = 1.0, legend=None) -> None:
    """Write a tone-mapped (clamped sRGB) PNG preview of linear radiance (H, W, 3), with the
    colour bar ``legend`` (a ``render.colormaps.Legend``) drawn over its bottom when given."""
    from PIL import Image

    image = to_srgb8(rgb, exposure)
    if legend is not None:
        from vastray.render.colormaps import draw_legend

        image = draw_legend(image, legend)
    with atomic_path(path) as tmp:
        Image.fromarray(image, mode="RGB").save(tmp, format="PNG")


#: ε of the per-pixel relative MSE ``mean((x - r)**2 / (r**2 + ε))`` (as in Rousselle et
#: al. 2011 and the denoising literature): keeps black pixels from dominating.
REL_MSE_EPSILON = 1e-2


def relative_mse(image: np.ndarray, reference: np.ndarray) -> float:
    """Per-pixel relative MSE, ``mean((x - r)**2 / (r**2 + ε))`` over pixels and channels."""
    x, r = image.astype(np.float64), reference.astype(np.float64)
    return float(np.mean((x - r) ** 2 / (r ** 2 + REL_MSE_EPSILON)))


def image_error(image: np.ndarray, reference: np.ndarray) -> dict:
    """MSE, PSNR (peak = reference maximum, at least 1), relative MSE and max abs difference.

    ``rel_mse`` is the per-pixel relative MSE ``mean((x - r)**2 / (r**2 + ε))``, ε = 1e-2
    (``REL_MSE_EPSILON``), the rendering literature's measure: every pixel's
    error relative to its own brightness. ``rel_mse_global`` is ``mse / mean(reference**2)``,
    the error relative to the reference's whole energy. ``psnr_db`` is ``None`` for identical
    images (infinite PSNR has no JSON spelling), ``rel_mse_global`` for an all-black
    reference."""
    if image.shape != reference.shape:
        raise ValueError(f"image shapes differ: {image.shape} vs {reference.shape}")
    ref = reference.astype(np.float64)
    diff = image.astype(np.float64) - ref
    mse = float(np.mean(diff ** 2))
    peak = max(float(np.max(reference)), 1.0)
    psnr = None if mse == 0 else float(10.0 * np.log10(peak ** 2 / mse))
    energy = float(np.mean(ref ** 2))
    rel_mse_global = mse / energy if energy > 0 else (0.0 if mse == 0 else None)
    return {"mse": mse, "psnr_db": psnr, "rel_mse": relative_mse(image, reference),
            "rel_mse_global": rel_mse_global, "max_abs_diff": float(np.max(np.abs(diff)))}
