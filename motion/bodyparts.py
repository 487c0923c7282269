"""Body parts: which landmarks bound each of the 15 capsules, mapped from any skeleton.

The body model is data (``motion/data/bodyparts/parts.yaml``): 15 tapered capsules, each
between two semantic landmarks (roles such as ``knee_l``) with two radii in metres. A
skeleton's joints are mapped to the roles automatically for the common BVH naming
conventions (``roles.yaml`` lists them and where each was seen), or by a spec file with the
same keys; what cannot be mapped is reported part by part. Another articulated object is
another parts file (``parts=``): its own parts, roles and parent tree -- or one spec file
holding ``parts`` and ``roles`` together (``motion/data/examples/robot_arm.yaml``).

A role is the mean of one or more *points*: joint positions, End Site positions written
``NAME.end``, or -- where a skeleton has no joint or End Site for a hand's or a foot's far
end -- a synthesized end ``NAME.tip``: a fixed offset from joint ``NAME`` (the wrist or the
ankle) that moves with it like an End Site, announced by a :class:`SynthesizedEndWarning`.
Shapes: ``J`` joints, ``E`` end sites, ``S`` synthesized ends, ``R`` roles, ``P`` parts.
Geometry: metres, the BVH rest pose (all rotations zero) for the synthesized offsets.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
import yaml
from torch import Tensor

from motion.kinematics import FKResult, Skeleton, end_site_positions, offset_points

__all__ = [
    "DEFAULT_PARTS",
    "FOOT_END_M",
    "HAND_END_M",
    "BodyModel",
    "BodyPartMappingError",
    "SynthesizedEndWarning",
    "canonical_name",
    "end_site_positions",  # from motion.kinematics: (..., E, 3) in end_sites order
    "joint_of_point",
    "load_spec",
    "map_roles",
    "parts_file",
    "read_parts",
]

DATA = Path(__file__).resolve().parent / "data" / "bodyparts"
#: the human body model: 15 capsules (every default of this module)
DEFAULT_PARTS = DATA / "parts.yaml"

TIP = ".tip"  # suffix of a synthesized end point
# Synthesized ends, measured on the shared CMU files (rest pose, metres): wrist to the middle
# finger's base is 0.09 m in the Daz-style files (rHand -> rMid1); ankle to the toe is about
# 0.12 m forward and 0.03 m down (cgspeed LeftFoot -> LeftToeBase, Daz lFoot's End Site).
HAND_END_M = 0.09
FOOT_END_M = (0.12, 0.03)  # (forward, down)
# end role -> (role whose joint it extends, what it is)
_FALLBACK_ENDS = {
    "hand_end_l": ("wrist_l", "hand"),
    "hand_end_r": ("wrist_r", "hand"),
    "toe_l": ("ankle_l", "foot"),
    "toe_r": ("ankle_r", "foot"),
}


class BodyPartMappingError(ValueError):
    """Some body parts could not be mapped to the skeleton's joints."""


class SynthesizedEndWarning(UserWarning):
    """A hand or foot end was not among the joints; a default-length end was synthesized."""


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
    path = _spec_path(name_or_path)
    spec = _read_yaml(path)
    if "roles" not in spec or not isinstance(spec["roles"], dict):
        raise BodyPartMappingError(f"{path}: expected a 'roles' mapping of role -> joint name(s)")
    return {r: [v] if isinstance(v, str) else list(v) for r, v in spec["roles"].items()}


def _spec_path(name_or_path: str | Path) -> Path:
    path = Path(name_or_path)
    return path if path.suffix else DATA / f"{name_or_path}.yaml"


def parts_file(parts: str | Path | None = None, spec=None) -> Path:
    """The parts file to use: ``parts`` if given, else the roles spec file itself when it
    lists ``parts`` (an object described by one file), else :data:`DEFAULT_PARTS`."""
    if parts is not None:
        return Path(parts)
    if isinstance(spec, str | Path) and "parts" in _read_yaml(_spec_path(spec)):
        return _spec_path(spec)
    return DEFAULT_PARTS


def read_parts(path: str | Path | None = None) -> dict[str, dict]:
    """``{part: {from, to, radii, parent}}`` of a parts file (default :data:`DEFAULT_PARTS`).

    Raises:
        BodyPartMappingError: naming the file, when it has no ``parts`` mapping or a part
            lacks ``from``, ``to`` or two positive ``radii``.
    """
    path = Path(path or DEFAULT_PARTS)
    parts = _read_yaml(path).get("parts")
    if not isinstance(parts, dict) or not parts:
        raise BodyPartMappingError(f"{path}: expected a 'parts' mapping of part -> entry")
    for name, d in parts.items():
        ok = isinstance(d, dict) and isinstance(d.get("from"), str) and isinstance(d.get("to"), str)
        radii = d.get("radii") if isinstance(d, dict) else None
        if not ok or not (
            isinstance(radii, list)
            and len(radii) == 2
            and all(isinstance(r, int | float) and r > 0 for r in radii)
        ):
            raise BodyPartMappingError(
                f"{path}: part {name!r} needs 'from' and 'to' roles and two radii > 0 in "
                f"metres; got {d!r}"
            )
    return parts


# Rig prefixes that carry no meaning: 3ds Max Biped ("Bip01 ", "Bip001 "), Valve's
# "ValveBiped.", Mixamo without its colon ("mixamorig", "mixamorig1_"), Character Creator.
_PREFIX = re.compile(r"^(valvebiped\.)?(bip0*1|mixamorig\d*|ccbase)")


def canonical_name(name: str) -> str:
    """The key joint names are compared by: namespace (``a:``) and rig prefixes dropped,
    lower case, spaces, underscores and hyphens removed (``"Bip01 L Thigh"`` -> ``"lthigh"``,
    ``"UpperArm_L"`` -> ``"upperarml"``). A trailing ``.end`` is kept."""
    base, end = (name[:-4], ".end") if name.lower().endswith(".end") else (name, "")
    key = re.sub(r"[\s_\-]+", "", base.split(":")[-1].lower())
    return (_PREFIX.sub("", key) or key) + end


def joint_of_point(point: str) -> tuple[str, bool]:
    """The joint a point moves with, and whether the point is offset from it (an End Site
    ``NAME.end`` or a synthesized end ``NAME.tip``) rather than the joint itself."""
    for suffix in (".end", TIP):
        if point.endswith(suffix):
            return point[: -len(suffix)], True
    return point, False


def _point_index(joint_names: list[str], end_site_joints: list[str]) -> dict[str, str]:
    """canonical key -> point name (joints, then ``NAME.end``); the first of a clash wins."""
    canon: dict[str, str] = {}
    for n in joint_names:
        canon.setdefault(canonical_name(n), n)
    for n in end_site_joints:
        canon.setdefault(canonical_name(n) + ".end", n + ".end")
    return canon


def _fallback_end(role: str, mapping: dict, end_site_joints: list[str]) -> list[str] | None:
    """For a missing hand or foot end: the End Site below the wrist/ankle joint, else a
    synthesized ``NAME.tip`` (with a warning); None when the wrist/ankle is not one joint."""
    proximal, kind = _FALLBACK_ENDS[role]
    base = mapping.get(proximal)
    if base is None or len(base) != 1 or joint_of_point(base[0])[1]:
        return None
    joint = base[0]
    if joint in end_site_joints:
        return [joint + ".end"]
    if kind == "hand":
        how = f"{HAND_END_M} m beyond {joint!r} along the forearm"
    else:
        how = f"{FOOT_END_M[0]} m ahead of and {FOOT_END_M[1]} m below {joint!r}"
    warnings.warn(
        f"{role}: no joint or End Site for the {kind}'s end; using a synthesized point {how} "
        f"(name one in a spec to choose it)",
        SynthesizedEndWarning,
        stacklevel=4,
    )
    return [joint + TIP]


def map_roles(
    joint_names: list[str],
    end_site_joints: list[str],
    spec: dict | str | Path | None = None,
    parts: str | Path | None = None,
) -> dict[str, list[str]]:
    """Map every role the parts need to point names of this skeleton.

    Roles are resolved part by part, proximal end first; an automatic candidate for a part's
    distal end is skipped when it is the same point as the proximal end (SMPL's ``L_Hand`` is
    a hand end, Daz's ``lHand`` a wrist). A hand or foot end that no candidate matches falls
    back to the End Site of the wrist/ankle joint, then to a synthesized ``NAME.tip`` with a
    :class:`SynthesizedEndWarning` (see :data:`HAND_END_M`, :data:`FOOT_END_M`).

    Args:
        joint_names: the skeleton's joints (compared by :func:`canonical_name`).
        end_site_joints: joints that have an End Site (their ``.end`` points exist).
        spec: explicit mapping (dict or spec file) used before the automatic table.
        parts: the parts file whose roles are mapped (default: :func:`parts_file` -- the
            spec file's own ``parts`` if it has them, else the human body model).

    Returns:
        role -> list of point names as they appear in the skeleton (``NAME``, ``NAME.end`` or
        ``NAME.tip``).

    Raises:
        BodyPartMappingError: naming each part that cannot be mapped and its missing roles.
    """
    explicit = load_spec(spec) if isinstance(spec, str | Path) else (spec or {})
    table = _read_yaml(DATA / "roles.yaml")["roles"]
    canon = _point_index(joint_names, end_site_joints)

    def resolve(candidate) -> list[str] | None:
        items = [candidate] if isinstance(candidate, str) else list(candidate)
        found = [canon.get(canonical_name(str(i))) for i in items]
        return None if any(f is None for f in found) else found

    def assign(role: str, avoid: list[str] | None) -> None:
        if role in mapping:
            return
        if role in explicit:
            got = resolve(explicit[role])
            if got is None:
                raise BodyPartMappingError(
                    f"spec maps role {role!r} to {explicit[role]!r}, not found among the joints"
                )
            mapping[role] = got
            return
        for cand in table.get(role, []):
            got = resolve(cand)
            if got is not None and got != avoid:
                mapping[role] = got
                return
        if role in _FALLBACK_ENDS:
            got = _fallback_end(role, mapping, end_site_joints)
            if got is not None:
                mapping[role] = got

    parts = read_parts(parts_file(parts, spec))
    mapping: dict[str, list[str]] = {}
    for d in parts.values():
        assign(d["from"], None)
        assign(d["to"], mapping.get(d["from"]))
    missing = {
        part: [r for r in (d["from"], d["to"]) if r not in mapping]
        for part, d in parts.items()
        if d["from"] not in mapping or d["to"] not in mapping
    }
    if missing:
        lines = "; ".join(f"{p} (no {', '.join(r)})" for p, r in missing.items())
        raise BodyPartMappingError(
            f"could not map {len(missing)} body parts: {lines}. Joints: {joint_names}. Pass a "
            "spec file mapping these roles to joint names (see motion/data/bodyparts/)."
        )
    return dict(sorted(mapping.items()))


def _rest_points(skeleton: Skeleton) -> dict[str, Tensor]:
    """Rest-pose positions (all rotations zero) of joints and End Sites, by point name."""
    pos: list[Tensor] = []
    for j, p in enumerate(skeleton.parents.tolist()):
        pos.append(skeleton.offsets[j] + (pos[p] if p >= 0 else 0))
    out = {n: pos[j] for j, n in enumerate(skeleton.names)}
    for j, o in skeleton.end_sites.items():
        out[skeleton.names[j] + ".end"] = pos[j] + o
    return out


def _unit(v: Tensor, what: str) -> Tensor:
    n = v.norm()
    if not n > 1e-9:
        raise BodyPartMappingError(f"cannot synthesize {what}: zero length at rest")
    return v / n


def _synthesized_offsets(skeleton: Skeleton, mapping: dict[str, list[str]]) -> dict[int, Tensor]:
    """``{joint: (3,) offset in metres in the joint's frame}`` for every ``NAME.tip`` role.

    At rest every BVH rotation is zero, so a joint's frame is the world's: a hand end lies
    :data:`HAND_END_M` beyond the wrist along elbow -> wrist; a foot end :data:`FOOT_END_M`
    ahead (``left x up``, left = hip_l - hip_r, up = ankle -> knee) and below the ankle.
    """
    rest = _rest_points(skeleton)

    def role(r: str) -> Tensor:
        return torch.stack([rest[n] for n in mapping[r]]).mean(0)

    out: dict[int, Tensor] = {}
    for end, (proximal, kind) in _FALLBACK_ENDS.items():
        if end not in mapping:  # a parts file without this role (another object)
            continue
        tip = mapping[end][0]
        if not tip.endswith(TIP):
            continue
        side = end[-1]
        if kind == "hand":
            along = _unit(role(proximal) - role(f"elbow_{side}"), f"{end} (the forearm)")
            offset = HAND_END_M * along
        else:
            up = _unit(role(f"knee_{side}") - role(proximal), f"{end} (the shin)")
            left = role("hip_l") - role("hip_r")
            forward = _unit(torch.linalg.cross(left, up), f"{end} (hips across the shin)")
            offset = FOOT_END_M[0] * forward - FOOT_END_M[1] * up
        out[skeleton.index(joint_of_point(tip)[0])] = offset
    return out


@dataclass
class BodyModel:
    """Capsule parts over a point set (joints, end sites, synthesized ends; or keypoints).

    Attributes:
        part_names: P names. roles: R role names.
        role_weights: ``(R, N)`` each role as a mean over the N points.
        part_roles: ``(P, 2)`` long, the roles at each part's ends.
        radii: ``(P, 2)`` metres, proximal and distal radius (the body-size adjustment G
            scales these and the skeleton's offsets).
        mapping: role -> point names used.
        synthesized: ``{joint: (3,) offset in metres}`` of the synthesized ``NAME.tip``
            points, in point order after the End Sites (empty for most skeletons).
        parts_path: the parts file the model was built from (:data:`DEFAULT_PARTS`: the
            human body); :class:`motion.body.BodySpec` reads the part tree from it.
    """

    part_names: list[str]
    roles: list[str]
    role_weights: Tensor
    part_roles: Tensor
    radii: Tensor
    mapping: dict[str, list[str]]
    synthesized: dict[int, Tensor] = field(default_factory=dict)
    parts_path: Path = DEFAULT_PARTS

    @classmethod
    def from_points(
        cls,
        point_names: list[str],
        mapping: dict[str, list[str]],
        parts: str | Path | None = None,
    ) -> BodyModel:
        """The parts of ``parts`` (default :data:`DEFAULT_PARTS`) over named points, each
        role the mean of the points ``mapping`` gives it."""
        path = Path(parts or DEFAULT_PARTS)
        parts = read_parts(path)
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
        missing = sorted(
            {r for p in names for r in (parts[p]["from"], parts[p]["to"])} - set(roles)
        )
        if missing:
            raise BodyPartMappingError(f"{path}: no points for the roles {missing}")
        radii = torch.tensor([parts[p]["radii"] for p in names], dtype=torch.float64)
        return cls(names, roles, w, part_roles, radii, mapping, parts_path=path)

    @classmethod
    def from_skeleton(
        cls,
        skeleton: Skeleton,
        spec: dict | str | Path | None = None,
        parts: str | Path | None = None,
    ) -> BodyModel:
        """Map a skeleton's joints (and End Sites) to the parts of ``parts``
        (:func:`parts_file`: by default the spec file's own ``parts`` if it lists them, else
        the human body model); a missing hand or foot end is synthesized
        (:func:`map_roles`, :class:`SynthesizedEndWarning`)."""
        parts = parts_file(parts, spec)
        end_joints = [skeleton.names[j] for j in skeleton.end_sites]
        mapping = map_roles(skeleton.names, end_joints, spec, parts)
        synthesized = _synthesized_offsets(skeleton, mapping)
        points = (
            list(skeleton.names)
            + [n + ".end" for n in end_joints]
            + [skeleton.names[j] + TIP for j in synthesized]
        )
        model = cls.from_points(points, mapping, parts)
        model.synthesized = synthesized
        return model

    @classmethod
    def from_keypoints(
        cls, spec: str | Path = "pose2sim_21", parts: str | Path | None = None
    ) -> BodyModel:
        """For a keypoint set without hierarchy, from a spec listing its ``markers``."""
        path = _spec_path(spec)
        raw = _read_yaml(path)
        if "markers" not in raw:
            raise BodyPartMappingError(f"{path}: a keypoint spec needs a 'markers' list")
        return cls.from_points(list(raw["markers"]), load_spec(path), parts_file(parts, path))

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
        """Joints, End Sites, then synthesized ends: the point order of :meth:`from_skeleton`.
        ``(..., J + E + S, 3)`` metres."""
        return torch.cat(
            [
                fk.positions,
                end_site_positions(skeleton, fk),
                offset_points(fk, self.synthesized),
            ],
            -2,
        )
