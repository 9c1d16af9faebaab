"""Procedural textures and tiled meshes, generated at run time and cached on disk.

Drake's VTK renderer clamps OBJ texture coordinates outside [0, 1], so a
textured surface is an OBJ with one quad per tile, each with UVs 0..1.
"""

import hashlib
from pathlib import Path

import cv2
import numpy as np

from .files import atomic_write_bytes, cache_root


def cache_dir() -> Path:
    """Where generated textures and meshes live (under `cache_root`)."""
    path = cache_root() / "assets"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _key(*parts) -> str:
    return hashlib.sha1(repr(parts).encode()).hexdigest()[:16]


def _fractal_noise(size, seed, beta=1.6):
    """Zero-mean, unit-std 1/f^beta noise on a periodic size x size grid."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(size)
    radius = np.hypot(*np.meshgrid(f, f, indexing="ij"))
    radius[0, 0] = 1.0
    spectrum = np.fft.fft2(rng.standard_normal((size, size))) / radius ** beta
    spectrum[0, 0] = 0.0
    noise = np.real(np.fft.ifft2(spectrum))
    return noise / noise.std()


def texture_png(kind: str, tone, roughness: float, seed: int, size: int = 128) -> str:
    """Path of a PNG texture (``asphalt``, ``concrete`` or ``grass``), made if missing."""
    path = cache_dir() / f"{kind}_{_key(kind, tuple(tone), roughness, seed, size)}.png"
    if path.exists():
        return str(path)
    noise = _fractal_noise(size, seed)
    fine = np.random.default_rng(seed + 1).standard_normal((size, size))
    shade = 1.0 + roughness * (0.10 * noise + 0.08 * fine)
    if kind == "concrete":          # slab joints at the tile border
        shade[:2, :] *= 0.65
        shade[:, :2] *= 0.65
    elif kind == "grass":           # mowing stripes along the tile
        shade *= 1.0 + 0.06 * np.sign(np.sin(np.linspace(0, 2 * np.pi, size)))[None, :]
    rgb = np.clip(np.asarray(tone)[None, None, :] * shade[..., None], 0, 1)
    ok, png = cv2.imencode(".png", (rgb[..., ::-1] * 255).astype(np.uint8))
    assert ok
    atomic_write_bytes(path, png.tobytes())
    return str(path)


def tiled_quad_obj(x_range, y_range, z: float, tile: float) -> str:
    """Path of an OBJ covering the rectangle with upward-facing tiles of ~``tile`` m,
    each mapping the whole texture (UV 0..1). Made if missing."""
    (x0, x1), (y0, y1) = x_range, y_range
    path = cache_dir() / f"quads_{_key(x0, x1, y0, y1, z, tile)}.obj"
    if path.exists():
        return str(path)
    xs = np.linspace(x0, x1, max(1, round((x1 - x0) / tile)) + 1)
    ys = np.linspace(y0, y1, max(1, round((y1 - y0) / tile)) + 1)
    lines = ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1", "vn 0 0 1"]
    n = 0
    for xa, xb in zip(xs[:-1], xs[1:]):
        for ya, yb in zip(ys[:-1], ys[1:]):
            lines += [f"v {xa:.3f} {ya:.3f} {z:.4f}", f"v {xb:.3f} {ya:.3f} {z:.4f}",
                      f"v {xb:.3f} {yb:.3f} {z:.4f}", f"v {xa:.3f} {yb:.3f} {z:.4f}"]
            a, b, c, d = n + 1, n + 2, n + 3, n + 4
            lines.append(f"f {a}/1/1 {b}/2/1 {c}/3/1 {d}/4/1")
            n += 4
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())
    return str(path)
