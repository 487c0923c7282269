"""Cameras: pinhole (with OpenCV's distortion model) and orthographic, rigs, DLT, calibration files.

Conventions (stated once): world points are metres; a camera maps world to camera frame by
``X_c = R X_w + t`` (OpenCV: x right, y down, z forward); pixels ``(u, v)`` with ``u`` to the
right and ``v`` down, origin at the top-left pixel's centre as OpenCV. Distortion is OpenCV's
``(k1, k2, p1, p2, k3)``. Shapes: ``C`` cameras, any leading batch ``(...)``, ``N`` points.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import Tensor

from motion.geometry import matrix_to_rotation_vector

__all__ = [
    "CameraFileError",
    "CameraRig",
    "decompose_projection",
    "dlt",
    "load_pose2sim_calibration",
    "resized_rig",
    "save_pose2sim_calibration",
]


class CameraFileError(ValueError):
    """A calibration file that cannot be used; the message names the file and the key."""


@dataclass
class CameraRig:
    """``C`` static cameras.

    Attributes:
        K: ``(C, 3, 3)`` intrinsics (pixels). For orthographic cameras ``K[0, 0]``/``K[1, 1]``
            are pixels per metre.
        R: ``(C, 3, 3)`` world-to-camera rotation. t: ``(C, 3)`` metres.
        dist: ``(C, 5)`` OpenCV distortion ``k1, k2, p1, p2, k3`` (zeros: none).
        size: ``(C, 2)`` image width and height in pixels.
        names: camera names. orthographic: project without the division by depth.
    """

    K: Tensor
    R: Tensor
    t: Tensor
    dist: Tensor
    size: Tensor
    names: list[str]
    orthographic: bool = False

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    def to(self, device: torch.device | str) -> CameraRig:
        """The same rig with its tensors on ``device``."""
        moved = {n: getattr(self, n).to(device) for n in ("K", "R", "t", "dist", "size")}
        return dataclasses.replace(self, **moved)

    def to_camera(self, points: Tensor) -> Tensor:
        """World to camera frames. ``(..., N, 3)`` -> ``(..., C, N, 3)``."""
        r = self.R.to(points)
        t = self.t.to(points)
        return torch.einsum("cij,...nj->...cni", r, points) + t[:, None, :]

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Pixels and depths of world points in every camera.

        Returns:
            uv ``(..., C, N, 2)`` pixels and depth ``(..., C, N)`` metres (``z`` in the camera
            frame; points with depth <= 0 are behind the camera and their ``uv`` is meaningless).
        """
        pc = self.to_camera(points)
        z = pc[..., 2]
        if self.orthographic:
            xy = pc[..., :2]
        else:
            xy = pc[..., :2] / z.unsqueeze(-1)
            xy = self._distort(xy)
        k = self.K.to(points)
        u = k[:, None, 0, 0] * xy[..., 0] + k[:, None, 0, 1] * xy[..., 1] + k[:, None, 0, 2]
        v = k[:, None, 1, 1] * xy[..., 1] + k[:, None, 1, 2]
        return torch.stack([u, v], -1), z

    def _distort(self, xy: Tensor) -> Tensor:
        d = self.dist.to(xy)[:, None, :]  # (C, 1, 5)
        k1, k2, p1, p2, k3 = d.unbind(-1)
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return torch.stack([xd, yd], -1)

    def centres(self) -> Tensor:
        """Camera centres in the world, ``(C, 3)`` metres: ``-R^T t``."""
        return -(self.R.transpose(-1, -2) @ self.t.unsqueeze(-1)).squeeze(-1)

    @classmethod
    def from_projection(cls, P: Tensor, size: Tensor, names: list[str]) -> CameraRig:
        """Distortion-free cameras from ``(C, 3, 4)`` projection matrices."""
        k, r, t = decompose_projection(P)
        return cls(k, r, t, torch.zeros(P.shape[0], 5, dtype=P.dtype), size, names)


def resized_rig(
    rig: CameraRig,
    native: list[tuple[int, int]],
    scaled: list[tuple[int, int]],
    size: tuple[int, int] | None = None,
) -> CameraRig:
    """The rig seeing the same scene in resized images: camera ``c``'s frames go from
    ``native[c]`` to ``scaled[c]`` pixels (width, height). Per axis, the exact resize factor
    ``s``: ``K`` row 0 times ``s_x`` then ``c_x -> (c_x + 0.5) s_x - 0.5`` (pixel centres,
    as ``cv2.resize`` samples them), row 1 likewise. The image size becomes ``size`` for
    every camera (a padded working size), or each camera's ``scaled`` size; R, t and the
    distortion are unchanged."""
    k = rig.K.clone().to(torch.float64)
    for c, ((w0, h0), (w1, h1)) in enumerate(zip(native, scaled, strict=True)):
        sx, sy = w1 / w0, h1 / h0
        k[c, 0] *= sx
        k[c, 1] *= sy
        k[c, 0, 2] += 0.5 * sx - 0.5
        k[c, 1, 2] += 0.5 * sy - 0.5
        k[c, 2] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    dtype = rig.K.dtype
    sizes = [list(size)] * rig.num_cameras if size is not None else [list(s) for s in scaled]
    return dataclasses.replace(rig, K=k.to(dtype), size=torch.tensor(sizes, dtype=dtype))


def _describe(value) -> str:
    """A short account of a TOML value for an error message (type, shape or raggedness)."""
    if isinstance(value, str):
        return f"the string {value[:40]!r}"
    if isinstance(value, bool):
        return f"the boolean {str(value).lower()}"
    if isinstance(value, int | float):
        return f"the number {value!r}"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        nested = [isinstance(v, list) for v in value]
        if any(nested) and not all(nested):
            return "a list mixing numbers and lists"
        if all(nested) and len({len(v) for v in value}) > 1:
            return f"a ragged list (rows of {', '.join(str(len(v)) for v in value)} values)"
        bad = [v for v in _flatten(value) if isinstance(v, bool) or not isinstance(v, int | float)]
        if bad:
            return f"a list holding {_describe(bad[0])}"
        return f"shape {_shape(value)}"
    return type(value).__name__


def _flatten(value) -> list:
    if isinstance(value, list):
        return [x for v in value for x in _flatten(v)]
    return [value]


def _shape(value) -> tuple[int, ...]:
    """Shape of a nested list that is known to be regular."""
    shape = []
    while isinstance(value, list):
        shape.append(len(value))
        value = value[0] if value else None
    return tuple(shape)


def _is_numeric_array(value, shape: tuple[int, ...]) -> bool:
    """A nested list of real numbers (not booleans) with exactly this shape."""
    if not shape:
        return isinstance(value, int | float) and not isinstance(value, bool)
    return (
        isinstance(value, list)
        and len(value) == shape[0]
        and all(_is_numeric_array(v, shape[1:]) for v in value)
    )


def _as_floats(value):
    """Nested numbers as floats; an integer too large for a float becomes inf (then refused)."""
    if isinstance(value, list):
        return [_as_floats(v) for v in value]
    try:
        return float(value)
    except OverflowError:
        return math.inf


def _camera_array(path: Path, key: str, cam: dict, name: str, shapes) -> Tensor:
    """``cam[name]`` as a float64 tensor of one of ``shapes``, finite; else a one-line error."""
    where = f"{path}: camera [{key}] '{name}'"
    if name not in cam:
        raise CameraFileError(f"{path}: camera [{key}] has no '{name}'")
    value = cam[name]
    shape = next((s for s in shapes if _is_numeric_array(value, s)), None)
    if shape is None:
        wanted = " or ".join(f"shape {s}" for s in shapes)
        raise CameraFileError(f"{where} must be numbers of {wanted}; got {_describe(value)}")
    tensor = torch.tensor(_as_floats(value), dtype=torch.float64)
    if not torch.isfinite(tensor).all():
        raise CameraFileError(f"{where} must be finite; got {value}")
    return tensor


def _check_intrinsics(path: Path, key: str, k: Tensor) -> None:
    """K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (what :meth:`project` uses)."""
    structural = torch.tensor([k[1, 0], k[2, 0], k[2, 1], k[2, 2] - 1.0]).abs().max()
    if not (k[0, 0] > 0 and k[1, 1] > 0) or structural > 1e-9:
        raise CameraFileError(
            f"{path}: camera [{key}] 'matrix' must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with "
            f"fx, fy > 0; got {k.tolist()}"
        )


def _camera(path: Path, key: str, cam: dict) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, str]:
    """One ``[cam]`` table -> K, R, t, dist (5,), size, name."""
    fisheye = cam.get("fisheye", False)
    if not isinstance(fisheye, bool):
        raise CameraFileError(
            f"{path}: camera [{key}] 'fisheye' must be a TOML boolean (true or false, unquoted); "
            f"got {_describe(fisheye)}"
        )
    if fisheye:
        raise CameraFileError(f"{path}: camera [{key}] is fisheye, which is not supported")
    k = _camera_array(path, key, cam, "matrix", [(3, 3)])
    _check_intrinsics(path, key, k)
    dist = _camera_array(path, key, cam, "distortions", [(4,), (5,)])
    dist = torch.cat([dist, torch.zeros(5 - len(dist), dtype=torch.float64)])
    rotation = _camera_array(path, key, cam, "rotation", [(3,)])
    translation = _camera_array(path, key, cam, "translation", [(3,)])
    size = _camera_array(path, key, cam, "size", [(2,)])
    if not (size >= 1).all():
        raise CameraFileError(
            f"{path}: camera [{key}] 'size' must be [width, height] of at least 1 pixel; got "
            f"{cam['size']}"
        )
    name = cam.get("name", key)
    if not isinstance(name, str):
        raise CameraFileError(
            f"{path}: camera [{key}] 'name' must be a string; got {_describe(name)}"
        )
    r = axis_angle_to_rotation_matrix(rotation[None])[0]
    return k, r, translation, dist, size, name


def load_pose2sim_calibration(path: str | Path) -> CameraRig:
    """Read a Pose2Sim calibration TOML (``[cam]`` tables with ``size``, ``matrix``,
    ``distortions`` (k1 k2 p1 p2, or OpenCV's five with k3), ``rotation`` (Rodrigues),
    ``translation``, ``fisheye``).

    Values must be TOML numbers (not strings) of the right shape and finite; ``matrix`` an
    intrinsic matrix with positive focal lengths and bottom row ``[0, 0, 1]``; ``size`` at least
    1 x 1 pixel; ``fisheye`` a TOML boolean -- a quoted ``"false"`` is refused rather than
    guessed at (any non-empty string would otherwise read as true).

    Raises:
        CameraFileError: naming the file, the camera and the key that is missing or malformed,
            or saying the file is not UTF-8 text or not TOML.
        FileNotFoundError: if the file does not exist.
    """
    path = Path(path)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise CameraFileError(
            f"{path}: not a text file (not valid UTF-8 at byte {err.start}); expected a Pose2Sim "
            "calibration TOML"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise CameraFileError(f"{path}: not valid TOML ({err})") from None
    cams = {k: v for k, v in data.items() if isinstance(v, dict) and k != "metadata"}
    if not cams:
        raise CameraFileError(f"{path}: no camera tables found")
    parts = [_camera(path, key, cam) for key, cam in cams.items()]
    ks, rs, ts, ds, sizes, names = zip(*parts, strict=True)
    return CameraRig(
        torch.stack(ks),
        torch.stack(rs),
        torch.stack(ts),
        torch.stack(ds),
        torch.stack(sizes),
        list(names),
    )


def _toml_string(text: str) -> str:
    """A TOML basic string: JSON's escapes are TOML's (``\\"``, ``\\\\``, ``\\n``, ``\\uXXXX``);
    DEL, which JSON leaves as is and TOML forbids raw, is escaped too."""
    return json.dumps(text, ensure_ascii=False).replace("\x7f", "\\u007f")


def _toml_key(text: str) -> str:
    """A table name: bare (``cam_01``, as Pose2Sim writes) when TOML allows, else quoted."""
    bare = text and all(ch.isascii() and (ch.isalnum() or ch in "_-") for ch in text)
    return text if bare else _toml_string(text)


def _toml_numbers(values) -> str:
    """Nested lists of floats as TOML arrays; ``repr`` is the shortest text that reads back to
    the same double."""
    if isinstance(values, list):
        return "[" + ", ".join(_toml_numbers(v) for v in values) + "]"
    return repr(float(values))


def save_pose2sim_calibration(rig: CameraRig, path: str | Path) -> Path:
    """Write ``rig`` as a Pose2Sim calibration TOML, the format
    :func:`load_pose2sim_calibration` reads: one ``[name]`` table per camera with ``name``,
    ``size`` (width, height px), ``matrix`` (K), ``distortions`` (OpenCV's k1 k2 p1 p2 k3),
    ``rotation`` (Rodrigues vector of world-to-camera R), ``translation`` (t, metres),
    ``fisheye = false``; then ``[metadata]`` (``adjusted = false``, ``error = 0.0``) as Pose2Sim
    writes it. Numbers are written in full double precision (read back exactly; rotations to
    ~1e-15 through the Rodrigues vector).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: an orthographic rig (the format is pinhole only), camera names that are
            repeated or named ``metadata`` (each names a table), or non-finite values.
    """
    path = Path(path)
    if rig.orthographic:
        raise ValueError(
            f"{path}: a Pose2Sim calibration holds pinhole cameras; got an orthographic rig"
        )
    names = [str(n) for n in rig.names]
    if len(names) != rig.num_cameras:
        raise ValueError(f"{path}: {rig.num_cameras} cameras but {len(names)} names")
    if len(set(names)) != len(names) or "metadata" in names:
        raise ValueError(
            f"{path}: camera names must be distinct and not 'metadata' (each names a table); "
            f"got {names}"
        )
    values = {
        n: getattr(rig, n).detach().cpu().to(torch.float64) for n in ("K", "R", "t", "dist", "size")
    }
    for key, value in values.items():
        if not torch.isfinite(value).all():
            raise ValueError(f"{path}: rig.{key} must be finite; got {value.tolist()}")
    lines: list[str] = []
    for c, name in enumerate(names):
        lines += [
            f"[{_toml_key(name)}]",
            f"name = {_toml_string(name)}",
            f"size = {_toml_numbers(values['size'][c].tolist())}",
            f"matrix = {_toml_numbers(values['K'][c].tolist())}",
            f"distortions = {_toml_numbers(values['dist'][c].tolist())}",
            f"rotation = {_toml_numbers(matrix_to_rotation_vector(values['R'][c]).tolist())}",
            f"translation = {_toml_numbers(values['t'][c].tolist())}",
            "fisheye = false",
            "",
        ]
    lines += ["[metadata]", "adjusted = false", "error = 0.0", ""]
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def _normaliser(points: Tensor) -> Tensor:
    """Hartley normalisation: centroid to 0, mean distance sqrt(dim). ``(N, d)`` -> ``(d+1, d+1)``."""
    d = points.shape[-1]
    mean = points.mean(0)
    scale = math.sqrt(d) / (points - mean).norm(dim=-1).mean().clamp_min(1e-12)
    t = torch.eye(d + 1, dtype=points.dtype)
    t[:d, :d] *= scale
    t[:d, d] = -scale * mean
    return t


def dlt(points3d: Tensor, points2d: Tensor) -> Tensor:
    """Projection matrix from 2D-3D correspondences by the normalised DLT (proposal 4.4.1).

    Args:
        points3d: ``(N, 3)`` world points, N >= 6, not all coplanar.
        points2d: ``(N, 2)`` their pixels (undistorted).

    Returns:
        ``(3, 4)`` P with ``P[2, :3]`` of unit norm and positive depth for the points.
    """
    if points3d.dim() != 2 or points3d.shape[-1] != 3 or points2d.shape != (points3d.shape[0], 2):
        raise ValueError(
            f"dlt needs points3d (N, 3) and points2d (N, 2); got {tuple(points3d.shape)} and "
            f"{tuple(points2d.shape)}"
        )
    if points3d.shape[0] < 6:
        raise ValueError(f"dlt needs at least 6 correspondences; got {points3d.shape[0]}")
    x3 = points3d.double()
    x2 = points2d.double()
    t3, t2 = _normaliser(x3), _normaliser(x2)
    h3 = torch.cat([x3, torch.ones(len(x3), 1, dtype=x3.dtype)], 1) @ t3.T
    h2 = torch.cat([x2, torch.ones(len(x2), 1, dtype=x2.dtype)], 1) @ t2.T
    zeros = torch.zeros_like(h3)
    rows_u = torch.cat([h3, zeros, -h2[:, :1] * h3], 1)
    rows_v = torch.cat([zeros, h3, -h2[:, 1:2] * h3], 1)
    a = torch.cat([rows_u, rows_v], 0)
    _, _, vh = torch.linalg.svd(a)
    p = torch.linalg.solve(t2, vh[-1].reshape(3, 4) @ t3)
    p = p / p[2, :3].norm()
    depth = torch.cat([x3, torch.ones(len(x3), 1, dtype=x3.dtype)], 1) @ p[2]
    if (depth < 0).sum() > len(depth) / 2:
        p = -p
    return p.to(points3d.dtype)


def decompose_projection(P: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``P = K [R | t]`` by RQ decomposition, ``K`` with positive diagonal, ``det R = +1``.

    Shapes: ``(..., 3, 4)`` -> K ``(..., 3, 3)`` (``K[2, 2] = 1``), R ``(..., 3, 3)``, t ``(..., 3)``.
    """
    m = P[..., :3]
    # RQ via QR of the row-reversed transpose: M = K R.
    flip = torch.flip(torch.eye(3, dtype=P.dtype), [0])
    q, r = torch.linalg.qr((flip @ m).transpose(-1, -2))
    k = flip @ r.transpose(-1, -2) @ flip
    rot = flip @ q.transpose(-1, -2)
    sign = torch.diag_embed(torch.sign(torch.diagonal(k, dim1=-2, dim2=-1)))
    k = k @ sign
    rot = sign @ rot
    det = torch.linalg.det(rot)
    rot = rot * det[..., None, None]
    scale = k[..., 2:3, 2:3]
    t = torch.linalg.solve(k, P[..., 3:]).squeeze(-1) * det[..., None]
    k = k / scale
    return k, rot, t
