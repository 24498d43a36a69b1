"""How good a fit is: joint errors against the truth, how well the body explains the masks, and
how the actor-size search scores a size."""
from __future__ import annotations

import numpy as np

from common.body import JOINT_NAMES
from common.fitting import FrameResult
from common.frame import FrameData


def joint_errors_mm(joints: np.ndarray, truth_frame) -> np.ndarray:
    """(17,) distances of fitted joints (17, 3) metres, in JOINT_NAMES order, from a TruthFrame's, mm."""
    true = np.array([truth_frame.joints[n] for n in JOINT_NAMES])
    return np.linalg.norm(np.asarray(joints) - true, axis=1) * 1000.0


def accuracy(records: list[dict], truth: dict | None) -> dict:
    """Joint position errors against the truth, millimetres."""
    if not truth:
        return {}
    errs = [joint_errors_mm([r["joints"][n] for n in JOINT_NAMES], truth[r["frame"]])
            for r in records if r["frame"] in truth]
    if not errs:
        return {}
    E = np.array(errs)
    per_frame = E.mean(axis=1)
    return {
        "mean_joint_error_mm": float(E.mean()),
        "max_joint_error_mm": float(E.max()),
        "per_joint_error_mm": {n: float(v) for n, v in zip(JOINT_NAMES, E.mean(axis=0))},
        "per_frame_error_mm": [float(v) for v in per_frame],
        "per_frame_max_error_mm": [float(v) for v in E.max(axis=1)],
    }


QUALITY_FLAG_SHARE = 0.3  # a frame whose XOR is above this share of a camera's silhouette is flagged


# A size larger than the model's is scored by its fit's XOR with each model pixel outside the
# silhouettes counted this many times. Masks hold foreground no body explains (a chair sat on, a
# mask worn, loose clothes), which a larger body covers while staying inside them, so the plain
# XOR falls past the actor's size (a seated body on a chair, truth 1.0: 6,275 at 1.0, 5,867 at
# 1.1); a body poking out of the silhouettes is wrong wherever the masks are whole. Every take of
# docs/accuracy.md's size table picks its size for weights 1.5-2.5.
SIZE_OUTSIDE_WEIGHT = 2.0


def silhouette_disagreement(data: FrameData, params: np.ndarray) -> np.ndarray:
    """(C, 2) pixel counts per camera of the pose ``params`` (35,) drawn against the frame's
    masks (undistorted images, the fit's own): [model pixels outside the silhouette, silhouette
    pixels the model misses]. Their sum is the camera's XOR."""
    rendered = data.whole_image_energy().render(np.asarray(params))
    sizes = [(c.height, c.width) for c in data.studio]
    return np.array([[np.count_nonzero(r[:h, :w] & ~m[:h, :w]), np.count_nonzero(m[:h, :w] & ~r[:h, :w])]
                     for r, m, (h, w) in zip(rendered, data.masks, sizes)], dtype=np.int64).reshape(-1, 2)


def size_score(data: FrameData, fit: FrameResult, larger: bool) -> float:
    """How well ``fit`` (made at the size of the actor whose ``data`` it is) explains the frame's
    masks, for the actor-size search (``server.session.choose_actor_scale``), on one side of the
    model's size. ``larger``: its XOR with the model pixels outside the silhouettes counted
    SIZE_OUTSIDE_WEIGHT times; smaller: the plain XOR. Foreground no body explains only ever
    favours a larger body, so only the step up needs the weight; the step down does not, and
    with it a body's own artefacts decided there: a crouch's thigh and calf ellipsoids poke out
    of its folded legs (1,210 model pixels outside at the truth's size and pose, 414 at 0.9),
    so the weighted score chose 0.9 for a crouching actor of the model's size."""
    outside, missed = silhouette_disagreement(data, fit.params).sum(axis=0)
    return float((SIZE_OUTSIDE_WEIGHT if larger else 1.0) * outside + missed)


def frame_quality(data: FrameData, params: np.ndarray) -> dict:
    """How well the pose ``params`` (35,) explains one frame's masks, per camera: the XOR (model
    xor silhouette) as a share of the silhouette's area, the whole frame's share, and whether
    (and which cameras) it is above QUALITY_FLAG_SHARE. The XOR's two sides per camera too:
    model pixels outside the silhouette (a body where the masks see none) and silhouette pixels
    the model misses (a limb not found, or foreground no body explains: a prop sat on, a
    shadow), which tell a wrong pose from masks that hold more than the actor."""
    outside, missed = (np.asarray(v, dtype=np.int64) for v in silhouette_disagreement(data, params).T)
    xor = [int(v) for v in outside + missed]
    sizes = [(c.height, c.width) for c in data.studio]
    area = [int(np.count_nonzero(m[:h, :w])) for m, (h, w) in zip(data.masks, sizes)]
    share = [x / a if a else (0.0 if x == 0 else 1.0) for x, a in zip(xor, area)]
    flagged = [c.name for c, v in zip(data.studio, share) if v > QUALITY_FLAG_SHARE]
    return {"xor_share": [round(v, 4) for v in share], "xor_pixels": xor, "silhouette_pixels": area,
            "outside_pixels": [int(v) for v in outside], "missed_pixels": [int(v) for v in missed],
            "xor_share_total": round(sum(xor) / max(sum(area), 1), 4), "flagged_cameras": flagged}


def quality_summary(records: list[dict], cameras: list[str]) -> dict:
    """Fit quality over the records: the mean and worst XOR share, per camera too, the mean
    shares of its two sides (model outside the silhouettes, silhouette missed; records written
    before they were kept have none), and the frames flagged (``frame_quality``) with the
    cameras that disagree."""
    q = [r["fit_quality"] for r in records if "fit_quality" in r]
    if not q:
        return {}
    total = np.array([v["xor_share_total"] for v in q])
    per_camera = np.array([v["xor_share"] for v in q])
    sides = {side: float(np.mean([sum(v[f"{side}_pixels"]) / max(sum(v["silhouette_pixels"]), 1) for v in q]))
             for side in ("outside", "missed") if all(f"{side}_pixels" in v for v in q)}
    return {"mean_xor_share": float(total.mean()), "max_xor_share": float(total.max()),
            **{f"mean_{side}_share": value for side, value in sides.items()},
            "per_camera_mean_xor_share": {c: float(v) for c, v in zip(cameras, per_camera.mean(axis=0))},
            "flag_share": QUALITY_FLAG_SHARE,
            "frames_flagged": [{"frame": r["frame"], "cameras": r["fit_quality"]["flagged_cameras"]}
                               for r in records if r.get("fit_quality", {}).get("flagged_cameras")]}
