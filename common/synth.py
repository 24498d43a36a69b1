"""The virtual studio (Bottino's protocol): real motion drives the body, K cameras film it.

Silhouettes are rendered from the smoothly skinned MakeHuman surface by default, a different
surface from the rigid segments and ellipsoids the fitter uses, so a fit is never the model
recognising itself. Cameras may differ in image size (``synth_studio``): every image is
written at its camera's size. Noise follows Cheung et al.: independent flips of foreground pixels
(missed, rate eta) and background pixels (false, rate xi), plus small false blobs.

The motion is a BVH clip or, with ``SynthOptions.posture``, a short take generated from joint
angles (``posture_motion``: seeded variations of a seated, crouching, kneeling or lying
posture, ``common.postures``), since no bundled clip sits, crouches or lies.

A real-like studio adds what real takes have and the body model cannot explain:

- lens distortion (``synth_studio(distortion=k1)``): strong barrel distortion, k1 with
  k2 = DISTORTION_K2_PER_K1 * k1, applied in the renderer exactly as ``Camera.project`` applies
  it, so ``common.frame.undistort_masks`` with the written calibration undoes it;
- a static prop (``SynthOptions.prop``): a chair under the actor's pelvis or a box beside the
  actor, made of axis-aligned boxes in the prop's frame (``prop_boxes``), their faces
  tessellated finely (``box_mesh``) so that per-vertex distortion stays exact enough, and
  rendered in one mesh with the body: real foreground in the silhouettes, occluding the body
  where it is in front; absent from the empty-studio backgrounds, as a chair brought in is;
- a world that is not z up (``SynthOptions.up``): everything is rendered in our z-up studio,
  and calibration.json and truth.jsonl's joints are written in the user's world
  (``common.world``: x_user = W^T x_fit); truth's params stay in the z-up fit frame, as the
  fitter's do.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from common.body import (FORWARD, LATERAL, P, SEGMENT_NAMES, BodyModel, forward_kinematics, joints_dict,
                         rigid_vertices, rot_z, skinned_vertices)
from common.calibration import save_calibration
from common.camera import Studio, circle_studio
from common.errors import UserError, print_warning
from common.motion_import import import_bvh
from common.postures import POSTURES, posture_params, varied_posture
from common.sequence import FRAME_NAME, write_mask_png, write_sequence_meta
from common.world import world_frame

CHEUNG_ETA = 0.043  # fraction of foreground pixels missed (Cheung et al. 2000)
CHEUNG_XI = 0.021   # fraction of background pixels falsely set
BLOBS_PER_IMAGE = 3         # small false-foreground blobs per camera image
BLOB_RADIUS_PX = (1.5, 4.0)  # their radius range, pixels
SURFACES = ("skinned", "rigid")
NOISE_MODELS = ("none", "cheung")
UP_AXES = ("+z", "-z", "+y", "-y")

RING_FOV_DEG = 55.0  # vertical field of view of the ring cameras, degrees
# k2 = -0.3 k1: opposite sign, and the radial map r -> r (1 + k1 r^2 + k2 r^4) stays monotonic
# (derivative 1 - 1.5 |k1| > 0 at its minimum, r = 1) for barrel k1 down to -2/3
DISTORTION_K2_PER_K1 = -0.3
MAX_DISTORTION_K1 = 0.6  # |k1| accepted

PROPS = ("chair", "box")
PROP_LABEL = len(SEGMENT_NAMES)   # label of the prop's triangles, after the body's segments
PROP_CELL_M = 0.02                # edge of the prop's surface triangles, metres
PROP_RGB = {"chair": (120, 80, 45), "box": (185, 145, 95)}  # wood, cardboard
SEAT_SIZE_M = 0.45                # chair seat width and depth, metres
SEAT_HEIGHT_M = 0.45              # nominal seat height, metres
SEAT_HEIGHT_RANGE_M = (0.30, 0.60)  # the seat top follows the actor's underside within this
SEAT_THICKNESS_M = 0.04
SEATED_SEGMENTS = tuple(SEGMENT_NAMES.index(n) for n in ("pelvis", "l_thigh", "r_thigh"))  # what a seat carries
SEAT_BEHIND_PELVIS_M = 0.14       # seat's back edge behind the pelvis joint (the buttocks)
CHAIR_LEG_M = 0.04                # square legs
CHAIR_BACK_M = (0.03, 0.45)       # backrest thickness and height above the seat, metres
BOX_SIZE_M = (0.5, 0.5, 0.45)     # box width (actor's lateral), depth, height, metres
BOX_CLEARANCE_M = 0.15            # gap between the actor's side and the box

POSTURE_FPS = 30.0        # frames per second of a posture take
POSTURE_KEY_FRAMES = 10   # frames between the take's keyframes
POSTURE_SPREAD = 0.08     # radians, the posture's own joint angles' variation per keyframe
# small movements on top, per keyframe (radians): arms and a lean of the trunk
GESTURE_SPREAD = {"l_shoulder_x": 0.25, "r_shoulder_x": 0.25, "l_shoulder_y": 0.15, "r_shoulder_y": 0.15,
                  "l_elbow": 0.3, "r_elbow": 0.3, "spine_x": 0.12, "neck_turn": 0.2}


@dataclass(frozen=True)
class SynthOptions:
    frames: int = 60
    start: int = 1          # frame 0 of the CMU conversions is an added T-pose
    step: int = 4           # 120 fps clips -> 30 fps
    noise: str = "none"
    surface: str = "skinned"
    seed: int = 0
    images: bool = False
    up: str = "+z"          # the written world's up axis (UP_AXES)
    prop: str | None = None  # None or one of PROPS
    posture: str | None = None  # a name in common.postures.POSTURES instead of the clip
    position: tuple[float, float] = (0.0, 0.0)  # the actor's floor position (x, y), metres, z-up frame


def add_cheung_noise(mask: np.ndarray, rng: np.random.Generator, eta: float = CHEUNG_ETA,
                     xi: float = CHEUNG_XI) -> np.ndarray:
    """(H, W) bool -> (H, W) bool with missed/false pixels at rates eta/xi and a few blobs."""
    flip = np.where(mask, rng.random(mask.shape) < eta, rng.random(mask.shape) < xi)
    out = mask ^ flip
    H, W = mask.shape
    yy, xx = np.mgrid[0:H, 0:W]
    for _ in range(BLOBS_PER_IMAGE):
        cx, cy = rng.uniform(0, W), rng.uniform(0, H)
        r = rng.uniform(*BLOB_RADIUS_PX)
        out |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
    return out


TRUE_SILHOUETTES = "silhouettes_true"  # exact masks kept beside colour images
BACKGROUND_FRAMES = 20  # empty-studio frames written per camera with --images


class ColourWriter:
    """Colour images for ``--images``: the body in clothing colours (and the prop, label
    PROP_LABEL, in ``prop_rgb``) in a textured room, their shadow on the floor, per-frame
    lighting gain and sensor noise; plus empty backgrounds. triangles: (T, 3) of the mesh
    whose vertices ``write_frame`` gets."""

    def __init__(self, studio: Studio, triangles: np.ndarray, rng: np.random.Generator, out: Path,
                 prop_rgb=None):
        from PIL import Image

        from common import colour_studio as cs

        self.cs, self.Image = cs, Image
        self.studio, self.triangles, self.rng, self.out = studio, triangles, rng, out
        self.prop_rgb = prop_rgb
        self.backgrounds = [cs.make_background(cam, rng) for cam in studio]
        empty = [np.zeros((c.height, c.width), dtype=bool) for c in studio]
        for n in range(BACKGROUND_FRAMES):
            gain = 1.0 + rng.uniform(-cs.GAIN_JITTER, cs.GAIN_JITTER)
            for cam, bg, e in zip(studio, self.backgrounds, empty):
                img = cs.composite_frame(cam, e, None, None, bg, rng, gain, cs.NOISE_SIGMA, psf_sigma=cs.PSF_SIGMA)
                self._save("background", cam.name, n, img)

    def _save(self, sub: str, camera: str, index: int, img: np.ndarray) -> None:
        path = self.out / sub / camera / FRAME_NAME.format(frame=index)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.Image.fromarray(img).save(path)

    def write_frame(self, index: int, vertices: np.ndarray, labels: list) -> None:
        cs = self.cs
        gain = 1.0 + self.rng.uniform(-cs.GAIN_JITTER, cs.GAIN_JITTER)
        darkening = self.rng.uniform(*cs.SHADOW_DARKENING)
        for cam, bg, lab in zip(self.studio, self.backgrounds, labels):
            shadow = cs.floor_shadow_mask(cam, vertices, cs.LIGHT_DIR, self.triangles)
            colours = cs.clothing_colours(lab)
            if self.prop_rgb is not None:
                colours[lab == PROP_LABEL] = self.prop_rgb
            img = cs.composite_frame(cam, lab >= 0, colours, shadow, bg, self.rng, gain,
                                     cs.NOISE_SIGMA, darkening, cs.PSF_SIGMA)
            self._save("images", cam.name, index, img)


def synth_studio(cameras: int, sizes, radius_m: float = 3.0, height_m: float = 1.5,
                 fov_y_deg: float = RING_FOV_DEG, distortion: float = 0.0) -> Studio:
    """``circle_studio`` of ``cameras`` cameras, camera i of image size sizes[i % len(sizes)]
    ((n, 2) width, height pixels): one size for a plain studio, several for a mixed one. A
    camera's pose and field of view do not depend on its size. fov_y_deg: the ring cameras'
    vertical field of view (the overhead camera keeps its own). distortion: k1 of every
    camera, with k2 = DISTORTION_K2_PER_K1 * k1 (0: none)."""
    sizes = [(int(w), int(h)) for w, h in sizes]
    studios = {size: circle_studio(cameras, *size, radius=radius_m, height_m=height_m, fov_y_deg=fov_y_deg)
               for size in set(sizes)}
    cams = [studios[sizes[i % len(sizes)]][i] for i in range(cameras)]
    if distortion != 0.0:
        dist = np.array([distortion, DISTORTION_K2_PER_K1 * distortion, 0.0, 0.0, 0.0])
        cams = [replace(c, dist=dist.copy()) for c in cams]
    return Studio(tuple(cams))


# --------------------------------------------------------------------------- motion
def clip_frames(total: int, opts: SynthOptions) -> np.ndarray:
    idx = opts.start + opts.step * np.arange(opts.frames)
    return idx[idx < total]


def clip_motion(model: BodyModel, clip_path, opts: SynthOptions, joint_map=None):
    """(F, 35) parameters of the clip's frames centred on ``opts.position``, fps, metadata."""
    from common.bvh import read_bvh

    total = read_bvh(clip_path).num_frames
    src = clip_frames(total, opts)
    if len(src) == 0:
        raise UserError(f"{clip_path}: --start {opts.start} is past the clip's last frame ({total - 1})")
    if len(src) < opts.frames:
        print_warning(f"{clip_path}: its {total} frames hold {len(src)} from frame {opts.start} every {opts.step}: "
                      f"synthesising {len(src)} frames, not {opts.frames}")
    motion = import_bvh(model, clip_path, src, joint_map)
    params = motion.params.copy()
    # centre the performance in the studio (the cameras look at the origin)
    params[:, 0:2] += np.asarray(opts.position) - params[:, 0:2].mean(axis=0)
    meta = dict(clip=str(clip_path), source_frames=[int(f) for f in src])
    return params, motion.fps / opts.step, meta  # 120 fps every 4th frame: 30.0, not 30.00012


def _on_floor(model: BodyModel, params: np.ndarray, x: float, y: float, heading: float) -> np.ndarray:
    """(35,) ``params``' joint angles through ``posture_params``: at (x, y, heading), clipped into
    the limits, the lowest surface point on the floor."""
    angles = {name: float(params[i]) for name, i in P.items() if i >= P["root_tilt_x"]}
    return posture_params(model, angles, x, y, heading)


def posture_keyframe(model: BodyModel, posture: str, rng: np.random.Generator, x: float, y: float,
                     heading: float) -> np.ndarray:
    """(35,) ``varied_posture`` with GESTURE_SPREAD arm movements and lean on top, on the floor."""
    params = varied_posture(model, posture, rng, POSTURE_SPREAD, x, y, heading)
    for name, spread in GESTURE_SPREAD.items():
        params[P[name]] += rng.normal(0.0, spread)
    return _on_floor(model, params, x, y, heading)


def posture_motion(model: BodyModel, posture: str, frames: int, rng: np.random.Generator,
                   position=(0.0, 0.0)) -> tuple[np.ndarray, float]:
    """(frames, 35) a take moving smoothly (smoothstep) between ``posture_keyframe``s every
    POSTURE_KEY_FRAMES frames, at ``position`` with a heading drawn from ``rng``, every frame
    on the floor; and its fps."""
    x, y = (float(v) for v in position)
    heading = float(rng.uniform(-np.pi, np.pi))
    keys = np.stack([posture_keyframe(model, posture, rng, x, y, heading)
                     for _ in range((frames - 1) // POSTURE_KEY_FRAMES + 2)])
    i = np.arange(frames)
    k, s = i // POSTURE_KEY_FRAMES, (i % POSTURE_KEY_FRAMES) / POSTURE_KEY_FRAMES
    w = (s * s * (3.0 - 2.0 * s))[:, None]
    between = (1.0 - w) * keys[k] + w * keys[k + 1]
    return np.stack([_on_floor(model, p, x, y, heading) for p in between]), POSTURE_FPS


# --------------------------------------------------------------------------- props
def prop_boxes(kind: str, seat_height_m: float = SEAT_HEIGHT_M) -> np.ndarray:
    """(B, 2, 3) the prop's boxes as (lower, upper) corners in its own frame, metres: origin on
    the floor under the seat's (box's) centre, x to the actor's left, y to the actor's front."""
    if kind == "box":
        half = np.array(BOX_SIZE_M) * [0.5, 0.5, 1.0]
        return np.array([[[-half[0], -half[1], 0.0], half]])
    h, a, leg = seat_height_m, SEAT_SIZE_M / 2.0, CHAIR_LEG_M
    back_t, back_h = CHAIR_BACK_M
    boxes = [[[-a, -a, h - SEAT_THICKNESS_M], [a, a, h]],          # seat
             [[-a, -a, h], [a, -a + back_t, h + back_h]]]           # backrest, behind the actor
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            cx, cy, r = sx * (a - leg / 2.0), sy * (a - leg / 2.0), leg / 2.0
            boxes.append([[cx - r, cy - r, 0.0], [cx + r, cy + r, h - SEAT_THICKNESS_M]])
    return np.array(boxes)


def box_mesh(boxes: np.ndarray, cell_m: float = PROP_CELL_M) -> tuple[np.ndarray, np.ndarray]:
    """(B, 2, 3) boxes -> ((V, 3) vertices, (T, 3) triangles) of their surfaces, every face
    a grid of cells no wider than ``cell_m``."""
    verts, tris = [], []
    for lo, hi in np.asarray(boxes, dtype=np.float64):
        for axis in range(3):
            b, c = [a for a in range(3) if a != axis]
            nb = max(1, int(np.ceil((hi[b] - lo[b]) / cell_m)))
            nc = max(1, int(np.ceil((hi[c] - lo[c]) / cell_m)))
            gb, gc = np.meshgrid(np.linspace(lo[b], hi[b], nb + 1), np.linspace(lo[c], hi[c], nc + 1),
                                 indexing="ij")
            idx = np.arange((nb + 1) * (nc + 1)).reshape(nb + 1, nc + 1)
            quad = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
            face_tris = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])
            for side in (lo[axis], hi[axis]):
                v = np.empty((idx.size, 3))
                v[:, axis], v[:, b], v[:, c] = side, gb.reshape(-1), gc.reshape(-1)
                tris.append(face_tris + sum(len(x) for x in verts))
                verts.append(v)
    return np.concatenate(verts), np.concatenate(tris)


@dataclass(frozen=True)
class Prop:
    """A static prop: boxes (B, 2, 3) as (lower, upper) corners in its own frame (``prop_boxes``),
    axes (3, 3) its frame's x, y, z axes in the world as rows, origin (3,) metres."""

    kind: str
    boxes: np.ndarray
    axes: np.ndarray
    origin: np.ndarray

    def corners(self) -> np.ndarray:
        """(B, 8, 3) world corners of the boxes (corner i takes bit 2, 1, 0 of i: upper x, y, z)."""
        pick = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=bool)
        local = np.where(pick[None], self.boxes[:, 1][:, None], self.boxes[:, 0][:, None])
        return local @ self.axes + self.origin

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """((V, 3) world vertices, (T, 3) triangles): the ``box_mesh`` of the boxes, placed."""
        verts, tris = box_mesh(self.boxes)
        return verts @ self.axes + self.origin, tris


def place_prop(model: BodyModel, kind: str, params: np.ndarray, surface_of) -> Prop:
    """The prop ``kind`` placed for a take. params: (F, 35); surface_of(i): (V, 3) the body's
    rendered vertices in frame i.

    The prop turns with the actor's first heading. A chair's seat is under the first frame's
    pelvis, its back edge SEAT_BEHIND_PELVIS_M behind it (so the thighs lie on it), its top at
    the underside of the pelvis and thighs over the seat (clamped to SEAT_HEIGHT_RANGE_M); a
    box stands BOX_CLEARANCE_M to the actor's left of the body's widest extent over the take,
    level with the body's middle front to back.
    """
    Rz = rot_z(params[0, P["root_heading"]])
    axes = np.stack([Rz @ LATERAL, Rz @ FORWARD, [0.0, 0.0, 1.0]])
    pelvis = np.array([params[0, P["root_x"]], params[0, P["root_y"]], 0.0])
    if kind == "chair":
        origin = pelvis + (SEAT_SIZE_M / 2.0 - SEAT_BEHIND_PELVIS_M) * axes[1]
        local = (surface_of(0) - origin) @ axes.T
        over = (np.all(np.abs(local[:, :2]) <= SEAT_SIZE_M / 2.0, axis=1)
                & np.isin(model.vertex_segment, SEATED_SEGMENTS))
        top = local[over, 2].min() if np.any(over) else SEAT_HEIGHT_M
        return Prop(kind, prop_boxes(kind, float(np.clip(top, *SEAT_HEIGHT_RANGE_M))), axes, origin)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)  # the body's extent across and along, over the take
    for i in range(len(params)):
        local = (surface_of(i) - pelvis) @ axes[:2].T
        lo, hi = np.minimum(lo, local.min(axis=0)), np.maximum(hi, local.max(axis=0))
    origin = pelvis + (hi[0] + BOX_CLEARANCE_M + BOX_SIZE_M[0] / 2.0) * axes[0] + 0.5 * (lo[1] + hi[1]) * axes[1]
    return Prop(kind, prop_boxes(kind), axes, origin)


# --------------------------------------------------------------------------- the take
def synthesize(model: BodyModel, studio: Studio, clip_path, out_dir, opts: SynthOptions,
               joint_map=None, progress=None) -> dict:
    """Write a sequence folder for ``opts.frames`` frames of ``clip_path`` (or of the posture
    ``opts.posture``, clip_path unused); returns its summary. ``studio`` is z up; the files
    are written in the world of ``opts.up``."""
    from common.render_gl import MeshRenderer

    if opts.noise not in NOISE_MODELS:
        raise ValueError(f"noise must be one of {NOISE_MODELS}")
    if opts.surface not in SURFACES:
        raise ValueError(f"surface must be one of {SURFACES}")
    if opts.up not in UP_AXES:
        raise ValueError(f"up must be one of {UP_AXES}")
    if opts.prop is not None and opts.prop not in PROPS:
        raise ValueError(f"prop must be one of {PROPS}")
    rng = np.random.default_rng(opts.seed)
    if opts.posture is not None:
        if opts.posture not in POSTURES:
            raise ValueError(f"posture must be one of {tuple(POSTURES)}")
        params, fps = posture_motion(model, opts.posture, opts.frames, rng, opts.position)
        meta = dict(posture=opts.posture, heading=float(params[0, P["root_heading"]]))
    else:
        params, fps, meta = clip_motion(model, clip_path, opts, joint_map)
    world = world_frame(opts.up)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_calibration(world.studio_to_user(studio), out / "calibration.json")
    pose = forward_kinematics(model, params)
    surface = skinned_vertices if opts.surface == "skinned" else rigid_vertices
    # a box is placed from every frame's surface, which the frames then render: skin each once
    surfaces = [surface(model, pose, i) for i in range(len(params))] if opts.prop == "box" else None

    def surface_of(i: int) -> np.ndarray:
        return surface(model, pose, i) if surfaces is None else surfaces[i]

    triangles, labels = model.triangles, model.triangle_segment
    prop_verts = np.zeros((0, 3))
    if opts.prop is not None:
        prop = place_prop(model, opts.prop, params, surface_of)
        prop_verts, prop_tris = prop.mesh()
        triangles = np.concatenate([triangles, prop_tris + len(model.vertices)])
        labels = np.concatenate([labels, np.full(len(prop_tris), PROP_LABEL)])
        meta["prop"] = {"kind": opts.prop, "boxes": world.points_to_user(prop.corners()).round(6).tolist()}
    renderer = MeshRenderer(studio, triangles, labels)
    colour = ColourWriter(studio, triangles, rng, out, PROP_RGB.get(opts.prop)) if opts.images else None
    with open(out / "truth.jsonl", "w") as truth:
        for i in range(len(params)):
            verts = np.concatenate([surface_of(i), prop_verts])
            rendered = renderer.render_labels(verts)
            for cam, lab in zip(studio, rendered):
                mask = lab >= 0
                if opts.noise == "cheung":
                    mask = add_cheung_noise(mask, rng)
                write_mask_png(out / "silhouettes" / cam.name / FRAME_NAME.format(frame=i), mask)
                if colour is not None:  # segmentation will overwrite silhouettes/: keep the truth
                    write_mask_png(out / TRUE_SILHOUETTES / cam.name / FRAME_NAME.format(frame=i), lab >= 0)
            if colour is not None:
                colour.write_frame(i, verts, rendered)
            truth.write(json.dumps({"frame": i, "params": [float(x) for x in params[i]],
                                    "joints": joints_dict(world.points_to_user(pose.joints[i]))}) + "\n")
            if progress:
                progress(i + 1, len(params))
    meta.update(noise=opts.noise, surface=opts.surface, seed=opts.seed)
    if opts.up != "+z":
        meta["up"] = opts.up
    write_sequence_meta(out, range(len(params)), fps, studio.names, **meta)
    return {"frames": len(params), "fps": fps, "cameras": len(studio), **meta}
