"""Scene geometry: textured rectangles ("quads") laid out along the route.

A quad is ``origin + a * axis_u + b * axis_v`` for ``0 <= a <= size_u``, ``0 <= b <= size_v``
with orthonormal axes; its normal is ``axis_u x axis_v``. Boxes (parked cars, pallets, poles)
are five quads. Everything is stored as flat arrays so the renderer intersects all candidate
quads with all rays in a few matrix products.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.sim.route import Route
from cusfm_ros.sim.textures import TEXTURE_SIZE, TextureLibrary


@dataclass
class World:
    origins: list = field(default_factory=list)
    axes_u: list = field(default_factory=list)
    axes_v: list = field(default_factory=list)
    sizes: list = field(default_factory=list)
    texture_ids: list = field(default_factory=list)
    texel_sizes_m: list = field(default_factory=list)
    texel_offsets: list = field(default_factory=list)
    albedo: list = field(default_factory=list)
    kinds: list = field(default_factory=list)
    planes: list = field(default_factory=list)
    sky: bool = True
    arrays: dict = field(default_factory=dict, repr=False)

    def add_plane(self, height_m: float, extent_xy: tuple[float, float, float, float],
                  tile_m: float, texture_ids: list[int], texel_size_m: float, seed: int,
                  kind: str) -> None:
        """A horizontal plane (ground, floor, ceiling) bounded by ``extent_xy``
        = (x_min, x_max, y_min, y_max), tiled with textures chosen per tile by a hash.

        Planes are intersected analytically (one division per ray) instead of as hundreds of
        tile quads.
        """
        self.planes.append(dict(height=float(height_m), extent=tuple(map(float, extent_xy)),
                                tile=float(tile_m), texture_ids=np.asarray(texture_ids),
                                texel=float(texel_size_m), seed=int(seed), kind=kind))

    def add_quad(self, origin, axis_u, axis_v, size_u, size_v, texture_id, texel_size_m,
                 rng: np.random.Generator, kind: str = "", albedo: float = 1.0) -> None:
        u = np.asarray(axis_u, float)
        v = np.asarray(axis_v, float)
        self.origins.append(np.asarray(origin, float))
        self.axes_u.append(u / np.linalg.norm(u))
        self.axes_v.append(v / np.linalg.norm(v))
        self.sizes.append((float(size_u), float(size_v)))
        self.texture_ids.append(int(texture_id))
        self.texel_sizes_m.append(float(texel_size_m))
        self.texel_offsets.append(rng.uniform(0, TEXTURE_SIZE, 2))
        self.albedo.append(float(albedo))
        self.kinds.append(kind)

    def add_box(self, center_xy, yaw_rad, length_m, width_m, height_m, texture_id,
                texel_size_m, rng, kind="box", base_z_m=0.0) -> None:
        """An upright box standing on the ground: four sides and a top."""
        c, s = np.cos(yaw_rad), np.sin(yaw_rad)
        forward, left, up = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0, 0, 1.0])
        center = np.array([center_xy[0], center_xy[1], base_z_m])
        half_l, half_w = forward * length_m / 2, left * width_m / 2
        # each side seen from outside: u along the side, v up, normal outwards
        self.add_quad(center - half_l - half_w, forward, up, length_m, height_m, texture_id,
                      texel_size_m, rng, kind)  # right side, normal -left
        self.add_quad(center + half_l + half_w, -forward, up, length_m, height_m, texture_id,
                      texel_size_m, rng, kind)
        self.add_quad(center + half_l - half_w, left, up, width_m, height_m, texture_id,
                      texel_size_m, rng, kind)
        self.add_quad(center - half_l + half_w, -left, up, width_m, height_m, texture_id,
                      texel_size_m, rng, kind)
        self.add_quad(center - half_l - half_w + up * height_m, forward, left, length_m,
                      width_m, texture_id, texel_size_m, rng, kind)

    def finalize(self) -> World:
        u = np.array(self.axes_u)
        v = np.array(self.axes_v)
        normal = np.cross(u, v)
        sizes = np.array(self.sizes)
        origins = np.array(self.origins)
        corners = np.stack([origins, origins + u * sizes[:, :1], origins + v * sizes[:, 1:],
                            origins + u * sizes[:, :1] + v * sizes[:, 1:]], axis=1)
        self.arrays = dict(origin=origins, u=u, v=v, normal=normal, size=sizes,
                           texture=np.array(self.texture_ids, np.int64),
                           texel=np.array(self.texel_sizes_m), offset=np.array(self.texel_offsets),
                           albedo=np.array(self.albedo, np.float32), corners=corners,
                           sphere_center=corners.mean(axis=1),
                           sphere_radius=0.5 * np.linalg.norm(u * sizes[:, :1]
                                                              + v * sizes[:, 1:], axis=1))
        return self

    def __len__(self) -> int:
        return len(self.origins)


def _facade_row(world: World, textures: TextureLibrary, rng, start, direction, length,
                offset_m, side: float, min_height, max_height, gap_probability,
                span_m: tuple[float, float] = (-np.inf, np.inf)):
    """Buildings along one straight, facing the road, on the side ``side`` (+1 left), each
    clipped to ``span_m`` (distance along the straight from its start)."""
    normal_in = np.array([-direction[1], direction[0]]) * side  # towards the facade
    facade_ids = textures.ids("facade_")
    poster_ids = textures.ids("poster_")
    position = -6.0
    while position < length + 6.0:
        width = rng.uniform(7.0, 16.0)
        if rng.random() < gap_probability:
            position += rng.uniform(3.0, 8.0)
            continue
        setback = rng.uniform(-0.8, 0.8)
        begin, end = max(position, span_m[0]), min(position + width, span_m[1])
        if end - begin < 3.0:  # outside the span, or too thin a sliver of a building
            position += width + rng.uniform(0.0, 1.5)
            continue
        next_position = position + width
        position, width = begin, end - begin
        base = start + direction * position + normal_in * (offset_m + setback)
        height = rng.uniform(min_height, max_height)
        # seen from the road, the facade's u axis runs to the viewer's right
        u = np.r_[direction * side, 0.0]
        origin = np.r_[base + direction * width if side < 0 else base, 0.0]
        texture = int(rng.choice(facade_ids))
        world.add_quad(origin, u, [0, 0, 1], width, height, texture,
                       rng.uniform(0.9, 1.3) * height / TEXTURE_SIZE * 1.0, rng, "facade")
        if rng.random() < 0.45:  # a shop sign / poster on the ground floor, 3 cm proud
            sign_w = min(width * 0.6, rng.uniform(2.5, 5.0))
            sign_origin = origin + u * rng.uniform(0.3, width - sign_w - 0.2) + np.r_[
                -normal_in * 0.03, rng.uniform(0.6, 1.6)]
            world.add_quad(sign_origin, u, [0, 0, 1], sign_w, sign_w * 0.6,
                           int(rng.choice(poster_ids)), sign_w / TEXTURE_SIZE, rng, "sign")
        position = next_position + rng.uniform(0.0, 1.5)


def build_street(route: Route, textures: TextureLibrary, seed: int) -> World:
    """A city block loop: asphalt road, facades on both sides, parked cars, poles."""
    rng = np.random.default_rng(seed)
    world = World(sky=True)
    hx, hy = route.half_extent_m
    margin = 45.0
    asphalt = textures.ids("asphalt_")
    world.add_plane(0.0, (-hx - margin, hx + margin, -hy - margin, hy + margin), 10.0, asphalt,
                    0.02, seed + 1, "ground")
    facade_offset = 9.0
    inner_room = min(route.straight_x_m, route.straight_y_m) / 2 + route.corner_radius_m
    for start, direction, length in route.segments():
        _facade_row(world, textures, rng, start, direction, length, facade_offset, -1.0, 7, 22,
                    0.12)
        if inner_room > facade_offset + 2.0:
            # inside the block a row ends where the next straight's would begin, facade_offset
            # from both roads' centre lines: past it the car would drive through the building
            # at the corner (a 1000-frame street did, once a lap)
            inner = (facade_offset - route.corner_radius_m,
                     length + route.corner_radius_m - facade_offset)
            _facade_row(world, textures, rng, start, direction, length, facade_offset, 1.0, 6,
                        15, 0.2, inner)
        left = np.array([-direction[1], direction[0]])
        # lane markings: dashed centre line slightly above the asphalt
        for d in np.arange(1.0, length - 3.0, 6.0):
            p = start + direction * d
            world.add_quad(np.r_[p - left * 0.06, 0.005], np.r_[direction, 0], np.r_[left, 0],
                           3.0, 0.12, textures.index("marking_0"), 0.05, rng, "marking")
        # parked cars along the kerbs and a few poles
        for side in (-1.0, 1.0):
            d = rng.uniform(0.0, 8.0)
            while d < length - 2.0:
                if rng.random() < 0.55:
                    center = start + direction * d + left * side * 5.6
                    yaw = np.arctan2(direction[1], direction[0]) + rng.normal(0, 0.03)
                    world.add_box(center, yaw, 4.3, 1.8, 1.45,
                                  int(rng.choice(textures.ids("car_"))), 0.01, rng, "car")
                d += rng.uniform(5.5, 12.0)
            for d in np.arange(rng.uniform(3, 12), length, rng.uniform(14, 22)):
                center = start + direction * d + left * side * 7.2
                world.add_box(center, 0.0, 0.25, 0.25, 4.5, textures.index("pole_0"), 0.01, rng,
                              "pole")
    return world.finalize()


def build_indoor(route: Route, textures: TextureLibrary, seed: int) -> World:
    """A warehouse/office loop: a corridor between an outer wall and an inner block."""
    rng = np.random.default_rng(seed)
    world = World(sky=False)
    hx, hy = route.half_extent_m
    half_width, height = 1.8, 3.0
    wall_ids = textures.ids("shelves_") + textures.ids("poster_") + textures.ids("facade_")
    floor_ids = textures.ids("floor_")

    def wall_ring(half_x, half_y, facing_in: bool):
        # counter-clockwise rectangle corners; walls face the corridor
        corners = [np.array([-half_x, -half_y]), np.array([half_x, -half_y]),
                   np.array([half_x, half_y]), np.array([-half_x, half_y])]
        for i in range(4):
            a, b = corners[i], corners[(i + 1) % 4]
            length = np.linalg.norm(b - a)
            direction = (b - a) / length
            position = 0.0
            while position < length - 1e-6:
                panel = min(rng.uniform(2.5, 5.0), length - position)
                if facing_in:  # outer wall seen from inside: u runs clockwise
                    origin, u = a + direction * (position + panel), -direction
                else:
                    origin, u = a + direction * position, direction
                world.add_quad(np.r_[origin, 0.0], np.r_[u, 0.0], [0, 0, 1], panel, height,
                               int(rng.choice(wall_ids)), height / TEXTURE_SIZE, rng, "wall")
                position += panel

    wall_ring(hx + half_width, hy + half_width, facing_in=True)
    inner_x, inner_y = hx - half_width, hy - half_width
    if inner_x > 0.2 and inner_y > 0.2:
        wall_ring(inner_x, inner_y, facing_in=False)
    extent = (-hx - half_width, hx + half_width, -hy - half_width, hy + half_width)
    world.add_plane(0.0, extent, 4.0, floor_ids, 0.008, seed + 1, "floor")
    world.add_plane(height, extent, 4.0, [textures.index("ceiling_0")], 0.01, seed + 2,
                    "ceiling")
    # pallets and boxes against the walls as occluders
    for start, direction, length in route.segments():
        left = np.array([-direction[1], direction[0]])
        for d in np.arange(rng.uniform(0.5, 3.0), length, rng.uniform(3.0, 6.0)):
            side = rng.choice([-1.0, 1.0])
            center = start + direction * d + left * side * (half_width - 0.35)
            world.add_box(center, np.arctan2(direction[1], direction[0]), 0.8, 0.5,
                          rng.uniform(0.4, 1.2), int(rng.choice(textures.ids("shelves_"))),
                          0.004, rng, "crate")
    return world.finalize()
