"""Body parts: which landmarks bound each of the 15 capsules, mapped from any skeleton.

The body model is data (``motion/data/bodyparts/parts.yaml``): 15 tapered capsules, each
between two semantic landmarks (roles such as ``knee_l``) with two radii in metres. A
skeleton's joints are mapped to the roles automatically for the common BVH naming
conventions (``roles.yaml``: CMU/MotionBuilder, Daz/Second Life, 3ds Max, Mixamo), or by a
spec file with the same keys; what cannot be mapped is reported part by part.

A role is the mean of one or more *points*: joint positions, or End Site positions written
``NAME.end``. Shapes: ``J`` joints, ``E`` end sites, ``R`` roles, ``P`` parts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import yaml
from torch import Tensor

from motion.kinematics import FKResult, Skeleton

__all__ = ["BodyModel", "BodyPartMappingError", "end_site_positions", "load_spec", "map_roles"]

DATA = Path(__file__).resolve().parent / "data" / "bodyparts"


class BodyPartMappingError(ValueError):
    """Some body parts could not be mapped to the skeleton's joints."""


def _read_yaml(path: Path) -> dict:
    try:
        return yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise FileNotFoundError(f"body-part spec not found: {path}") from None
    except yaml.YAMLError as err:
        raise BodyPartMappingError(f"{path}: not valid YAML ({err})") from None


def load_spec(name_or_path: str | Path) -> dict[str, list[str]]:
    """A role -> point-names mapping from a spec file (a path, or a bundled name such as
    ``"cmu_cgspeed"``, ``"cmu_daz"``, ``"pose2sim_21"``)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = DATA / f"{name_or_path}.yaml"
    spec = _read_yaml(path)
    if "roles" not in spec or not isinstance(spec["roles"], dict):
        raise BodyPartMappingError(f"{path}: expected a 'roles' mapping of role -> joint name(s)")
    return {r: [v] if isinstance(v, str) else list(v) for r, v in spec["roles"].items()}


def _parts() -> dict[str, dict]:
    return _read_yaml(DATA / "parts.yaml")["parts"]


def map_roles(
    joint_names: list[str], end_site_joints: list[str], spec: dict | str | Path | None = None
) -> dict[str, list[str]]:
    """Map every role the parts need to point names of this skeleton.

    Args:
        joint_names: the skeleton's joints (a ``prefix:`` such as Mixamo's is ignored).
        end_site_joints: joints that have an End Site (their ``.end`` points exist).
        spec: explicit mapping (dict or spec file) used before the automatic table.

    Returns:
        role -> list of point names as they appear in the skeleton (``NAME`` or ``NAME.end``).

    Raises:
        BodyPartMappingError: naming each part that cannot be mapped and its missing roles.
    """
    explicit = load_spec(spec) if isinstance(spec, str | Path) else (spec or {})
    table = _read_yaml(DATA / "roles.yaml")["roles"]
    canon = {}
    for n in joint_names:
        canon[n.split(":")[-1].lower()] = n
    for n in end_site_joints:
        canon[n.split(":")[-1].lower() + ".end"] = n + ".end"

    def resolve(candidate) -> list[str] | None:
        items = [candidate] if isinstance(candidate, str) else list(candidate)
        found = [canon.get(str(i).lower()) for i in items]
        return None if any(f is None for f in found) else found

    needed = sorted({r for p in _parts().values() for r in (p["from"], p["to"])})
    mapping: dict[str, list[str]] = {}
    for role in needed:
        if role in explicit:
            got = resolve(explicit[role])
            if got is None:
                raise BodyPartMappingError(
                    f"spec maps role {role!r} to {explicit[role]!r}, not found among the joints"
                )
            mapping[role] = got
            continue
        for cand in table.get(role, []):
            got = resolve(cand)
            if got is not None:
                mapping[role] = got
                break
    missing = {
        part: [r for r in (d["from"], d["to"]) if r not in mapping]
        for part, d in _parts().items()
        if d["from"] not in mapping or d["to"] not in mapping
    }
    if missing:
        lines = "; ".join(f"{p} (no {', '.join(r)})" for p, r in missing.items())
        raise BodyPartMappingError(
            f"could not map {len(missing)} body parts: {lines}. Joints: {joint_names}. Pass a "
            "spec file mapping these roles to joint names (see motion/data/bodyparts/)."
        )
    return mapping


def end_site_positions(skeleton: Skeleton, fk: FKResult) -> Tensor:
    """Positions of every End Site (in ``skeleton.end_sites`` order). ``(..., E, 3)`` metres."""
    if not skeleton.end_sites:
        return fk.positions[..., :0, :]
    joints = torch.tensor(list(skeleton.end_sites), dtype=torch.long)
    offs = torch.stack(list(skeleton.end_sites.values())).to(fk.positions)  # (E, 3)
    rot = fk.rotations[..., joints, :, :]
    return fk.positions[..., joints, :] + (rot @ offs.unsqueeze(-1)).squeeze(-1)


@dataclass
class BodyModel:
    """Capsule parts over a point set (joints then end sites, or keypoints).

    Attributes:
        part_names: P names. roles: R role names.
        role_weights: ``(R, N)`` each role as a mean over the N points.
        part_roles: ``(P, 2)`` long, the roles at each part's ends.
        radii: ``(P, 2)`` metres, proximal and distal radius (the body-size adjustment G
            scales these and the skeleton's offsets).
        mapping: role -> point names used.
    """

    part_names: list[str]
    roles: list[str]
    role_weights: Tensor
    part_roles: Tensor
    radii: Tensor
    mapping: dict[str, list[str]]

    @classmethod
    def from_points(cls, point_names: list[str], mapping: dict[str, list[str]]) -> BodyModel:
        parts = _parts()
        roles = sorted(mapping)
        index = {n: i for i, n in enumerate(point_names)}
        w = torch.zeros(len(roles), len(point_names), dtype=torch.float64)
        for r, role in enumerate(roles):
            for name in mapping[role]:
                if name not in index:
                    raise BodyPartMappingError(f"role {role!r}: no point {name!r}")
                w[r, index[name]] += 1.0 / len(mapping[role])
        role_index = {r: i for i, r in enumerate(roles)}
        names = list(parts)
        part_roles = torch.tensor(
            [[role_index[parts[p]["from"]], role_index[parts[p]["to"]]] for p in names]
        )
        radii = torch.tensor([parts[p]["radii"] for p in names], dtype=torch.float64)
        return cls(names, roles, w, part_roles, radii, mapping)

    @classmethod
    def from_skeleton(cls, skeleton: Skeleton, spec: dict | str | Path | None = None) -> BodyModel:
        """Map a skeleton's joints (and End Sites) to the body parts."""
        end_joints = [skeleton.names[j] for j in skeleton.end_sites]
        mapping = map_roles(skeleton.names, end_joints, spec)
        points = list(skeleton.names) + [n + ".end" for n in end_joints]
        return cls.from_points(points, mapping)

    @classmethod
    def from_keypoints(cls, spec: str | Path = "pose2sim_21") -> BodyModel:
        """For a keypoint set without hierarchy, from a spec listing its ``markers``."""
        path = Path(spec) if Path(spec).suffix else DATA / f"{spec}.yaml"
        raw = _read_yaml(path)
        if "markers" not in raw:
            raise BodyPartMappingError(f"{path}: a keypoint spec needs a 'markers' list")
        return cls.from_points(list(raw["markers"]), load_spec(path))

    @property
    def num_parts(self) -> int:
        return len(self.part_names)

    def landmarks(self, points: Tensor) -> Tensor:
        """Role positions from point positions. ``(..., N, 3)`` -> ``(..., R, 3)``."""
        return self.role_weights.to(points) @ points

    def segments(self, points: Tensor) -> Tensor:
        """Part end points. ``(..., N, 3)`` -> ``(..., P, 2, 3)`` (proximal, distal)."""
        return self.landmarks(points)[..., self.part_roles, :]

    def skeleton_points(self, skeleton: Skeleton, fk: FKResult) -> Tensor:
        """Joints then End Sites, the point order of :meth:`from_skeleton`. ``(..., N, 3)``."""
        return torch.cat([fk.positions, end_site_positions(skeleton, fk)], -2)
