"""OpenEXR (float) and PNG (tone-mapped sRGB) output, written atomically; EXR input."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import OpenEXR

from vastray.scene.errors import InputError


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it into place only on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


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
    with atomic_path(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(tmp)


def read_exr(path) -> np.ndarray:
    """Read the RGB layer of an EXR file as (H, W, 3) float32."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image not found")
    try:
        with OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if "RGB" in channels:
                return np.asarray(channels["RGB"].pixels, dtype=np.float32)
            if all(c in channels for c in "RGB"):
                return np.stack([channels[c].pixels for c in "RGB"], axis=-1).astype(np.float32)
    except Exception as exc:  # OpenEXR raises plain RuntimeError/Exception for bad files
        raise InputError(path, f"not a readable OpenEXR image ({exc})") from None
    raise InputError(path, "has no RGB channels")


def read_image(path) -> np.ndarray:
    """(H, W, 3) float32 from ``.exr`` or ``.npy``."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        if not path.is_file():
            raise InputError(path, "image not found")
        arr = np.load(path, allow_pickle=False)
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise InputError(path, f"expected an (H, W, 3) array, found {arr.shape}")
        return arr.astype(np.float32)
    return read_exr(path)


def to_srgb8(rgb: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Clamp and encode linear radiance as 8-bit sRGB. (H, W, 3) float -> (H, W, 3) uint8."""
    x = np.clip(np.nan_to_num(rgb * exposure, nan=0.0, posinf=1.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png(path, rgb: np.ndarray, exposure: float = 1.0) -> None:
    """Write a tone-mapped (clamped sRGB) PNG preview of linear radiance (H, W, 3)."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(to_srgb8(rgb, exposure), mode="RGB").save(tmp, format="PNG")


def image_error(image: np.ndarray, reference: np.ndarray) -> dict:
    """MSE, PSNR (peak = reference maximum, at least 1) and max abs difference."""
    if image.shape != reference.shape:
        raise ValueError(f"image shapes differ: {image.shape} vs {reference.shape}")
    diff = image.astype(np.float64) - reference.astype(np.float64)
    mse = float(np.mean(diff ** 2))
    peak = max(float(np.max(reference)), 1.0)
    psnr = float("inf") if mse == 0 else 10.0 * np.log10(peak ** 2 / mse)
    return {"mse": mse, "psnr_db": psnr, "max_abs_diff": float(np.max(np.abs(diff)))}
