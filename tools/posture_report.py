"""Posture figures of a fitted result without truth: hip and knee bend, feet above the floor,
frame-to-frame jitter and the XOR share (the real-take check of the README's table).

    python tools/posture_report.py RESULT [--json]

Angles in degrees from the joint positions (180 minus the angle at the joint: 0 is straight);
heights along the fit's up axis, metres, of the ankle joints and of each foot's lowest point
(the bottom of the foot's ellipsoid at the actor's size: the sole, which an ankle joint stands
some centimetres above); jitter: the mean over joints of the distance a joint moves from one
fitted frame to the next, millimetres.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common.body import JOINT_NAMES, SEGMENT_NAMES, forward_kinematics, load_body_model  # noqa: E402
from common.energy import ellipsoid_world  # noqa: E402
from common.errors import InputFileError, UserError  # noqa: E402
from common.world import world_frame  # noqa: E402
from server.results import POSES_FILE, SUMMARY_FILE, load_records  # noqa: E402


def bend_deg(a: np.ndarray, joint: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F, 3) x 3 -> (F,) 180 minus the angle a-joint-b, degrees (0: straight)."""
    u, v = a - joint, b - joint
    cos = np.sum(u * v, axis=-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
    return 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def foot_lowest_m(records: list[dict], actor_scale: float) -> dict:
    """{side: (F,) height of the foot's lowest point} in the fit frame (z up), metres: the
    records' parameters posed on the body model at ``actor_scale``, each foot's ellipsoid
    {c + A u : |u| <= 1} lowest at c_z - |A's z row|."""
    model = load_body_model().scaled(actor_scale)
    pose = forward_kinematics(model, np.array([r["params"] for r in records], dtype=np.float64))
    feet = [SEGMENT_NAMES.index(f"{side}_foot") for side in ("l", "r")]
    centres, A = ellipsoid_world(model, pose.rotations, pose.origins, feet)
    lowest = centres[..., 2] - np.linalg.norm(A[..., 2, :], axis=-1)
    return {"l": lowest[:, 0], "r": lowest[:, 1]}


def posture_figures(records: list[dict], actor_scale: float | None = None) -> dict:
    """The figures of the module docstring; the feet's lowest points where ``actor_scale`` (the
    run's, in its summary.json) is given."""
    up = str(records[0].get("world_up", "+z"))
    J = world_frame(up).points_to_fit(np.array([[r["joints"][n] for n in JOINT_NAMES] for r in records]))
    j = {n: J[:, i] for i, n in enumerate(JOINT_NAMES)}
    trunk_top = j["neck"]
    out = {"frames": len(records), "world_up": up}
    for side in ("l", "r"):
        out[f"{side}_hip_bend_deg"] = bend_deg(trunk_top, j[f"{side}_hip"], j[f"{side}_knee"]).tolist()
        out[f"{side}_knee_bend_deg"] = bend_deg(j[f"{side}_hip"], j[f"{side}_knee"], j[f"{side}_ankle"]).tolist()
        out[f"{side}_ankle_height_m"] = j[f"{side}_ankle"][:, 2].tolist()
    if actor_scale is not None:
        for side, heights in foot_lowest_m(records, actor_scale).items():
            out[f"{side}_foot_lowest_m"] = heights.tolist()
    out["jitter_mm"] = (np.linalg.norm(np.diff(J, axis=0), axis=-1).mean(axis=1) * 1000.0).tolist()
    out["xor_share"] = [r.get("fit_quality", {}).get("xor_share_total") for r in records]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="posture_report", description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("result", type=Path, help="a mocap fit result folder")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    summary = args.result / SUMMARY_FILE
    try:
        records = load_records(args.result)
        if not records:
            raise InputFileError(args.result / POSES_FILE, "holds no fitted frame")
        scale = json.loads(summary.read_text()).get("actor_scale") if summary.is_file() else None
    except (OSError, ValueError, AttributeError) as exc:  # a summary unreadable, not JSON, not an object
        print(f"posture_report: error: {summary}: {exc}", file=sys.stderr)
        return 2
    except UserError as exc:
        print(f"posture_report: error: {exc}", file=sys.stderr)
        return 2
    fig = posture_figures(records, scale)
    if args.json:
        print(json.dumps(fig, indent=1))
        return 0
    for key, values in fig.items():
        if isinstance(values, list) and values and values[0] is not None:
            v = np.array(values, dtype=float)
            print(f"{key:22s} min {v.min():8.3f}  median {np.median(v):8.3f}  max {v.max():8.3f}")
        else:
            print(f"{key:22s} {values}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
