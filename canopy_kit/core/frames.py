"""Coordinate frames of a robot: rigid transforms between named frames, as ROS tf keeps them.

A transform ``parent -> child`` maps child coordinates into the parent frame (the pose of
the child in the parent), as in ``geometry_msgs/TransformStamped``. :class:`FrameGraph`
answers ``transform(target, source)`` for any two connected frames, whatever the
direction of the edges between them, and says where each edge came from (``tf_static``,
``tf``, ``rig file``, ``estimated``...).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from canopy_kit.errors import InputError


def rigid(
    rotation: np.ndarray | Rotation | None = None,
    translation: np.ndarray | Iterable[float] | None = None,
) -> np.ndarray:
    """A 4x4 rigid transform from a rotation (matrix or scipy Rotation) and a translation."""
    out = np.eye(4)
    if rotation is not None:
        out[:3, :3] = (
            rotation.as_matrix() if isinstance(rotation, Rotation) else np.asarray(rotation, float)
        )
    if translation is not None:
        out[:3, 3] = np.asarray(list(translation), float)
    return out


def from_quaternion(translation: Iterable[float], quaternion_xyzw: Iterable[float]) -> np.ndarray:
    """A 4x4 transform from a translation and a quaternion (x, y, z, w; normalised here)."""
    q = np.asarray(list(quaternion_xyzw), float)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"quaternion {q.tolist()} has no direction")
    return rigid(Rotation.from_quat(q / norm), translation)


def from_rpy(translation: Iterable[float], rpy_deg: Iterable[float]) -> np.ndarray:
    """A 4x4 transform from a translation and roll, pitch, yaw in degrees.

    The ROS convention (tf2 ``setRPY``, URDF ``rpy``): fixed axes, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
    """
    return rigid(Rotation.from_euler("xyz", list(rpy_deg), degrees=True), translation)


def rpy_deg(matrix: np.ndarray) -> list[float]:
    """Roll, pitch, yaw (degrees, ROS convention) of a rotation or rigid transform."""
    return Rotation.from_matrix(np.asarray(matrix)[:3, :3]).as_euler("xyz", degrees=True).tolist()


def rotation_angle_deg(a: np.ndarray, b: np.ndarray | None = None) -> float:
    """Angle (degrees) of the rotation of ``a`` (or of the rotation taking ``b`` to ``a``)."""
    r = np.asarray(a)[:3, :3]
    if b is not None:
        r = np.asarray(b)[:3, :3].T @ r
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def invert(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    r = transform[:3, :3]
    return rigid(r.T, -r.T @ transform[:3, 3])


@dataclass(frozen=True)
class FrameTransform:
    """One edge of the frame tree: ``matrix`` maps ``child`` coordinates into ``parent``."""

    parent: str
    child: str
    matrix: np.ndarray
    source: str

    def to_dict(self) -> dict:
        """Parent, translation, quaternion, roll/pitch/yaw and source (for JSON and reports)."""
        return {
            "parent": self.parent,
            "child": self.child,
            "translation": [round(float(v), 6) for v in self.matrix[:3, 3]],
            "quaternion": [
                round(float(v), 9) for v in Rotation.from_matrix(self.matrix[:3, :3]).as_quat()
            ],
            "rpy_deg": [round(v, 4) for v in rpy_deg(self.matrix)],
            "source": self.source,
        }


class FrameGraph:
    """Named frames joined by rigid transforms; each child has one parent (as in tf)."""

    def __init__(self, transforms: Iterable[FrameTransform] = ()) -> None:
        self._edges: dict[str, FrameTransform] = {}
        for t in transforms:
            self.add(t)

    def add(self, transform: FrameTransform) -> None:
        """Add an edge; an edge to the same child replaces the one before (a later source wins)."""
        if transform.parent == transform.child:
            raise InputError(f"frame {transform.child!r}: a transform from a frame to itself")
        if not np.all(np.isfinite(transform.matrix)):
            raise InputError(
                f"transform {transform.parent!r} -> {transform.child!r} ({transform.source}): "
                "non-finite values"
            )
        self._edges[transform.child] = transform

    def __contains__(self, frame: str) -> bool:
        return frame in self.frames

    def __len__(self) -> int:
        return len(self._edges)

    @property
    def frames(self) -> set[str]:
        """Every frame named by an edge."""
        return {e.child for e in self._edges.values()} | {e.parent for e in self._edges.values()}

    @property
    def edges(self) -> list[FrameTransform]:
        """The edges, sorted by child frame."""
        return [self._edges[k] for k in sorted(self._edges)]

    def _path(self, target: str, source: str) -> list[tuple[FrameTransform, bool]] | None:
        """Edges from ``source`` to ``target``, each with True when walked child -> parent."""
        if target == source:
            return []
        links: dict[str, list[tuple[str, FrameTransform, bool]]] = {}
        for e in self._edges.values():
            links.setdefault(e.child, []).append((e.parent, e, True))
            links.setdefault(e.parent, []).append((e.child, e, False))
        came: dict[str, tuple[str, FrameTransform, bool]] = {}
        queue, seen = deque([source]), {source}
        while queue:
            frame = queue.popleft()
            if frame == target:
                path = []
                while frame != source:
                    prev, edge, up = came[frame]
                    path.append((edge, up))
                    frame = prev
                return path[::-1]
            for nxt, edge, up in links.get(frame, []):
                if nxt not in seen:
                    seen.add(nxt)
                    came[nxt] = (frame, edge, up)
                    queue.append(nxt)
        return None

    def try_transform(self, target: str, source: str) -> np.ndarray | None:
        """The 4x4 mapping ``source`` coordinates into ``target``, or None when not connected."""
        path = self._path(target, source)
        if path is None:
            return None
        out = np.eye(4)
        for edge, up in path:  # each step maps the current frame into the next one
            out = (edge.matrix if up else invert(edge.matrix)) @ out
        return out

    def transform(self, target: str, source: str) -> np.ndarray:
        """The 4x4 mapping ``source`` coordinates into ``target`` (InputError when not connected)."""
        out = self.try_transform(target, source)
        if out is None:
            known = ", ".join(sorted(self.frames)) or "none"
            raise InputError(
                f"no transform between frames {source!r} and {target!r} (frames known: {known})"
            )
        return out

    def sources(self, target: str, source: str) -> list[str]:
        """Where the edges joining two frames came from (empty when the frames are the same)."""
        path = self._path(target, source) or []
        return list(dict.fromkeys(edge.source for edge, _ in path))
