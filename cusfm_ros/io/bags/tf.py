"""The transform tree of a bag: static edges from /tf_static, time series from /tf."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.core.geometry import Rigid3, first_non_increasing
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import BagError, GeometryError


@dataclass
class TransformTree:
    static: dict[str, tuple[str, Rigid3]] = field(default_factory=dict)
    """child -> (parent, parent_from_child)."""
    dynamic: dict[tuple[str, str], list[tuple[int, Rigid3]]] = field(default_factory=dict)
    """(parent, child) -> [(stamp_ns, parent_from_child)] in arrival order."""

    def add_static(self, parent: str, child: str, parent_from_child: Rigid3) -> None:
        self.static[child.lstrip("/")] = (parent.lstrip("/"), parent_from_child)

    def add_dynamic(self, stamp_ns: int, parent: str, child: str, pose: Rigid3) -> None:
        self.dynamic.setdefault((parent.lstrip("/"), child.lstrip("/")), []).append(
            (stamp_ns, pose))

    def _parent(self, frame: str) -> tuple[str, Rigid3 | None] | None:
        if frame in self.static:
            return self.static[frame][0], self.static[frame][1]
        for parent, child in self.dynamic:
            if child == frame:
                return parent, None
        return None

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        while (step := self._parent(chain[-1])) is not None:
            if step[0] in chain:
                raise BagError(f"the tf tree has a cycle through {step[0]}")
            chain.append(step[0])
        return chain

    def static_transform(self, target: str, source: str) -> Rigid3:
        """``target_from_source`` through static edges only (extrinsics)."""
        target, source = target.lstrip("/"), source.lstrip("/")

        def to_root(frame: str) -> dict[str, Rigid3]:
            out, pose = {frame: Rigid3.identity()}, Rigid3.identity()
            while frame in self.static:
                parent, parent_from_frame = self.static[frame]
                pose = parent_from_frame * pose
                frame = parent
                if frame in out:
                    raise BagError(f"/tf_static has a cycle through {frame}")
                out[frame] = pose
            return out

        from_source, from_target = to_root(source), to_root(target)
        common = next((f for f in from_source if f in from_target), None)
        if common is None:
            raise BagError(f"/tf_static has no chain between {target} and {source}")
        return from_target[common].inverse() * from_source[common]

    def trajectory(self, world: str, body: str) -> Trajectory:
        """``world_from_body`` over time through the dynamic (and static) edges between them.

        The stamps of the densest dynamic edge on the chain are the time base; the other
        dynamic edges are interpolated there (stamps outside their span are dropped).
        """
        chain = self._chain(body)
        if world not in chain:
            raise BagError(f"no tf chain from {world} to {body} (the chain of {body} is "
                           f"{' <- '.join(chain)}); pass --odom-topic or --world-frame")
        chain = chain[: chain.index(world) + 1]
        edges = []  # from the body upwards: (parent, child, static pose or None)
        for child, parent in zip(chain[:-1], chain[1:]):
            static = self.static.get(child)
            edges.append((parent, child, static[1] if static and static[0] == parent else None))
        series = {}
        for parent, child, static in edges:
            if static is None:
                samples = self.dynamic[(parent, child)]
                stamps = np.array([s for s, _ in samples], dtype=np.int64)
                if (bad := first_non_increasing(stamps)) is not None:
                    raise BagError(f"/tf {parent} -> {child}: stamps are not increasing at "
                                   f"message {bad}; the recording mixes publishers or clocks")
                series[(parent, child)] = Trajectory(
                    stamps, np.stack([p.matrix() for _, p in samples]))
        if not series:
            raise BagError(f"the chain {world} -> {body} has no moving transform")
        stamps = max(series.values(), key=len).stamps_ns  # the densest edge sets the time base
        for trajectory in series.values():
            inside = (stamps >= trajectory.stamps_ns[0]) & (stamps <= trajectory.stamps_ns[-1])
            stamps = stamps[inside]
        if len(stamps) == 0:
            raise BagError(f"the moving transforms of {world} -> {body} never overlap in time")
        poses = np.repeat(np.eye(4)[None], len(stamps), axis=0)
        for parent, child, static in edges:  # compose world_from_body = ... * parent_from_child
            edge = (np.repeat(static.matrix()[None], len(stamps), axis=0) if static is not None
                    else series[(parent, child)].interpolate(stamps))
            poses = edge @ poses
        try:
            return Trajectory(stamps, poses)
        except GeometryError as exc:
            raise BagError(f"tf {world} -> {body}: {exc}") from None
