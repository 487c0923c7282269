"""BVH motion files: a strict reader that names the file and line of every problem.

A BVH file has a HIERARCHY (joints with parents, offsets and rotation/position channels)
and a MOTION block (one row of channel values per frame). Values are returned exactly as
stored: offsets and positions in the file's own length unit (CMU cgspeed files use inches
times 0.45 -- not metres), angles in degrees, channel order as declared per joint.

Forward kinematics, unit conversion and body-part specs build on this (see the motion issue).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["BVH", "BVHError", "read_bvh", "write_bvh"]

CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")


class BVHError(ValueError):
    """A malformed BVH file; the message names the file and the line."""


@dataclass
class BVH:
    """Contents of a BVH file.

    Attributes:
        path: the file read.
        names: ``J`` joint names, parents before children.
        parents: ``(J,)`` int, parent index of each joint, -1 for the root.
        offsets: ``(J, 3)`` float64 offset of each joint from its parent (file units).
        channels: per joint, the channel names in file order (e.g. ``Zrotation``).
        end_sites: ``{joint index: (3,) offset}`` of End Site children.
        frame_time: seconds per frame.
        motion: ``(F, C)`` float64 channel values per frame (C = total channel count).
    """

    path: Path
    names: list[str]
    parents: np.ndarray
    offsets: np.ndarray
    channels: list[list[str]]
    end_sites: dict[int, np.ndarray]
    frame_time: float
    motion: np.ndarray

    @property
    def num_frames(self) -> int:
        return self.motion.shape[0]

    @property
    def frame_rate(self) -> float:
        return 1.0 / self.frame_time

    def channel_slices(self) -> list[slice]:
        """Column range of each joint's channels in :attr:`motion`."""
        out, start = [], 0
        for ch in self.channels:
            out.append(slice(start, start + len(ch)))
            start += len(ch)
        return out

    def has_reference_pose(self) -> bool:
        """True when frame 0 looks like the cgspeed converter's reference pose (a root named
        ``Hips`` and whole-degree rotations; ../shared/data/README.md): not part of the motion."""
        rot0 = self.motion[0, self.rotation_columns()]
        return (
            len(self.motion) > 1
            and self.names[0] == "Hips"
            and bool(np.array_equal(rot0, np.round(rot0)))
        )

    def motion_frames(self) -> np.ndarray:
        """``(F', C)`` the motion without a converter's reference pose in frame 0."""
        return self.motion[1:] if self.has_reference_pose() else self.motion

    def rotation_columns(self) -> np.ndarray:
        """Indices of all rotation channels (degrees) in :attr:`motion`."""
        flat = [c for ch in self.channels for c in ch]
        return np.array([i for i, c in enumerate(flat) if c.endswith("rotation")], dtype=np.int64)


def _floats(tokens: list[str], path: Path, line: int, what: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError as err:
        raise BVHError(f"{path}:{line}: {what}: not a number ({err})") from None
    if not all(math.isfinite(v) for v in values):
        raise BVHError(f"{path}:{line}: {what}: non-finite value (NaN or inf)")
    return values


def read_bvh(path: str | Path) -> BVH:
    """Read a BVH file.

    Args:
        path: the file (any line ends, any channel order, exponent notation accepted).

    Returns:
        :class:`BVH`.

    Raises:
        BVHError: naming the file and line, for unbalanced braces, unknown channel names, a
            truncated MOTION block, a row with the wrong number of values, NaN values.
        FileNotFoundError: if the file does not exist.
    """
    path = Path(path)
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []
    end_sites: dict[int, np.ndarray] = {}
    stack: list[int] = []  # open joints; -2 marks an End Site block
    pending: int | None = None  # joint declared, waiting for its "{"
    i = 0
    if not lines or lines[0].strip() != "HIERARCHY":
        raise BVHError(f"{path}:1: expected 'HIERARCHY' as the first line")
    i = 1
    while i < len(lines):
        lineno = i + 1
        tokens = lines[i].split()
        i += 1
        if not tokens:
            continue
        key = tokens[0]
        if key in ("ROOT", "JOINT"):
            if len(tokens) < 2:
                raise BVHError(f"{path}:{lineno}: {key} without a name")
            if key == "ROOT" and (stack or names):
                raise BVHError(f"{path}:{lineno}: a second ROOT (only one skeleton per file)")
            if key == "JOINT" and (not stack or stack[-1] < 0):
                raise BVHError(f"{path}:{lineno}: JOINT outside a joint block")
            names.append(" ".join(tokens[1:]))
            parents.append(stack[-1] if stack else -1)
            offsets.append([0.0, 0.0, 0.0])
            channels.append([])
            pending = len(names) - 1
        elif key == "End":
            if not stack or stack[-1] < 0:
                raise BVHError(f"{path}:{lineno}: End Site outside a joint block")
            pending = -2
        elif key == "{":
            if pending is None:
                raise BVHError(f"{path}:{lineno}: '{{' without a ROOT, JOINT or End Site")
            stack.append(pending if pending >= 0 else -(stack[-1] + 3))
            pending = None
        elif key == "}":
            if not stack:
                raise BVHError(f"{path}:{lineno}: unbalanced '}}'")
            stack.pop()
        elif key == "OFFSET":
            if not stack:
                raise BVHError(f"{path}:{lineno}: OFFSET outside a block")
            values = _floats(tokens[1:], path, lineno, "OFFSET")
            if len(values) != 3:
                raise BVHError(f"{path}:{lineno}: OFFSET needs 3 values, got {len(values)}")
            top = stack[-1]
            if top >= 0:
                offsets[top] = values
            else:
                end_sites[-top - 3] = np.array(values)
        elif key == "CHANNELS":
            if not stack or stack[-1] < 0:
                raise BVHError(f"{path}:{lineno}: CHANNELS outside a joint block")
            try:
                count = int(tokens[1])
            except (IndexError, ValueError):
                raise BVHError(f"{path}:{lineno}: CHANNELS needs a count") from None
            declared = tokens[2:]
            if len(declared) != count:
                raise BVHError(
                    f"{path}:{lineno}: CHANNELS declares {count} channels but names {len(declared)}"
                )
            for c in declared:
                if c not in CHANNEL_NAMES:
                    raise BVHError(
                        f"{path}:{lineno}: unknown channel name {c!r} (expected one of "
                        f"{', '.join(CHANNEL_NAMES)})"
                    )
            channels[stack[-1]] = declared
        elif key == "MOTION":
            if stack:
                raise BVHError(f"{path}:{lineno}: MOTION before all joint blocks are closed")
            break
        else:
            raise BVHError(f"{path}:{lineno}: unexpected {key!r} in HIERARCHY")
    else:
        raise BVHError(f"{path}: no MOTION block (file truncated?)")
    if not names:
        raise BVHError(f"{path}: no ROOT joint in HIERARCHY")

    def header(prefix: str) -> str:
        nonlocal i
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines) or not lines[i].strip().startswith(prefix):
            raise BVHError(f"{path}:{i + 1}: expected '{prefix}' after MOTION")
        value = lines[i].strip()[len(prefix) :].strip()
        i += 1
        return value

    try:
        num_frames = int(header("Frames:"))
        frame_time = float(header("Frame Time:"))
    except ValueError as err:
        raise BVHError(f"{path}:{i}: bad MOTION header ({err})") from None
    if num_frames < 1 or not (frame_time > 0 and math.isfinite(frame_time)):
        raise BVHError(f"{path}:{i}: need Frames >= 1 and Frame Time > 0")
    num_channels = sum(len(c) for c in channels)
    rows = []
    for j in range(i, len(lines)):
        tokens = lines[j].split()
        if not tokens:
            continue
        if len(tokens) != num_channels:
            raise BVHError(
                f"{path}:{j + 1}: frame {len(rows)} has {len(tokens)} values; the hierarchy "
                f"declares {num_channels} channels"
            )
        rows.append(_floats(tokens, path, j + 1, f"frame {len(rows)}"))
    if len(rows) != num_frames:
        raise BVHError(
            f"{path}:{len(lines)}: MOTION declares {num_frames} frames but {len(rows)} rows "
            "follow (truncated file?)"
        )
    return BVH(
        path=path,
        names=names,
        parents=np.array(parents, dtype=np.int64),
        offsets=np.array(offsets, dtype=np.float64),
        channels=channels,
        end_sites=end_sites,
        frame_time=frame_time,
        motion=np.array(rows, dtype=np.float64).reshape(num_frames, num_channels),
    )


def write_bvh(bvh: BVH, path: str | Path) -> Path:
    """Write a :class:`BVH` so that :func:`read_bvh` gives back the same numbers exactly.

    Values are written with Python's shortest round-trip float repr; line ends are ``\\n``.
    Returns the path written.
    """
    path = Path(path)
    children: dict[int, list[int]] = {j: [] for j in range(len(bvh.names))}
    for j, p in enumerate(bvh.parents.tolist()):
        if p >= 0:
            children[p].append(j)
    out = ["HIERARCHY"]

    def fmt(values) -> str:
        return " ".join(repr(float(v)) for v in values)

    def joint(j: int, depth: int) -> None:
        pad = "\t" * depth
        out.append(f"{pad}{'ROOT' if j == 0 else 'JOINT'} {bvh.names[j]}")
        out.append(f"{pad}{{")
        out.append(f"{pad}\tOFFSET {fmt(bvh.offsets[j])}")
        if bvh.channels[j]:
            out.append(f"{pad}\tCHANNELS {len(bvh.channels[j])} {' '.join(bvh.channels[j])}")
        for c in children[j]:
            joint(c, depth + 1)
        if j in bvh.end_sites:
            out.append(f"{pad}\tEnd Site")
            out.append(f"{pad}\t{{")
            out.append(f"{pad}\t\tOFFSET {fmt(bvh.end_sites[j])}")
            out.append(f"{pad}\t}}")
        out.append(f"{pad}}}")

    joint(0, 0)
    out.append("MOTION")
    out.append(f"Frames: {bvh.num_frames}")
    out.append(f"Frame Time: {bvh.frame_time!r}")
    out.extend(fmt(row) for row in bvh.motion)
    path.write_text("\n".join(out) + "\n", encoding="utf-8")
    return path
