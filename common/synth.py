"""The virtual studio (Bottino's protocol): real motion drives the body, K cameras film it.

Silhouettes are rendered from the smoothly skinned MakeHuman surface by default, a different
surface from the rigid segments and ellipsoids the fitter uses, so a fit is never the model
recognising itself. Cameras may differ in image size (``synth_studio``): every image is
written at its camera's size. Noise follows Cheung et al.: independent flips of foreground pixels
(missed, rate eta) and background pixels (false, rate xi), plus small false blobs.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.body import BodyModel, forward_kinematics, joints_dict, rigid_vertices, skinned_vertices
from common.calibration import save_calibration
from common.camera import Studio, circle_studio
from common.motion_import import import_bvh
from common.sequence import FRAME_NAME, write_mask_png, write_sequence_meta

CHEUNG_ETA = 0.043  # fraction of foreground pixels missed (Cheung et al. 2000)
CHEUNG_XI = 0.021   # fraction of background pixels falsely set
BLOBS_PER_IMAGE = 3         # small false-foreground blobs per camera image
BLOB_RADIUS_PX = (1.5, 4.0)  # their radius range, pixels
SURFACES = ("skinned", "rigid")
NOISE_MODELS = ("none", "cheung")


@dataclass(frozen=True)
class SynthOptions:
    frames: int = 60
    start: int = 1          # frame 0 of the CMU conversions is an added T-pose
    step: int = 4           # 120 fps clips -> 30 fps
    noise: str = "none"
    surface: str = "skinned"
    seed: int = 0
    images: bool = False


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
    """Colour images for ``--images``: the body in clothing colours in a textured room, its
    shadow on the floor, per-frame lighting gain and sensor noise; plus empty backgrounds."""

    def __init__(self, studio: Studio, model: BodyModel, rng: np.random.Generator, out: Path):
        from PIL import Image

        from common import colour_studio as cs

        self.cs, self.Image = cs, Image
        self.studio, self.model, self.rng, self.out = studio, model, rng, out
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
            shadow = cs.floor_shadow_mask(cam, vertices, cs.LIGHT_DIR, self.model.triangles)
            img = cs.composite_frame(cam, lab >= 0, cs.clothing_colours(lab), shadow, bg, self.rng, gain,
                                     cs.NOISE_SIGMA, darkening, cs.PSF_SIGMA)
            self._save("images", cam.name, index, img)


def synth_studio(cameras: int, sizes, radius_m: float = 3.0, height_m: float = 1.5) -> Studio:
    """``circle_studio`` of ``cameras`` cameras, camera i of image size sizes[i % len(sizes)]
    ((n, 2) width, height pixels): one size for a plain studio, several for a mixed one. A
    camera's pose and field of view do not depend on its size."""
    sizes = [(int(w), int(h)) for w, h in sizes]
    studios = {size: circle_studio(cameras, *size, radius=radius_m, height_m=height_m) for size in set(sizes)}
    return Studio(tuple(studios[sizes[i % len(sizes)]][i] for i in range(cameras)))


def clip_frames(total: int, opts: SynthOptions) -> np.ndarray:
    idx = opts.start + opts.step * np.arange(opts.frames)
    return idx[idx < total]


def synthesize(model: BodyModel, studio: Studio, clip_path, out_dir, opts: SynthOptions,
               joint_map=None, progress=None) -> dict:
    """Write a sequence folder for ``opts.frames`` frames of ``clip_path``; returns its summary."""
    from common.bvh import read_bvh
    from common.render_gl import MeshRenderer

    if opts.noise not in NOISE_MODELS:
        raise ValueError(f"noise must be one of {NOISE_MODELS}")
    if opts.surface not in SURFACES:
        raise ValueError(f"surface must be one of {SURFACES}")
    total = read_bvh(clip_path).num_frames
    src = clip_frames(total, opts)
    motion = import_bvh(model, clip_path, src, joint_map)
    params = motion.params.copy()
    # centre the performance in the studio (the cameras look at the origin)
    params[:, 0:2] -= params[:, 0:2].mean(axis=0)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_calibration(studio, out / "calibration.json")
    renderer = MeshRenderer(studio, model.triangles, model.triangle_segment)
    rng = np.random.default_rng(opts.seed)
    pose = forward_kinematics(model, params)
    colour = ColourWriter(studio, model, rng, out) if opts.images else None
    fps = 1.0 / (motion.frame_time * opts.step)
    with open(out / "truth.jsonl", "w") as truth:
        for i in range(len(params)):
            verts = skinned_vertices(model, pose, i) if opts.surface == "skinned" else rigid_vertices(model, pose, i)
            labels = renderer.render_labels(verts)
            for cam, lab in zip(studio, labels):
                mask = lab >= 0
                if opts.noise == "cheung":
                    mask = add_cheung_noise(mask, rng)
                write_mask_png(out / "silhouettes" / cam.name / FRAME_NAME.format(frame=i), mask)
                if colour is not None:  # segmentation will overwrite silhouettes/: keep the truth
                    write_mask_png(out / TRUE_SILHOUETTES / cam.name / FRAME_NAME.format(frame=i), lab >= 0)
            if colour is not None:
                colour.write_frame(i, verts, labels)
            truth.write(json.dumps({"frame": i, "params": [float(x) for x in params[i]],
                                    "joints": joints_dict(pose.joints[i])}) + "\n")
            if progress:
                progress(i + 1, len(params))
    meta = dict(clip=str(clip_path), source_frames=[int(f) for f in src], noise=opts.noise,
                surface=opts.surface, seed=opts.seed)
    write_sequence_meta(out, range(len(params)), fps, studio.names, **meta)
    return {"frames": len(params), "fps": fps, "cameras": len(studio), **meta}
