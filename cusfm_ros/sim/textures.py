"""Texture library for the simulator: real photographs plus procedural detail, mipmapped.

Photographs come from scikit-image's bundled data (offline, in the wheel). Every texture is
resized to ``TEXTURE_SIZE`` squared so all of them stack into one array per mip level, which
makes sampling fully vectorized: ``levels[l][texture_id, row, col]``.

Sampling is trilinear (bilinear within two mip levels, blended by the level of detail), which
is the anti-aliasing: a pixel whose footprint spans many texels reads a pre-filtered level.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

TEXTURE_SIZE = 512

# skimage.data loaders that ship inside the wheel (no download), with what they look like.
PHOTOS_COLOUR = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field",
                 "immunohistochemistry", "retina", "colorwheel")
PHOTOS_GREY = ("brick", "camera", "grass", "gravel", "moon", "coins", "cell", "text", "page",
               "clock")


def _load_photo(name: str) -> np.ndarray:
    import skimage.data  # imported lazily: only the simulator needs scikit-image

    if name == "stereo_motorcycle":
        image = skimage.data.stereo_motorcycle()[0]
    else:
        image = getattr(skimage.data, name)()
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    return image[..., :3].astype(np.float32) / 255.0


def _square(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random square crop resized to TEXTURE_SIZE."""
    h, w = image.shape[:2]
    side = min(h, w)
    top = int(rng.integers(0, h - side + 1))
    left = int(rng.integers(0, w - side + 1))
    crop = image[top:top + side, left:left + side]
    return cv2.resize(crop, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_AREA)


def _value_noise(rng: np.random.Generator, octaves: int = 6) -> np.ndarray:
    """Fractal value noise in [0, 1] (seamless enough for tiling via wrap borders)."""
    out = np.zeros((TEXTURE_SIZE, TEXTURE_SIZE), np.float32)
    amplitude, total = 1.0, 0.0
    for octave in range(octaves):
        cells = 4 * 2**octave
        grid = rng.random((cells, cells)).astype(np.float32)
        grid = np.pad(grid, 1, mode="wrap")
        up = cv2.resize(grid, (TEXTURE_SIZE + 2 * TEXTURE_SIZE // cells,) * 2,
                        interpolation=cv2.INTER_CUBIC)
        offset = TEXTURE_SIZE // cells
        out += amplitude * up[offset:offset + TEXTURE_SIZE, offset:offset + TEXTURE_SIZE]
        total += amplitude
        amplitude *= 0.55
    out /= total
    return (out - out.min()) / max(float(np.ptp(out)), 1e-6)


def _tint(grey: np.ndarray, colour: np.ndarray) -> np.ndarray:
    return grey[..., None] * colour[None, None, :]


def _facade(base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A building facade: photo-based wall with a grid of windows and frames."""
    wall = base * (0.6 + 0.5 * rng.random(3).astype(np.float32))
    out = np.clip(wall, 0, 1).copy()
    rows, cols = int(rng.integers(3, 6)), int(rng.integers(3, 7))
    cell_h, cell_w = TEXTURE_SIZE // rows, TEXTURE_SIZE // cols
    glass = rng.random(3).astype(np.float32) * 0.25
    for r in range(rows):
        for c in range(cols):
            if rng.random() < 0.12:
                continue  # a missing window breaks the repetition
            y0 = r * cell_h + int(cell_h * rng.uniform(0.2, 0.3))
            x0 = c * cell_w + int(cell_w * rng.uniform(0.15, 0.3))
            y1 = r * cell_h + int(cell_h * rng.uniform(0.75, 0.85))
            x1 = c * cell_w + int(cell_w * rng.uniform(0.7, 0.85))
            out[y0 - 3:y1 + 3, x0 - 3:x1 + 3] = 0.85
            shade = glass + rng.random() * 0.2
            out[y0:y1, x0:x1] = shade + 0.15 * base[y0:y1, x0:x1]
            if rng.random() < 0.5:  # curtains / reflections
                out[y0:(y0 + y1) // 2, x0:x1] += 0.25 * rng.random()
    return np.clip(out, 0, 1)


def _asphalt(rng: np.random.Generator, gravel: np.ndarray) -> np.ndarray:
    noise = _value_noise(rng)
    grey = 0.25 + 0.25 * gravel.mean(axis=2) + 0.15 * noise
    return _tint(grey, np.array([1.0, 1.0, 1.02], np.float32)).clip(0, 1)


def _shelves(rng: np.random.Generator, photo: np.ndarray) -> np.ndarray:
    """Warehouse shelving: horizontal beams with boxes of varied colour and labels."""
    out = np.full((TEXTURE_SIZE, TEXTURE_SIZE, 3), 0.2, np.float32)
    levels = int(rng.integers(3, 5))
    height = TEXTURE_SIZE // levels
    for level in range(levels):
        y_beam = level * height
        out[y_beam:y_beam + 10] = np.array([0.9, 0.45, 0.1], np.float32)  # orange beams
        x = 6
        while x < TEXTURE_SIZE - 20:
            w = int(rng.integers(30, 110))
            h = int(rng.integers(height // 3, height - 20))
            colour = np.array([0.55, 0.4, 0.25], np.float32) * rng.uniform(0.7, 1.3)
            box = np.clip(colour, 0, 1)[None, None, :] * (0.85 + 0.3 * photo[:h, :w])
            y0 = y_beam + height - h - 2
            out[y0:y0 + h, x:min(x + w, TEXTURE_SIZE)] = box[:, :min(w, TEXTURE_SIZE - x)]
            label_y, label_x = y0 + h // 3, x + w // 4
            out[label_y:label_y + 12, label_x:label_x + w // 2] = 0.95
            x += w + int(rng.integers(4, 20))
    return out.clip(0, 1)


@dataclass
class TextureLibrary:
    """Named textures, stacked into one mip pyramid array per level."""

    names: list[str]
    levels: list[np.ndarray]
    """levels[l]: (T, S >> l, S >> l, 3) float32."""

    def index(self, name: str) -> int:
        return self.names.index(name)

    def ids(self, prefix: str) -> list[int]:
        return [i for i, n in enumerate(self.names) if n.startswith(prefix)]

    def sample(self, texture_ids: np.ndarray, u_texel: np.ndarray, v_texel: np.ndarray,
               lod: np.ndarray) -> np.ndarray:
        """Trilinear samples (N, 3) at level-0 texel coordinates, wrapping (tiled)."""
        lod = np.clip(lod, 0.0, len(self.levels) - 1.0)
        base = np.floor(lod).astype(np.int64)
        frac = (lod - base).astype(np.float32)[:, None]
        out = np.empty((len(texture_ids), 3), np.float32)
        for level in np.unique(base):
            sel = np.nonzero(base == level)[0]
            low = self._bilinear(level, texture_ids[sel], u_texel[sel], v_texel[sel])
            if level + 1 < len(self.levels):
                high = self._bilinear(level + 1, texture_ids[sel], u_texel[sel], v_texel[sel])
                out[sel] = low + frac[sel] * (high - low)
            else:
                out[sel] = low
        return out

    def _bilinear(self, level: int, ids: np.ndarray, u: np.ndarray, v: np.ndarray
                  ) -> np.ndarray:
        tex = self.levels[level]
        size = tex.shape[1]
        x = u / (1 << level) - 0.5
        y = v / (1 << level) - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0).astype(np.float32)[:, None], (y - y0).astype(np.float32)[:, None]
        x0 = x0.astype(np.int64) % size
        y0 = y0.astype(np.int64) % size
        x1, y1 = (x0 + 1) % size, (y0 + 1) % size
        top = tex[ids, y0, x0] * (1 - fx) + tex[ids, y0, x1] * fx
        bottom = tex[ids, y1, x0] * (1 - fx) + tex[ids, y1, x1] * fx
        return top * (1 - fy) + bottom * fy


def build_texture_library(seed: int) -> TextureLibrary:
    """Deterministic texture set: facades, ground, posters, shelves, cars, floor, ceiling."""
    rng = np.random.default_rng(seed)
    photos = {name: _load_photo(name) for name in PHOTOS_COLOUR + PHOTOS_GREY}
    textures: dict[str, np.ndarray] = {}
    wall_bases = ("brick", "camera", "moon", "coins", "gravel", "cell")
    for i in range(12):
        base = _square(photos[wall_bases[i % len(wall_bases)]], rng)
        textures[f"facade_{i}"] = _facade(base, rng)
    for i, name in enumerate(PHOTOS_COLOUR):
        textures[f"poster_{i}"] = _square(photos[name], rng)
    gravel = _square(photos["gravel"], rng)
    for i in range(4):
        textures[f"asphalt_{i}"] = _asphalt(rng, np.roll(gravel, 97 * i, axis=(0, 1)))
    grass = _square(photos["grass"], rng)
    textures["grass_0"] = _tint(0.3 + 0.7 * grass.mean(axis=2),
                                np.array([0.45, 0.75, 0.3], np.float32))
    for i in range(6):
        textures[f"shelves_{i}"] = _shelves(rng, _square(photos[PHOTOS_GREY[i]], rng))
    for i in range(4):
        noise = _value_noise(rng)
        textures[f"floor_{i}"] = _tint(0.45 + 0.3 * noise + 0.15 * gravel.mean(axis=2),
                                       np.array([0.8, 0.78, 0.7], np.float32))
    textures["ceiling_0"] = _tint(0.8 + 0.15 * _value_noise(rng),
                                  np.array([1.0, 1.0, 0.97], np.float32))
    for i in range(6):
        colour = rng.uniform(0.15, 0.9, 3).astype(np.float32)
        detail = 0.75 + 0.25 * _square(photos["coins"], rng).mean(axis=2)
        car = _tint(detail, colour)
        car[TEXTURE_SIZE // 3: TEXTURE_SIZE // 2] *= 0.35  # dark windows band
        textures[f"car_{i}"] = car
    textures["marking_0"] = np.full((TEXTURE_SIZE, TEXTURE_SIZE, 3), 0.92, np.float32)
    textures["pole_0"] = _tint(0.35 + 0.2 * _value_noise(rng),
                               np.array([0.6, 0.6, 0.65], np.float32))
    names = list(textures)
    level0 = np.stack([textures[n] for n in names]).astype(np.float32)
    levels = [level0]
    while levels[-1].shape[1] > 4:
        prev = levels[-1]
        levels.append(0.25 * (prev[:, 0::2, 0::2] + prev[:, 1::2, 0::2] + prev[:, 0::2, 1::2]
                              + prev[:, 1::2, 1::2]))
    return TextureLibrary(names, levels)
