"""Vectorized ray casting of a ``World`` through any of the project's camera models.

Each pixel's ray comes from ``camera.unproject`` (so distortion, fisheye and F-theta are exact),
is moved into the world by the camera pose — one pose per image row under a rolling shutter —
and is intersected with the horizontal planes analytically and with the candidate quads in a few
matrix products. Quads are culled per image by range and by the camera's viewing pyramid.

Written here rather than with an OpenGL/Vulkan rasterizer because rasterizers cannot express
non-pinhole projections or per-row poses, and CI has no GPU.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.sim.textures import TEXTURE_SIZE, TextureLibrary
from cusfm_ros.sim.world import World


@dataclass(frozen=True)
class Lighting:
    sun_direction: tuple[float, float, float] = (0.4, 0.3, 0.86)
    ambient: float = 0.45
    exposure: float = 1.0
    sky_horizon: tuple[float, float, float] = (0.78, 0.84, 0.92)
    sky_zenith: tuple[float, float, float] = (0.35, 0.52, 0.85)


@dataclass(frozen=True)
class RenderOptions:
    max_range_m: float = 150.0
    small_object_range_m: float = 60.0
    noise_sigma: float = 1.5 / 255.0
    shot_noise: float = 0.004


TILE_PX = 32


@dataclass
class CameraRays:
    """Per-camera cache: unit rays (N, 3), angular pixel size (N,), viewing pyramid, and
    square pixel tiles with their bounding cones (axis, half-angle) for per-tile culling."""

    rays: np.ndarray
    pixel_angle_rad: np.ndarray
    pyramid_normals: np.ndarray | None
    tiles: list[np.ndarray]
    tile_axes: np.ndarray
    tile_half_angles_rad: np.ndarray

    @classmethod
    def for_camera(cls, camera: CameraBase) -> CameraRays:
        grid = camera.pixel_grid()
        rays = camera.unproject(grid)
        shifted = camera.unproject(grid + np.array([1.0, 0.0]))
        angle = np.linalg.norm(shifted - rays, axis=1)
        index = np.arange(len(grid)).reshape(camera.height, camera.width)
        tiles, axes, half_angles = [], [], []
        for top in range(0, camera.height, TILE_PX):
            for left in range(0, camera.width, TILE_PX):
                members = index[top:top + TILE_PX, left:left + TILE_PX].ravel()
                axis = rays[members].mean(axis=0)
                axis /= np.linalg.norm(axis)
                cos = np.clip(rays[members] @ axis, -1.0, 1.0)
                tiles.append(members)
                axes.append(axis)
                half_angles.append(np.arccos(cos.min()) + 2.0 * angle[members].max())
        normals = None
        if rays[:, 2].min() > 0.05:  # perspective-like: bounded x/z, y/z
            xz, yz = rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]
            pad = 0.02
            normals = np.array([[1, 0, -(xz.min() - pad)], [-1, 0, xz.max() + pad],
                                [0, 1, -(yz.min() - pad)], [0, -1, yz.max() + pad]])
        return cls(rays, angle, normals, tiles, np.array(axes), np.array(half_angles))


class Renderer:
    def __init__(self, world: World, textures: TextureLibrary,
                 options: RenderOptions = RenderOptions()) -> None:
        self.world = world
        self.textures = textures
        self.options = options
        self._small = np.isin(np.array(world.kinds), ["car", "pole", "crate", "sign",
                                                       "marking"])

    # ------------------------------------------------------------------------------ culling
    def _candidates(self, cam_from_world: np.ndarray, rays: CameraRays) -> np.ndarray:
        arr = self.world.arrays
        center = -cam_from_world[:3, :3].T @ cam_from_world[:3, 3]
        rel = center - arr["origin"]
        a = np.clip(np.einsum("ij,ij->i", rel, arr["u"]), 0, arr["size"][:, 0])
        b = np.clip(np.einsum("ij,ij->i", rel, arr["v"]), 0, arr["size"][:, 1])
        closest = arr["origin"] + a[:, None] * arr["u"] + b[:, None] * arr["v"]
        distance = np.linalg.norm(closest - center, axis=1)
        keep = distance < np.where(self._small, self.options.small_object_range_m,
                                   self.options.max_range_m)
        corners_cam = arr["corners"] @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        if rays.rays[:, 2].min() >= 0.0:  # the camera sees nothing behind itself
            keep &= ~np.all(corners_cam[..., 2] < 0, axis=1)
        if rays.pyramid_normals is not None:
            side = corners_cam @ rays.pyramid_normals.T  # (M, 4 corners, 4 planes)
            keep &= ~np.any(np.all(side < 0, axis=1), axis=1)
        return np.nonzero(keep)[0]

    # -------------------------------------------------------------------------- intersection
    def _intersect_quads(self, origins: np.ndarray, dirs: np.ndarray, quads: np.ndarray):
        """Nearest quad hit per ray: (t, quad index or -1, a, b)."""
        arr = self.world.arrays
        n = arr["normal"][quads].astype(np.float32)
        u = arr["u"][quads].astype(np.float32)
        v = arr["v"][quads].astype(np.float32)
        q = arr["origin"][quads]
        size = arr["size"][quads].astype(np.float32)
        d32 = dirs.astype(np.float32)
        o = origins.astype(np.float64)
        dn, du, dv = d32 @ n.T, d32 @ u.T, d32 @ v.T
        if o.ndim == 1:  # one origin for all rays (global shutter)
            on = ((q - o) * arr["normal"][quads]).sum(1).astype(np.float32)[None]
            ou = ((o - q) * arr["u"][quads]).sum(1).astype(np.float32)[None]
            ov = ((o - q) * arr["v"][quads]).sum(1).astype(np.float32)[None]
        else:
            on = ((q * arr["normal"][quads]).sum(1)[None] - o @ arr["normal"][quads].T)
            ou = (o @ arr["u"][quads].T - (q * arr["u"][quads]).sum(1)[None])
            ov = (o @ arr["v"][quads].T - (q * arr["v"][quads]).sum(1)[None])
            on, ou, ov = on.astype(np.float32), ou.astype(np.float32), ov.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = on / dn
        a = ou + t * du
        b = ov + t * dv
        valid = (t > 1e-3) & (a >= 0) & (a <= size[:, 0]) & (b >= 0) & (b <= size[:, 1])
        t = np.where(valid, t, np.inf)
        best = np.argmin(t, axis=1)
        rows = np.arange(len(dirs))
        hit = np.isfinite(t[rows, best])
        index = np.where(hit, quads[best], -1)
        # the search ran in float32; the winning distance is recomputed exactly in float64
        k = quads[best]
        o_full = np.broadcast_to(o, dirs.shape)
        normal64 = arr["normal"][k]
        t_exact = (np.einsum("ij,ij->i", arr["origin"][k] - o_full, normal64)
                   / np.einsum("ij,ij->i", dirs, normal64))
        t_best = np.where(hit, t_exact, np.inf)
        return t_best, index, a[rows, best], b[rows, best]

    # ------------------------------------------------------------------------------- shading
    def render(self, camera: CameraBase, rays: CameraRays, world_from_cam: np.ndarray,
               lighting: Lighting, rng: np.random.Generator | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """Render one image.

        Args:
            world_from_cam: (4, 4) for a global shutter or (height, 4, 4), one pose per row.
            rng: sensor-noise generator; None renders noise-free.
        Returns:
            (height, width, 3) uint8 RGB image and (height, width) float64 range along each ray
            in metres (inf where the ray leaves the scene).
        """
        height, width = camera.height, camera.width
        per_row = world_from_cam.ndim == 3
        mid = world_from_cam[height // 2] if per_row else world_from_cam
        quads = self._candidates(np.linalg.inv(mid), rays)
        # Per-tile culling: a quad's bounding sphere must reach into the tile's cone of rays.
        # Under a rolling shutter the camera moves during readout: widen both by that motion.
        slack_m, slack_rad = 0.0, 0.0
        if per_row:
            row_of_pixel = np.repeat(np.arange(height), width)
            slack_m = float(np.max(np.linalg.norm(world_from_cam[:, :3, 3] - mid[:3, 3], axis=1)))
            relative = np.einsum("rji,jk->rik", world_from_cam[:, :3, :3], mid[:3, :3])
            slack_rad = float(np.max(np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2)
                                                        - 1) / 2, -1, 1))))
        arr = self.world.arrays
        to_center = arr["sphere_center"][quads] - mid[:3, 3]
        distance = np.linalg.norm(to_center, axis=1)
        radius = arr["sphere_radius"][quads] + slack_m
        inside = distance <= radius
        angular_radius = np.arcsin(np.clip(radius / np.maximum(distance, 1e-9), 0.0, 1.0))
        directions = to_center / np.maximum(distance, 1e-9)[:, None]
        axes_world = rays.tile_axes @ mid[:3, :3].T
        angle = np.arccos(np.clip(axes_world @ directions.T, -1.0, 1.0))  # (tiles, quads)
        reach = angle <= (rays.tile_half_angles_rad[:, None] + angular_radius[None]
                          + slack_rad + 1e-3)
        reach |= inside[None]
        if per_row:
            poses = world_from_cam[row_of_pixel]
            dirs = np.einsum("nij,nj->ni", poses[:, :3, :3], rays.rays)
            origins = poses[:, :3, 3]
        else:
            dirs = rays.rays @ mid[:3, :3].T
            origins = mid[:3, 3]
        count = height * width
        best_t = np.full(count, np.inf)
        index = np.full(count, -1, np.int64)
        a = np.zeros(count, np.float32)
        b = np.zeros(count, np.float32)
        for tile_index, members in enumerate(rays.tiles):
            tile_quads = quads[reach[tile_index]]
            if len(tile_quads):
                tile_origins = origins[members] if per_row else origins
                best_t[members], index[members], a[members], b[members] = (
                    self._intersect_quads(tile_origins, dirs[members], tile_quads))
        colour, range_m = self._shade(origins, dirs, rays.pixel_angle_rad, best_t, index, a, b,
                                      lighting)
        if rng is not None:
            sigma = np.sqrt(self.options.noise_sigma**2 + self.options.shot_noise * colour)
            colour = colour + rng.standard_normal(colour.shape).astype(np.float32) * sigma
        image = np.clip(colour * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return image.reshape(height, width, 3), range_m.reshape(height, width)

    def _shade(self, origins, dirs, pixel_angle, best_t, index, a, b, lighting: Lighting):
        count = len(dirs)
        origins_full = np.broadcast_to(origins, dirs.shape)
        tex_id = np.zeros(count, np.int64)
        tu = np.zeros(count)
        tv = np.zeros(count)
        texel = np.ones(count)
        normal = np.zeros((count, 3))
        albedo = np.ones(count, np.float32)
        hit = index >= 0
        if hit.any():
            arr = self.world.arrays
            k = index[hit]
            tex_id[hit] = arr["texture"][k]
            texel[hit] = arr["texel"][k]
            tu[hit] = a[hit] / texel[hit] + arr["offset"][k, 0]
            tv[hit] = arr["offset"][k, 1] - b[hit] / texel[hit]
            normal[hit] = arr["normal"][k]
            albedo[hit] = arr["albedo"][k]
        for plane in self.world.planes:
            dz = dirs[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (plane["height"] - origins_full[:, 2]) / dz
            x = origins_full[:, 0] + t * dirs[:, 0]
            y = origins_full[:, 1] + t * dirs[:, 1]
            x0, x1, y0, y1 = plane["extent"]
            hit = (t > 1e-3) & (t < best_t) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            if not hit.any():
                continue
            tile = plane["tile"]
            ix = np.floor(x[hit] / tile).astype(np.int64)
            iy = np.floor(y[hit] / tile).astype(np.int64)
            key = (ix * 73856093) ^ (iy * 19349663) ^ plane["seed"]
            choice = plane["texture_ids"][np.abs(key) % len(plane["texture_ids"])]
            offset = (np.abs(key * 2654435761) % TEXTURE_SIZE).astype(np.float64)
            best_t[hit] = t[hit]
            tex_id[hit] = choice
            texel[hit] = plane["texel"]
            tu[hit] = x[hit] / plane["texel"] + offset
            tv[hit] = -y[hit] / plane["texel"] + offset * 0.37
            normal[hit] = [0.0, 0.0, 1.0]
            albedo[hit] = 1.0
        hit = np.isfinite(best_t)
        out = np.empty((count, 3), np.float32)
        if hit.any():
            cos_incidence = np.abs(np.einsum("ij,ij->i", normal[hit], dirs[hit]))
            footprint = best_t[hit] * pixel_angle[hit] / (
                texel[hit] * np.sqrt(np.maximum(cos_incidence, 0.02)))
            lod = np.log2(np.maximum(footprint, 1.0))
            texture = self.textures.sample(tex_id[hit], tu[hit], tv[hit], lod)
            facing = -np.sign(np.einsum("ij,ij->i", normal[hit], dirs[hit]))[:, None] * normal[hit]
            sun = np.asarray(lighting.sun_direction) / np.linalg.norm(lighting.sun_direction)
            diffuse = np.maximum(facing @ sun, 0.0).astype(np.float32)
            shade = lighting.ambient + (1.0 - lighting.ambient) * diffuse
            out[hit] = texture * (albedo[hit] * shade * lighting.exposure)[:, None]
        if (~hit).any():
            up = np.clip(dirs[~hit, 2], 0.0, 1.0)[:, None].astype(np.float32)
            horizon = np.asarray(lighting.sky_horizon, np.float32)
            zenith = np.asarray(lighting.sky_zenith, np.float32)
            sky = horizon + (zenith - horizon) * np.sqrt(up)
            out[~hit] = (sky if self.world.sky else sky * 0.1) * lighting.exposure
        return out, best_t
