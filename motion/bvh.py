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

__all__ = ["BVH", "FRAME_TIME_RANGE", "BVHError", "read_bvh", "write_bvh"]

CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")


class BVHError(ValueError):
    """A malformed BVH file; the message names the file and the line."""


# Seconds per frame accepted in ``Frame Time:``: from 100 kHz (1e-5 s) to one frame a minute
# (60 s). Motion capture runs at 24-1000 Hz and pose files use 1 s or so; anything outside
# this range is a corrupt header (``1e308`` would give a frame rate of 1e-308 Hz).
FRAME_TIME_RANGE = (1e-5, 60.0)

_END = -2  # ``pending`` marker: an End Site declared, waiting for its "{"


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


def _read_lines(path: Path) -> list[str]:
    """The file's lines; a UTF-8 byte-order mark is dropped, UTF-16 is refused."""
    raw = path.read_bytes()
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise BVHError(f"{path}:1: UTF-16 text is not supported; save the file as UTF-8 or ASCII")
    return raw.decode("utf-8-sig", errors="replace").splitlines()


class _Hierarchy:
    """Line-by-line parser of the HIERARCHY block; :meth:`feed` returns True at ``MOTION``.

    ``stack`` holds the open blocks: a joint index, or ``-(parent + 3)`` for an End Site.
    Every problem raises :class:`BVHError` naming the file and the line.
    """

    def __init__(self, path: Path):
        self.path = path
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[list[float] | None] = []
        self.channels: list[list[str] | None] = []
        self.end_sites: dict[int, np.ndarray] = {}
        self.declared_at: list[int] = []  # line of each joint's ROOT/JOINT keyword
        self.stack: list[int] = []
        self.pending: tuple[int, int] | None = None  # (joint index or _END, line) before "{"
        self.end_open: dict[int, int] = {}  # End Site blocks open: parent -> line

    def error(self, lineno: int, message: str) -> BVHError:
        return BVHError(f"{self.path}:{lineno}: {message}")

    def in_joint(self) -> bool:
        return bool(self.stack) and self.stack[-1] >= 0

    def feed(self, tokens: list[str], lineno: int) -> bool:
        key = tokens[0]
        if self.pending is not None and key != "{":
            what, line = self.pending
            kind = "End Site" if what == _END else f"joint {self.names[what]!r}"
            raise self.error(lineno, f"expected '{{' after the {kind} of line {line}; got {key!r}")
        if key in ("{", "}") and len(tokens) > 1:
            raise self.error(
                lineno, f"unexpected {tokens[1]!r} after {key!r} (one keyword per line)"
            )
        handler = {
            "ROOT": self.joint,
            "JOINT": self.joint,
            "End": self.end_site,
            "{": self.open,
            "}": self.close,
            "OFFSET": self.offset,
            "CHANNELS": self.channel_list,
        }.get(key)
        if key == "MOTION":
            if self.stack:
                raise self.error(lineno, "MOTION before all joint blocks are closed")
            return True
        if handler is None:
            raise self.error(lineno, f"unexpected {key!r} in HIERARCHY")
        handler(tokens, lineno)
        return False

    def joint(self, tokens: list[str], lineno: int) -> None:
        key = tokens[0]
        if len(tokens) < 2:
            raise self.error(lineno, f"{key} without a name")
        if key == "ROOT" and (self.stack or self.names):
            raise self.error(lineno, "a second ROOT (only one skeleton per file)")
        if key == "JOINT" and not self.in_joint():
            raise self.error(lineno, "JOINT outside a joint block")
        name = " ".join(tokens[1:])
        if name in self.names:
            first = self.declared_at[self.names.index(name)]
            raise self.error(
                lineno,
                f"joint name {name!r} is already used at line {first}; joint names must be unique",
            )
        self.names.append(name)
        self.parents.append(self.stack[-1] if self.stack else -1)
        self.offsets.append(None)
        self.channels.append(None)
        self.declared_at.append(lineno)
        self.pending = (len(self.names) - 1, lineno)

    def end_site(self, tokens: list[str], lineno: int) -> None:
        if tokens[1:] != ["Site"]:
            raise self.error(lineno, f"expected 'End Site'; got {' '.join(tokens)!r}")
        if not self.in_joint():
            raise self.error(lineno, "End Site outside a joint block")
        if self.stack[-1] in self.end_sites:
            raise self.error(lineno, f"joint {self.names[self.stack[-1]]!r} has a second End Site")
        self.pending = (_END, lineno)

    def open(self, tokens: list[str], lineno: int) -> None:
        if self.pending is None:
            raise self.error(lineno, "'{' without a ROOT, JOINT or End Site")
        what, line = self.pending
        if what == _END:
            self.end_open[self.stack[-1]] = line
            self.stack.append(-(self.stack[-1] + 3))
        else:
            self.stack.append(what)
        self.pending = None

    def close(self, tokens: list[str], lineno: int) -> None:
        if not self.stack:
            raise self.error(lineno, "unbalanced '}'")
        top = self.stack.pop()
        if top >= 0 and self.offsets[top] is None:
            raise self.error(
                lineno, f"joint {self.names[top]!r} (line {self.declared_at[top]}) has no OFFSET"
            )
        if top < 0:
            parent = -top - 3
            line = self.end_open.pop(parent)
            if parent not in self.end_sites:
                raise self.error(
                    lineno, f"the End Site of line {line} ({self.names[parent]!r}) has no OFFSET"
                )

    def offset(self, tokens: list[str], lineno: int) -> None:
        if not self.stack:
            raise self.error(lineno, "OFFSET outside a block")
        values = _floats(tokens[1:], self.path, lineno, "OFFSET")
        if len(values) != 3:
            raise self.error(lineno, f"OFFSET needs 3 values, got {len(values)}")
        top = self.stack[-1]
        done = self.offsets[top] is not None if top >= 0 else (-top - 3) in self.end_sites
        if done:
            raise self.error(lineno, "a second OFFSET in the same block")
        if top >= 0:
            self.offsets[top] = values
        else:
            self.end_sites[-top - 3] = np.array(values)

    def channel_list(self, tokens: list[str], lineno: int) -> None:
        if not self.in_joint():
            raise self.error(lineno, "CHANNELS outside a joint block")
        try:
            count = int(tokens[1])
        except (IndexError, ValueError):
            raise self.error(lineno, "CHANNELS needs a count") from None
        declared = tokens[2:]
        if len(declared) != count:
            raise self.error(
                lineno, f"CHANNELS declares {count} channels but names {len(declared)}"
            )
        for c in declared:
            if c not in CHANNEL_NAMES:
                raise self.error(
                    lineno,
                    f"unknown channel name {c!r} (expected one of {', '.join(CHANNEL_NAMES)})",
                )
        if len(set(declared)) != len(declared):
            raise self.error(lineno, f"CHANNELS names a channel twice: {' '.join(declared)}")
        if self.channels[self.stack[-1]] is not None:
            raise self.error(lineno, "a second CHANNELS line in the same joint block")
        self.channels[self.stack[-1]] = declared


def _parse_hierarchy(path: Path, lines: list[str]) -> tuple[_Hierarchy, int]:
    """Parse up to ``MOTION``; returns the parser and the index of the line after it."""
    i = 0
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i == len(lines):
        raise BVHError(f"{path}:1: empty file; expected 'HIERARCHY'")
    if lines[i].strip() != "HIERARCHY":
        raise BVHError(
            f"{path}:{i + 1}: expected 'HIERARCHY' as the first line; got {lines[i].strip()[:40]!r}"
        )
    parser = _Hierarchy(path)
    for j in range(i + 1, len(lines)):
        tokens = lines[j].split()
        if tokens and parser.feed(tokens, j + 1):
            if not parser.names:
                raise BVHError(f"{path}:{j + 1}: MOTION before any ROOT joint")
            return parser, j + 1
    if parser.stack or parser.pending is not None:
        raise BVHError(
            f"{path}:{len(lines)}: no MOTION block: the file ends inside the HIERARCHY (truncated?)"
        )
    raise BVHError(f"{path}: no MOTION block (file truncated?)")


def _motion_header(path: Path, lines: list[str], i: int) -> tuple[int, float, int]:
    """``Frames:`` and ``Frame Time:`` from line index ``i``; returns them and the next index."""

    def header(prefix: str) -> tuple[str, int]:
        nonlocal i
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines) or not lines[i].strip().startswith(prefix):
            raise BVHError(f"{path}:{i + 1}: expected '{prefix}' after MOTION")
        i += 1
        return lines[i - 1].strip()[len(prefix) :].strip(), i

    text, line = header("Frames:")
    try:
        num_frames = int(text)
    except ValueError:
        num_frames = 0
    if num_frames < 1:
        raise BVHError(f"{path}:{line}: 'Frames:' needs a whole number >= 1; got {text!r}")
    text, line = header("Frame Time:")
    try:
        frame_time = float(text)
    except ValueError:
        frame_time = math.nan
    low, high = FRAME_TIME_RANGE
    if not low <= frame_time <= high:
        raise BVHError(
            f"{path}:{line}: 'Frame Time:' needs seconds per frame between {low:g} and "
            f"{high:g}; got {text!r}"
        )
    return num_frames, frame_time, i


def _motion_rows(path: Path, lines: list[str], i: int, num_channels: int) -> list[list[float]]:
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
    return rows


def read_bvh(path: str | Path) -> BVH:
    """Read a BVH file.

    Args:
        path: the file (any line ends, any channel order, exponent notation accepted; a UTF-8
            byte-order mark and blank lines before ``HIERARCHY`` are accepted).

    Returns:
        :class:`BVH`.

    Raises:
        BVHError: naming the file and line, for unbalanced braces, a keyword where ``{`` was
            expected, unknown or repeated channel names, a joint or End Site without OFFSET,
            repeated joint names, a truncated MOTION block, a row with the wrong number of
            values, NaN values, ``Frames`` < 1, a ``Frame Time`` outside
            :data:`FRAME_TIME_RANGE` seconds, UTF-16 text.
        FileNotFoundError: if the file does not exist.
    """
    path = Path(path)
    lines = _read_lines(path)
    hierarchy, i = _parse_hierarchy(path, lines)
    num_frames, frame_time, i = _motion_header(path, lines, i)
    channels = [c or [] for c in hierarchy.channels]
    num_channels = sum(len(c) for c in channels)
    rows = _motion_rows(path, lines, i, num_channels)
    if len(rows) != num_frames:
        raise BVHError(
            f"{path}:{len(lines)}: MOTION declares {num_frames} frames but {len(rows)} rows "
            "follow (truncated file?)"
        )
    return BVH(
        path=path,
        names=hierarchy.names,
        parents=np.array(hierarchy.parents, dtype=np.int64),
        offsets=np.array(hierarchy.offsets, dtype=np.float64).reshape(-1, 3),
        channels=channels,
        end_sites=hierarchy.end_sites,
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
