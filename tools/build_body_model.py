"""Build common/data/body_model.npz from the CC0 MakeHuman base mesh in ../shared/data/body/makehuman.

Run once by maintainers (the result is committed):  python tools/build_body_model.py [MAKEHUMAN_DIR]

What it does:
- keeps the `body` group of base.obj (skin only), splits quads into triangles;
- converts to our world (metres, z up, actor facing -y, feet on z = 0);
- places our 17 joints at the rig's joint heads;
- labels every vertex with one of our 16 segments by its largest CMU-bone weight, and keeps
  the weights summed per segment for smooth skinning (the virtual studio's surface);
- fits one ellipsoid per segment to the segment's vertices (the cpu energy's surface).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common.body import JOINT_NAMES, SEGMENT_NAMES  # noqa: E402

MESH_UNIT = 0.1  # metres per base.obj unit
# Our segments <- MakeHuman CMU bones whose vertices they take.
SEGMENT_BONES = {
    "pelvis": ["Hips", "LHipJoint", "RHipJoint", "LowerBack"],
    "abdomen": ["Spine"],
    "chest": ["Spine1", "LeftShoulder", "RightShoulder"],
    "head": ["Neck", "Neck1", "Head"],
    "l_upperarm": ["LeftArm"], "l_forearm": ["LeftForeArm"],
    "l_hand": ["LeftHand", "LeftFingerBase", "LeftHandFinger1", "LThumb"],
    "r_upperarm": ["RightArm"], "r_forearm": ["RightForeArm"],
    "r_hand": ["RightHand", "RightFingerBase", "RightHandFinger1", "RThumb"],
    "l_thigh": ["LeftUpLeg"], "l_shin": ["LeftLeg"], "l_foot": ["LeftFoot", "LeftToeBase"],
    "r_thigh": ["RightUpLeg"], "r_shin": ["RightLeg"], "r_foot": ["RightFoot", "RightToeBase"],
}
# Our joints <- rig bone head (or tail) positions.
JOINT_SOURCE = {
    "pelvis": ("Hips", "head"), "spine": ("Spine", "head"), "chest": ("Spine1", "head"),
    "neck": ("Neck", "head"),
    "l_shoulder": ("LeftArm", "head"), "l_elbow": ("LeftForeArm", "head"), "l_wrist": ("LeftHand", "head"),
    "r_shoulder": ("RightArm", "head"), "r_elbow": ("RightForeArm", "head"), "r_wrist": ("RightHand", "head"),
    "l_hip": ("LeftUpLeg", "head"), "l_knee": ("LeftLeg", "head"), "l_ankle": ("LeftFoot", "head"),
    "r_hip": ("RightUpLeg", "head"), "r_knee": ("RightLeg", "head"), "r_ankle": ("RightFoot", "head"),
    "head_top": ("Head", "tail"),
}
SHELL_VARIANCE_FACTOR = 3.0  # points on an ellipsoid's surface: var along an axis = r^2 / 3


def read_body_group(obj_path: Path):
    verts, faces, group = [], [], None
    for line in obj_path.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("g "):
            group = line[2:].strip()
        elif line.startswith("f ") and group == "body":
            idx = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
            for k in range(1, len(idx) - 1):  # fan triangulation of quads
                faces.append([idx[0], idx[k], idx[k + 1]])
    return np.array(verts), np.array(faces, dtype=np.int64)


def main(mh_dir: Path) -> None:
    verts_obj, faces = read_body_group(mh_dir / "base.obj")
    # obj is y-up facing +z; ours is z-up facing -y: (x, y, z)_obj -> (x, -z, y)
    verts = np.stack([verts_obj[:, 0], -verts_obj[:, 2], verts_obj[:, 1]], axis=1) * MESH_UNIT
    used = np.unique(faces)
    remap = -np.ones(len(verts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    verts, faces = verts[used], remap[faces]
    orig_index = used

    rig = json.loads((mh_dir / "rig.cmu_mb.json").read_text())
    joints = np.array([rig[b][end]["default_position"] for b, end in (JOINT_SOURCE[j] for j in JOINT_NAMES)])
    shift = np.array([-joints[0, 0], -joints[0, 1], -verts[:, 2].min()])
    verts = verts + shift
    joints = joints + shift

    weights_doc = json.loads((mh_dir / "weights.cmu_mb.json").read_text())["weights"]
    bone_to_seg = {b: SEGMENT_NAMES.index(s) for s, bones in SEGMENT_BONES.items() for b in bones}
    full = np.zeros((len(verts_obj), len(SEGMENT_NAMES)))
    for bone, pairs in weights_doc.items():
        seg = bone_to_seg[bone]
        arr = np.asarray(pairs, dtype=np.float64)
        np.add.at(full[:, seg], arr[:, 0].astype(np.int64), arr[:, 1])
    skin = full[orig_index]
    missing = skin.sum(1) == 0
    if missing.any():
        raise SystemExit(f"{missing.sum()} body vertices carry no weight")
    skin /= skin.sum(1, keepdims=True)
    vertex_segment = skin.argmax(1)
    # a triangle belongs to the segment most of its vertices belong to (first vertex on ties)
    tri_seg_votes = vertex_segment[faces]
    tri_segment = np.array([np.bincount(v, minlength=len(SEGMENT_NAMES)).argmax() for v in tri_seg_votes])

    # area-weighted surface moments: vertex density varies a lot (the face is dense)
    tri_pts = verts[faces]
    tri_area = 0.5 * np.linalg.norm(np.cross(tri_pts[:, 1] - tri_pts[:, 0], tri_pts[:, 2] - tri_pts[:, 0]), axis=1)
    tri_centre = tri_pts.mean(1)
    centres, axes, radii = [], [], []
    for s in range(len(SEGMENT_NAMES)):
        sel = tri_segment == s
        w = tri_area[sel] / tri_area[sel].sum()
        pts = tri_centre[sel] - joints[s]
        c = w @ pts
        d = pts - c
        evals, evecs = np.linalg.eigh((d * w[:, None]).T @ d)
        if np.linalg.det(evecs) < 0:
            evecs[:, 0] *= -1
        centres.append(c)
        axes.append(evecs)  # columns are the ellipsoid's axes
        radii.append(np.sqrt(SHELL_VARIANCE_FACTOR * np.maximum(evals, 1e-8)))

    keep = skin >= 1e-3  # store weights sparsely enough to stay small
    skin = np.where(keep, skin, 0.0)
    skin /= skin.sum(1, keepdims=True)
    out = ROOT / "common" / "data" / "body_model.npz"
    np.savez_compressed(
        out,
        joint_rest=joints.astype(np.float64),
        vertices=verts.astype(np.float32),
        triangles=faces.astype(np.int32),
        triangle_segment=tri_segment.astype(np.int8),
        vertex_segment=vertex_segment.astype(np.int8),
        skin_weights=skin.astype(np.float16),
        ellipsoid_centres=np.array(centres),
        ellipsoid_axes=np.array(axes),
        ellipsoid_radii=np.array(radii),
    )
    print(f"wrote {out}: {len(verts)} vertices, {len(faces)} triangles, height {verts[:, 2].max():.3f} m")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT.parent / "shared" / "data" / "body" / "makehuman")
