"""Textures and cameras of the simulator: grey-level photographs shipped with matplotlib (nothing is
downloaded), resampled to one texel per pixel, and the pinhole cameras of the real sensors."""

from __future__ import annotations

import gzip

import numpy as np

from cmax_taichi.core.events import Camera

__all__ = ["SENSORS", "TEXTURES", "load_texture", "default_camera"]

#: sensor sizes (W, H) by name
SENSORS = {
    "davis240": (240, 180),
    "davis346": (346, 260),
    "vga": (640, 480),
    "hd": (1280, 720),
}

#: the images shipped with matplotlib that serve as textures (nothing is downloaded)
TEXTURES = ("grace_hopper", "minduka", "dem", "mri")

# Focal lengths of the real sensors (ECD DAVIS240C, MVSEC DAVIS346), px; other sizes use 0.65 W.
_FOCAL = {(240, 180): 199.0, (346, 260): 226.0}


def _srgb_to_linear(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def load_texture(name: str) -> np.ndarray:
    """A grey-level texture from the sample data that ships with matplotlib.

    Parameters
    ----------
    name : str
        One of :data:`TEXTURES`: ``"grace_hopper"`` (photograph, 600x512), ``"minduka"`` (photograph,
        128x128), ``"dem"`` (hill-shaded elevation model of the Jacksboro fault, 344x403), ``"mri"``
        (MRI slice, 256x256).

    Returns
    -------
    numpy.ndarray
        (H, W) float64 linear intensity in [0, 1] (photographs are converted from sRGB).
    """
    import matplotlib.cbook as cbook
    import matplotlib.image as mimage

    if name == "grace_hopper" or name == "minduka":
        fname = "grace_hopper.jpg" if name == "grace_hopper" else "Minduka_Present_Blue_Pack.png"
        img = np.asarray(mimage.imread(cbook.get_sample_data(fname, asfileobj=False)), dtype=np.float64)
        if img.max() > 1.0:
            img = img / 255.0
        rgb = img[..., :3]
        grey = _srgb_to_linear(rgb) @ np.array([0.2126, 0.7152, 0.0722])
    elif name == "dem":
        from matplotlib.colors import LightSource

        dem = cbook.get_sample_data("jacksboro_fault_dem.npz")
        elevation = np.asarray(dem["elevation"], dtype=np.float64)
        grey = LightSource(azdeg=315, altdeg=45).hillshade(elevation, vert_exag=0.05, dx=10.0, dy=10.0)
        grey = _srgb_to_linear(grey)
    elif name == "mri":
        with cbook.get_sample_data("s1045.ima.gz") as f:
            raw = f.read()
            if isinstance(f, gzip.GzipFile) or raw[:2] != b"\x1f\x8b":
                data = raw
            else:
                data = gzip.decompress(raw)
        img = np.frombuffer(data, np.uint16).reshape(256, 256).astype(np.float64)
        grey = _srgb_to_linear(img / img.max())
    else:
        raise ValueError(f"unknown texture {name!r}; valid textures: {', '.join(TEXTURES)}")
    return np.clip(grey, 0.0, 1.0)


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resample an image to (height, width) with an antialiasing filter (Pillow ships with matplotlib)."""
    from PIL import Image

    im = Image.fromarray(np.asarray(img, dtype=np.float32), mode="F")
    out = im.resize((int(width), int(height)), Image.Resampling.LANCZOS)
    return np.clip(np.asarray(out, dtype=np.float64), 0.0, 1.0)


def fit_texture(tex: np.ndarray, width: int, height: int, margin: float = 1.0) -> np.ndarray:
    """Resample ``tex`` to one texel per pixel so that it covers a ``width x height`` view (times
    ``margin``), keeping its aspect ratio."""
    th, tw = tex.shape
    scale = margin * max(width / tw, height / th)
    return resize_image(tex, max(2, round(tw * scale)), max(2, round(th * scale)))


def default_camera(sensor_size: tuple[int, int]) -> Camera:
    """Pinhole camera of a sensor: the real focal length of the DAVIS240C / DAVIS346 (0.65 W for other
    sizes) and the principal point at the image centre ``((W-1)/2, (H-1)/2)``, which is also the centre
    the core uses without a camera."""
    W, H = (int(v) for v in sensor_size)
    f = _FOCAL.get((W, H), 0.65 * W)
    return Camera(fx=f, fy=f, cx=(W - 1) / 2.0, cy=(H - 1) / 2.0)
