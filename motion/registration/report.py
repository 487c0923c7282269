"""The HTML report of a registration: one self-contained page a coach can read.

What it shows, top to bottom: the headline numbers (time offset, speed ratio, fit), the
largest joint differences in words, the time correspondence curve, a heat map of per-joint
differences over time, the fit quality per frame (where to trust the result), key frames side
by side (video, registered student, reference) and the per-joint table. Every picture is a PNG
embedded in the page (``data:`` URIs), so the file opens offline and can be mailed as is.

The page is a Jinja2 template (``templates/report.html.j2``); the figures are matplotlib's.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import jinja2
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from motion.angles import describe_coordinate
from motion.cameras import CameraRig
from motion.registration.export import (
    TRUSTED_FIT,
    JointAngles,
    RegistrationSummary,
    proportion_words,
)
from motion.registration.render import BodyPoses, side_by_side_frames
from motion.registration.types import Registration

__all__ = ["FIT_FAIR", "FIT_GOOD", "KeyFrame", "ReportInputs", "key_frames", "write_report"]

#: silhouette IoU from which a frame's registration is called good (the body model's
#: capsules never cover a clothed silhouette exactly: 0.7 is a close fit)
FIT_GOOD = 0.7
#: below this IoU the frame is called poor: the body drawn there may be wrong
FIT_FAIR = TRUSTED_FIT
#: key frames shown side by side in the report
KEY_FRAMES = 4
#: seconds at least between two key frames
KEY_FRAME_GAP_S = 0.25
#: pixels of height of each key-frame panel (cropped around the person)
KEY_FRAME_HEIGHT = 300
#: key frames are drawn on the video upscaled to this height before the crop, so a person
#: filling half the frame is drawn at about the panel's size, not magnified from a small one
KEY_FRAME_DRAW_HEIGHT = 2 * KEY_FRAME_HEIGHT
#: joints drawn in the heat map (the largest mean differences; all if fewer)
HEATMAP_JOINTS = 16

_TEMPLATES = jinja2.Environment(
    loader=jinja2.PackageLoader("motion.registration", "templates"),
    autoescape=jinja2.select_autoescape(["html", "j2"]),
    undefined=jinja2.StrictUndefined,
)


@dataclass(frozen=True)
class ReportInputs:
    """What the report is made from.

    Attributes:
        registration: the result.
        summary: its summary (offset, speed, per-joint differences, ...).
        angles: per joint and frame, reference and student angles.
        poses: the two bodies to draw (:func:`motion.registration.render.body_poses`).
        frames: per camera, the video frames ``(T', H, W, 3)`` uint8 at the rig's size.
        rig: the cameras (the rig the features were computed with).
        video_names: a name per camera (e.g. the video files).
        trusted: ``(T', J')`` bool per frame and joint of ``angles``: where the findings
            may come from (a good enough fit, the joint's bones inside the image); the rest
            is greyed in the heat map, and frames with a poor fit in the curves.
        files: output files to list in the report (name -> relative path).
    """

    registration: Registration
    summary: RegistrationSummary
    angles: JointAngles
    poses: BodyPoses
    frames: Sequence[np.ndarray]
    rig: CameraRig
    video_names: Sequence[str]
    trusted: np.ndarray
    files: dict[str, str]


@dataclass(frozen=True)
class KeyFrame:
    """A video frame worth looking at, and why."""

    frame: int
    why: str


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _image_uri(image: np.ndarray) -> str:
    ok, data = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("could not encode a key frame as PNG")
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode("ascii")


def _video_time(inputs: ReportInputs) -> np.ndarray:
    return np.asarray(inputs.angles.time_s, dtype=np.float64)


def _shade_untrusted(ax, time: np.ndarray, trusted: np.ndarray) -> None:
    """Grey bands over the frames not trusted (there the curves may be wrong)."""
    step = (time[1] - time[0]) if len(time) > 1 else 1.0
    for t, ok in zip(time, trusted, strict=True):
        if not ok:
            ax.axvspan(t - step / 2, t + step / 2, color="0.85", lw=0, zorder=0)


def correspondence_figure(inputs: ReportInputs) -> str:
    """C as reference time against the source video's time, stage 1's and the
    least-squares straight line (the summary's speed ratio) beside it."""
    s, reg = inputs.summary, inputs.registration
    time = _video_time(inputs)
    rate = s.reference_rate_hz
    fig, ax = plt.subplots(figsize=(7.5, 3.2))
    _shade_untrusted(ax, time, inputs.registration.fit.numpy() >= FIT_FAIR)
    ax.plot(time, reg.C_stage1.numpy() / rate, ":", color="0.5", label="first pass (stage 1)")
    ax.plot(time, reg.C.numpy() / rate, "-", color="C0", lw=2, label="registered")
    line = np.polyval(np.polyfit(time, reg.C.numpy() / rate, 1), time) if len(time) > 1 else None
    ax.plot(
        time,
        reg.C.numpy() / rate if line is None else line,
        "--",
        color="C3",
        lw=1,
        label=f"straight-line fit: speed x{s.speed_ratio:.2f}",
    )
    ax.set_xlabel("student video time (s)")
    ax.set_ylabel("reference time (s)")
    ax.set_title("Which moment of the reference each video frame matches")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return _png(fig)


def _heatmap_joints(inputs: ReportInputs) -> list[int]:
    means = np.nanmean(np.abs(inputs.angles.difference_deg.numpy()), 0)
    order = np.argsort(-np.nan_to_num(means, nan=-1.0))
    return sorted(order[:HEATMAP_JOINTS].tolist())


def heatmap_figure(inputs: ReportInputs) -> str:
    """Joint angle differences (student - reference, degrees) over video time: red where
    the student flexes (adducts, ...) more, blue where less."""
    a = inputs.angles
    cols = _heatmap_joints(inputs)
    diff = a.difference_deg.numpy()[:, cols].T.copy()
    diff[~inputs.trusted[:, cols].T] = np.nan  # shown grey: not trusted
    finite = np.abs(diff[np.isfinite(diff)])
    limit = max(5.0, float(np.percentile(finite, 98))) if finite.size else 5.0
    time = _video_time(inputs)
    fig, ax = plt.subplots(figsize=(7.5, 0.28 * len(cols) + 1.4))
    step = (time[1] - time[0]) if len(time) > 1 else 1.0
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.8")
    im = ax.imshow(
        diff,
        aspect="auto",
        cmap=cmap,
        vmin=-limit,
        vmax=limit,
        extent=(time[0] - step / 2, time[-1] + step / 2, len(cols) - 0.5, -0.5),
        interpolation="nearest",
    )
    ax.set_yticks(
        range(len(cols)), [describe_coordinate(a.coordinates[c]).label for c in cols], fontsize=8
    )
    ax.set_xlabel("student video time (s)")
    ax.set_title("How much more (red) or less (blue) each joint angle is than the reference's")
    fig.colorbar(im, ax=ax, label="degrees", fraction=0.04, pad=0.02)
    return _png(fig)


def fit_figure(inputs: ReportInputs) -> str:
    """Per-frame silhouette IoU with the trust bands."""
    fit = inputs.registration.fit.numpy()
    time = _video_time(inputs)
    fig, ax = plt.subplots(figsize=(7.5, 2.4))
    _shade_untrusted(ax, time, inputs.registration.fit.numpy() >= FIT_FAIR)
    ax.axhspan(FIT_GOOD, 1.0, color="#d9f0d3", lw=0, alpha=0.7)
    ax.axhspan(FIT_FAIR, FIT_GOOD, color="#fdf1c7", lw=0, alpha=0.7)
    ax.axhspan(0.0, FIT_FAIR, color="#f6d5d5", lw=0, alpha=0.7)
    ax.plot(time, fit, color="k", lw=1.5)
    ax.set_ylim(0, 1)
    ax.set_xlim(time[0], time[-1] if len(time) > 1 else time[0] + 1)
    ax.set_xlabel("student video time (s)")
    ax.set_ylabel("silhouette overlap")
    ax.set_title("Fit quality: green = trust, yellow = check, red = unreliable")
    return _png(fig)


def key_frames(inputs: ReportInputs, count: int = KEY_FRAMES) -> list[KeyFrame]:
    """The middle of each of the largest differences stated, then the best-fitting frame,
    then evenly spread frames, in time order; a candidate closer than :data:`KEY_FRAME_GAP_S`
    to one already chosen is skipped (a finding's frame is kept over the others)."""
    time = _video_time(inputs)
    n = len(time)
    chosen: dict[int, str] = {}

    def offer(t: int, why: str) -> None:
        far = all(abs(time[t] - time[k]) >= KEY_FRAME_GAP_S for k in chosen)
        if len(chosen) < count and far:
            chosen[t] = why

    for d in inputs.summary.largest_differences:
        if not d["stated"]:
            continue
        mid = 0.5 * (d["start_s"] + d["end_s"])
        offer(int(np.argmin(np.abs(time - mid))), d["text"])
    offer(int(np.argmax(inputs.registration.fit.numpy())), "the best-fitting frame")
    for t in np.linspace(0, n - 1, count + 2)[1:-1].round().astype(int).tolist():
        offer(int(t), "")
    return [KeyFrame(t, chosen[t]) for t in sorted(chosen)]


def _fit_word(iou: float) -> str:
    return "good" if iou >= FIT_GOOD else ("fair" if iou >= FIT_FAIR else "poor")


def _key_frame_pictures(inputs: ReportInputs, frames: list[KeyFrame]) -> list[dict]:
    reg, s = inputs.registration, inputs.summary
    ids = [k.frame for k in frames]
    pictures = list(
        side_by_side_frames(
            inputs.frames[0],
            inputs.rig,
            0,
            inputs.poses,
            frame_ids=ids,
            captions=[("video", "registered student", "reference")] * len(ids),
            with_video=True,
            zoom=KEY_FRAME_HEIGHT,
            min_height=KEY_FRAME_DRAW_HEIGHT,
        )
    )
    out = []
    for k, pic in zip(frames, pictures, strict=True):
        iou = float(reg.fit[k.frame])
        out.append(
            {
                "image": _image_uri(pic),
                "time": f"{float(inputs.angles.time_s[k.frame]):.2f}",
                "reference_time": f"{int(reg.C[k.frame]) / s.reference_rate_hz:.2f}",
                "fit": f"{iou:.2f} ({_fit_word(iou)})",
                "why": k.why,
            }
        )
    return out


def _trust_counts(fit: np.ndarray) -> dict[str, float]:
    n = max(1, len(fit))
    return {
        "good": 100.0 * float((fit >= FIT_GOOD).sum()) / n,
        "fair": 100.0 * float(((fit >= FIT_FAIR) & (fit < FIT_GOOD)).sum()) / n,
        "poor": 100.0 * float((fit < FIT_FAIR).sum()) / n,
    }


def _speed_words(ratio: float) -> str:
    if abs(ratio - 1) < 0.03:
        return "at the reference's speed"
    how = "faster" if ratio > 1 else "slower"
    return f"{abs(ratio - 1) * 100:.0f} % {how} than the reference"


def render_report(inputs: ReportInputs) -> str:
    """The report's HTML text (self-contained)."""
    s, reg = inputs.summary, inputs.registration
    fit = reg.fit.numpy()
    per_joint = sorted(s.per_joint_mean_abs_deg.items(), key=lambda kv: -kv[1])
    template = _TEMPLATES.get_template("report.html.j2")
    return template.render(
        title=f"Registration of {html.unescape(', '.join(inputs.video_names))}",
        s=s,
        reference_name=Path(s.reference).name,
        duration=f"{s.num_video_frames / s.video_rate_hz:.2f}",
        start_s=f"{s.reference_start_s:.2f}",
        video_start=f"{s.video_start_s:.2f}",
        first_frame=s.video_frames[0],
        size_measured=s.G_measured,
        size_note=s.notes.get("G", ""),
        proportions=proportion_words(s.proportions),
        speed_words=_speed_words(s.speed_ratio),
        fit_mean=f"{float(fit.mean()):.2f}",
        fit_word=_fit_word(float(fit.mean())),
        trust=_trust_counts(fit),
        untrusted=int((fit < FIT_FAIR).sum()),
        trusted_frames=int(inputs.trusted.any(-1).sum()),
        fit_good=FIT_GOOD,
        fit_fair=FIT_FAIR,
        correspondence=correspondence_figure(inputs),
        heatmap=heatmap_figure(inputs),
        fit_plot=fit_figure(inputs),
        key_frames=_key_frame_pictures(inputs, key_frames(inputs)),
        stated=[d for d in s.largest_differences if d["stated"]],
        withheld=[d for d in s.largest_differences if not d["stated"]],
        per_joint=[(describe_coordinate(n).label, n, f"{deg:.1f}") for n, deg in per_joint],
        timings=[(k, f"{v:.1f}") for k, v in s.timings.items()],
        notes=sorted(s.notes.items()),
        other_warnings=s.warnings[len(s.movement.get("reasons", [])) :],
        files=sorted(inputs.files.items()),
        cameras=", ".join(inputs.rig.names),
    )


def write_report(path: str | Path, inputs: ReportInputs) -> Path:
    """Write the report to ``path`` (HTML, self-contained) and return the path."""
    path = Path(path)
    path.write_text(render_report(inputs), encoding="utf-8")
    return path
