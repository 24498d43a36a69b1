"""Pictures of a result folder: silhouette overlays, 3D views of the fitted model, a GIF, plots.

- Overlays: per camera, the input silhouette in grey, the fitted model's outline, and the XOR
  pixels in colour (orange: silhouette the model misses; blue: model outside the silhouette).
  The model is the rigid segment mesh (OpenGL, ``common.render_gl``); without a GL context the
  analytic ellipsoids of the cpu energy stand in.
- Views: the fitted mesh, flat-shaded per triangle and coloured per segment (left side warm,
  right side cool), on a floor grid, from any viewpoint (``common.camera.look_at``), with the
  true skeleton drawn over it where the sequence has truth.
- ``sequence.gif`` and ``sequence.mp4``: one camera's overlay beside a 3D view (Pillow; H.264
  through imageio-ffmpeg's ffmpeg): the GIF subsampled to at most MAX_GIF_FRAMES, the video every
  frame of the take at its frame rate.
- Plots (matplotlib, Agg): energy, joint error per frame and per joint, time per frame and per
  chain.

``make_result_pictures`` writes them all into ``RESULT/pictures/``.

One module of about 700 lines: every picture (overlays, skeleton views, contact sheets, the
MP4) draws with the same projection and tile helpers.
"""
from __future__ import annotations

import io
import itertools
import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from common.body import (
    JOINT_NAMES, SEGMENT_NAMES, SEGMENT_PARENTS, BodyModel, forward_kinematics, rigid_vertices,
)
from common.camera import Camera, Studio, look_at
from common.errors import InputFileError, UserError, print_warning
from common.export import FittedMotion
from common.sequence import Sequence, load_sequence
from server.output import staged_folder
from server.progress import Progress
from server.results import (FOREGROUND_FILE, RUN_FILE, SUMMARY_FILE, frames_text, load_records,
                            read_foreground_left_out, read_run_settings)

PICTURES_DIR = "pictures"
GIF_NAME = "sequence.gif"
VIDEO_NAME = "sequence.mp4"
MAX_OVERLAY_CAMERAS = 4      # cameras in a default overlay strip
MAX_PICTURE_FRAMES = 4       # frames with an overlay strip and a 3D view by default
MAX_GIF_FRAMES = 300         # longer sequences are subsampled in the GIF
GIF_HEIGHT = 240             # pixels, each panel of the GIF
CROP_MARGIN = 0.12           # cropped overlays: margin around the actor, fraction of its size
CROP_MIN_FRACTION = 0.4      # cropped overlays: at least this fraction of the image height
VIDEO_QUALITY = 7            # imageio-ffmpeg's 0-10 scale: small files, no visible blocks at these sizes
VIDEO_BLOCK = 2              # H.264 in yuv420p needs even frame sizes: frames are padded to a multiple
VIEW_SIZE = (480, 480)       # pixels, 3D views
VIEW_DISTANCE_M = 4.0        # 3D view camera distance from the pelvis
VIEW_FOV_DEG = 40.0
GIF_VIEW_DISTANCE_M = 3.2    # closer than VIEW_DISTANCE_M: the GIF's panels are small
SHADE_LEVELS = 15            # flat-shading levels per segment (16 x 15 labels fit the 8-bit label buffer)
GRID_STEP_M = 0.5            # floor grid spacing
GRID_HALF_M = 2.0            # floor grid extent around the actor

# overlay colours (RGB)
BACKGROUND = (246, 246, 246)
AGREE = (150, 150, 150)      # silhouette and model
MISSED = (235, 110, 30)      # silhouette only: the model misses it
EXTRA = (40, 110, 225)       # model only: outside the silhouette
OUTLINE = (15, 15, 15)
TRUTH_COLOUR = (20, 160, 70)     # true skeleton over 3D views
# segment base colours: torso grey-blue, head sand, left limbs warm, right limbs cool
SEGMENT_COLOURS = {
    "pelvis": (120, 130, 150), "abdomen": (130, 140, 160), "chest": (140, 150, 170), "head": (215, 190, 160),
    "l_upperarm": (235, 140, 90), "l_forearm": (240, 160, 110), "l_hand": (245, 185, 140),
    "r_upperarm": (80, 160, 200), "r_forearm": (100, 180, 215), "r_hand": (135, 200, 225),
    "l_thigh": (215, 110, 80), "l_shin": (225, 130, 95), "l_foot": (235, 155, 120),
    "r_thigh": (70, 140, 180), "r_shin": (90, 160, 195), "r_foot": (120, 180, 210),
}
BONES = tuple((SEGMENT_PARENTS[s], s) for s in range(1, 16)) + ((3, 16),)  # joint index pairs


# ----------------------------------------------------------------------------- result data

@dataclass(frozen=True)
class ResultData:
    """A result folder opened for pictures and reports.

    records: poses.jsonl lines; summary: summary.json ({} when missing); motion: the fitted
    motion; sequence: the sequence it was fitted to, or None when it cannot be found;
    truth: (F, 17, 3) true joints aligned with motion.frames (NaN where a frame has none), or None,
    in the z-up fit frame as everything drawn is (``motion.fit_joints``; the files hold the user's).
    """

    path: Path
    records: list
    summary: dict
    motion: FittedMotion
    sequence: Sequence | None
    truth: np.ndarray | None

    @property
    def energies(self) -> np.ndarray:
        return np.array([r.get("energy", np.nan) for r in self.records], dtype=np.float64)

    @property
    def seconds(self) -> np.ndarray:
        return np.array([r.get("seconds", np.nan) for r in self.records], dtype=np.float64)

    def joint_errors_mm(self) -> np.ndarray | None:
        """(F, 17) distance from fitted to true joints, mm (NaN where no truth), or None."""
        if self.truth is None:
            return None
        return np.linalg.norm(self.motion.fit_joints - self.truth, axis=-1) * 1000.0


def _recorded_sequence(result_dir: Path, summary: dict) -> str | None:
    """The sequence a result was fitted from: summary.json's, else run.json's (written before
    the first frame, so an interrupted fit has it too)."""
    if summary.get("sequence"):
        return str(summary["sequence"])
    try:
        return str(read_run_settings(result_dir / RUN_FILE).get("sequence") or "") or None
    except (OSError, UserError):
        return None


def _sequence_path(result_dir: Path, summary: dict, sequence_dir) -> Path | None:
    if sequence_dir is not None:
        return Path(sequence_dir)
    recorded = _recorded_sequence(result_dir, summary)
    if recorded and Path(recorded).is_dir():
        return Path(recorded)
    return None


def load_result(result_dir, sequence_dir=None, fps: float | None = None) -> ResultData:
    """Open a result folder. The sequence comes from ``sequence_dir`` or summary.json's path.

    Frame rate: ``fps`` if given, else the sequence's. Raises UserError when neither is known.
    """
    result_dir = Path(result_dir)
    if not result_dir.is_dir():
        raise InputFileError(result_dir, "not a result folder (does not exist)")
    records = load_records(result_dir)
    if not records:
        raise InputFileError(result_dir / "poses.jsonl", "holds no fitted frame")
    summary_path = result_dir / SUMMARY_FILE
    summary = {}
    if summary_path.exists():
        try:
            summary = json.loads(summary_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:  # read as a result without one: run.json names the sequence
            print_warning(f"{summary_path}: not valid JSON ({exc}); read without it")
        if not isinstance(summary, dict):
            summary = {}
    seq_path = _sequence_path(result_dir, summary, sequence_dir)
    up = records[0].get("world_up", "+z")  # the frame the fit ran in
    cleaned = bool(summary.get("masks_cleaned", True))
    sequence = (load_sequence(seq_path, up=up, clean_masks=cleaned, calibration=summary.get("calibration"))
                if seq_path is not None else None)
    if sequence is not None and summary.get("cameras_left_out"):  # drawn as fitted: without them
        sequence = sequence.without_cameras(summary["cameras_left_out"])
    if sequence is not None and (cleared := read_foreground_left_out(result_dir)) is not None:
        if cleared.shape != (len(sequence.studio), *sequence.studio.padded_shape):
            raise InputFileError(result_dir / FOREGROUND_FILE, f"cleared pixels for {cleared.shape[0]} cameras of "
                                 f"{cleared.shape[2]}x{cleared.shape[1]}, where {sequence.path} has "
                                 f"{len(sequence.studio)} of {sequence.studio.padded_shape[1]}x"
                                 f"{sequence.studio.padded_shape[0]}: not the sequence this result was fitted to")
        sequence = sequence.without_foreground(cleared)  # the masks as the fit had them
    if fps is None:
        if sequence is None:
            recorded = _recorded_sequence(result_dir, summary) or "(not recorded)"
            raise UserError(f"{result_dir}: the sequence {recorded!r} is not there, so its frame rate is unknown; "
                            "pass --sequence SEQ or --fps FPS")
        fps = sequence.fps
    motion = FittedMotion.from_records(records, fps, str(result_dir / "poses.jsonl"))
    truth = None
    if sequence is not None:
        frames_truth = sequence.truth()
        if frames_truth:
            truth = np.full(motion.joints.shape, np.nan)
            for i, f in enumerate(motion.frames):
                t = frames_truth.get(int(f))
                if t is not None:
                    truth[i] = [t.joints[n] for n in JOINT_NAMES]
            truth = None if np.all(np.isnan(truth)) else motion.world.points_to_fit(truth)
    return ResultData(result_dir, records, summary, motion, sequence, truth)


def default_frames(result: ResultData, count: int = MAX_PICTURE_FRAMES) -> list[int]:
    """Frame numbers worth a picture: spread evenly from first to last, plus the worst one."""
    F = len(result.motion.frames)
    spread = np.linspace(0, F - 1, min(count - 1, F)).round().astype(int)
    chosen = {int(result.motion.frames[i]) for i in spread} | {worst_frame(result)}
    return sorted(chosen)


def worst_frame(result: ResultData) -> int:
    """The frame number with the largest mean joint error (or energy where there is no truth)."""
    err = result.joint_errors_mm()
    score = err.mean(axis=1) if err is not None else result.energies  # NaN rows: frames without truth
    return int(result.motion.frames[int(np.nanargmax(score))]) if np.any(np.isfinite(score)) else int(result.motion.frames[0])


def default_cameras(studio: Studio, count: int = MAX_OVERLAY_CAMERAS) -> list[str]:
    """Up to ``count`` camera names spread evenly over the studio."""
    idx = np.linspace(0, len(studio) - 1, min(count, len(studio))).round().astype(int)
    return [studio[int(i)].name for i in dict.fromkeys(idx.tolist())]


def frame_index(result: ResultData, frame: int) -> int:
    hits = np.flatnonzero(result.motion.frames == int(frame))
    if hits.size == 0:
        raise UserError(f"{result.path}: frame {frame} was not fitted (fitted: {frames_text(result.motion.frames)})")
    return int(hits[0])


def camera_indices(studio: Studio, cameras) -> list[int]:
    """Camera names (or indices) -> indices into the studio; UserError for unknown names."""
    out = []
    for c in cameras:
        if isinstance(c, (int, np.integer)):
            if not 0 <= c < len(studio):
                raise UserError(f"--cameras: camera index {c} outside 0..{len(studio) - 1}")
            out.append(int(c))
        elif c in studio.names:
            out.append(studio.names.index(c))
        else:
            raise UserError(f"--cameras: unknown camera {c!r}; the studio has {', '.join(studio.names)}")
    return out


# ---------------------------------------------------------------------------------- painting

class ModelPainter:
    """Draws one actor's fitted mesh: silhouettes in studio cameras, shaded views from anywhere.

    Uses OpenGL (one MeshRenderer per set of cameras, kept); falls back to the analytic
    ellipsoids of the cpu energy when no headless GL context can be made.
    """

    def __init__(self, model: BodyModel):
        self.model = model
        self.renderers: dict = {}
        self.gl = None  # decided at first use

    def _renderer(self, cameras: tuple[Camera, ...]):
        if self.gl is None:
            try:
                from common.render_gl import gl_context

                gl_context()
                self.gl = True
            except UserError:
                self.gl = False
        if not self.gl:
            return None
        key = tuple((c.name, c.width, c.height, c.K.tobytes(), c.R.tobytes(), c.t.tobytes()) for c in cameras)
        if key not in self.renderers:
            from common.render_gl import MeshRenderer

            self.renderers[key] = MeshRenderer(Studio(cameras), self.model.triangles,
                                               np.zeros(len(self.model.triangles)))
        return self.renderers[key]

    def silhouettes(self, params: np.ndarray, cameras: tuple[Camera, ...]) -> list[np.ndarray]:
        """(35,) pose -> per camera (H, W) bool silhouette of the rigid segment mesh."""
        renderer = self._renderer(tuple(cameras))
        if renderer is None:
            return [self._ellipsoid_labels(params, cam) >= 0 for cam in cameras]
        pose = forward_kinematics(self.model, params)
        return renderer.render_masks(rigid_vertices(self.model, pose))

    def _ellipsoid_labels(self, params: np.ndarray, cam: Camera) -> np.ndarray:
        """(H, W) int16 segment label image of the ellipsoids, far segments painted first."""
        from common.conic_bits import conic_coverage
        from common.energy import ellipsoid_world, image_conics

        pose = forward_kinematics(self.model, params)
        centres, A = ellipsoid_world(self.model, pose.rotations, pose.origins, range(16))
        C, drawable = image_conics(cam.projection_matrix[None], centres, A)
        labels = np.full((cam.height, cam.width), -1, dtype=np.int16)
        zero = np.zeros(1)
        for s in np.argsort(-cam.depth(centres[0])):
            one = np.ascontiguousarray(C[:, :, s:s + 1]), np.ascontiguousarray(drawable[:, :, s:s + 1])
            labels[conic_coverage(*one, zero, zero, cam.height, cam.width)[0, 0]] = s
        return labels

    def view(self, params: np.ndarray, cam: Camera, skeleton: np.ndarray | None = None,
             floor_centre: np.ndarray | None = None) -> np.ndarray:
        """(35,) pose seen by ``cam`` -> (H, W, 3) uint8: shaded mesh on a floor grid.

        skeleton: optional (17, 3) joints (the truth) drawn as lines over the model;
        floor_centre: (2+,) where the floor grid is centred (default: below the pelvis).
        """
        img = Image.new("RGB", (cam.width, cam.height), BACKGROUND)
        if floor_centre is None:
            floor_centre = params[:2]
        _draw_floor(ImageDraw.Draw(img), cam, floor_centre)
        out = np.array(img)
        renderer = self._renderer((cam,))
        if renderer is None:
            seg = self._ellipsoid_labels(params, cam)
            shade = np.full(seg.shape, SHADE_LEVELS - 1)
        else:
            pose = forward_kinematics(self.model, params)
            verts = rigid_vertices(self.model, pose)
            renderer.set_triangle_labels(self._triangle_labels(verts, cam))
            lab = renderer.render_labels(verts)[0]
            seg = np.where(lab >= 0, lab // SHADE_LEVELS, -1)
            shade = np.where(lab >= 0, lab % SHADE_LEVELS, 0)
        palette = np.array([SEGMENT_COLOURS[n] for n in SEGMENT_NAMES], dtype=np.float64)
        light = 0.35 + 0.65 * shade / (SHADE_LEVELS - 1)
        body = seg >= 0
        out[body] = (palette[seg[body]] * light[body, None]).clip(0, 255).astype(np.uint8)
        if skeleton is not None and np.all(np.isfinite(skeleton)):
            img = Image.fromarray(out)
            draw = ImageDraw.Draw(img)
            uv = cam.project(skeleton)
            for a, b in BONES:
                draw.line([tuple(uv[a]), tuple(uv[b])], fill=TRUTH_COLOUR, width=2)
            for x, y in uv:
                draw.ellipse([x - 2, y - 2, x + 2, y + 2], fill=TRUTH_COLOUR)
            out = np.array(img)
        return out

    def _triangle_labels(self, verts: np.ndarray, cam: Camera) -> np.ndarray:
        """(T,) label = segment * SHADE_LEVELS + shade, flat shading by a light at the camera."""
        tri = verts[self.model.triangles]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        to_eye = cam.center - tri.mean(axis=1)
        to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
        lambert = np.abs(np.einsum("ti,ti->t", n, to_eye))  # winding-independent
        shade = np.round(lambert * (SHADE_LEVELS - 1)).astype(np.int64)
        return self.model.triangle_segment.astype(np.int64) * SHADE_LEVELS + shade


def _draw_floor(draw: ImageDraw.ImageDraw, cam: Camera, centre) -> None:
    """Grid lines on z = 0 around ``centre`` (x, y), snapped to the grid."""
    c = np.round(np.asarray(centre[:2]) / GRID_STEP_M) * GRID_STEP_M
    ticks = np.arange(-GRID_HALF_M, GRID_HALF_M + 1e-9, GRID_STEP_M)
    for t in ticks:
        for a, b in (((c[0] + t, c[1] - GRID_HALF_M), (c[0] + t, c[1] + GRID_HALF_M)),
                     ((c[0] - GRID_HALF_M, c[1] + t), (c[0] + GRID_HALF_M, c[1] + t))):
            pts = np.array([[a[0], a[1], 0.0], [b[0], b[1], 0.0]])
            if np.all(cam.depth(pts) > 0.1):
                uv = cam.project(pts)
                draw.line([tuple(uv[0]), tuple(uv[1])], fill=(205, 205, 205), width=1)


def orbit_camera(target: np.ndarray, azimuth_deg: float, elevation_deg: float, size=VIEW_SIZE,
                 distance_m: float = VIEW_DISTANCE_M, name: str = "view") -> Camera:
    """A look_at camera on a sphere around ``target``; azimuth 0 looks from +x, -90 from the front (-y)."""
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = np.asarray(target, dtype=np.float64) + distance_m * np.array(
        [np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return look_at(name, eye, target, size[0], size[1], VIEW_FOV_DEG)


def view_target(joints: np.ndarray) -> np.ndarray:
    """(17, 3) joints -> (3,) look-at point: above the pelvis at mid body height."""
    return np.array([joints[0, 0], joints[0, 1], 0.5 * (joints[:, 2].max() + max(joints[:, 2].min(), 0.0))])


# ---------------------------------------------------------------------------------- overlays

def outline(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool -> (H, W) bool: mask pixels with a 4-neighbour outside the mask."""
    m = np.pad(mask, 1)
    inner = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    return mask & ~inner


def overlay_image(silhouette: np.ndarray, model: np.ndarray) -> np.ndarray:
    """Input (H, W) bool and model (H, W) bool -> (H, W, 3) uint8 overlay picture."""
    out = np.empty(silhouette.shape + (3,), dtype=np.uint8)
    out[:] = BACKGROUND
    out[silhouette & model] = AGREE
    out[silhouette & ~model] = MISSED
    out[model & ~silhouette] = EXTRA
    out[outline(model)] = OUTLINE
    return out


def _caption(img: np.ndarray, text: str) -> np.ndarray:
    """Adds a caption bar above an (H, W, 3) picture."""
    bar = Image.new("RGB", (img.shape[1], 16), (255, 255, 255))
    ImageDraw.Draw(bar).text((4, 2), text, fill=(40, 40, 40))
    return np.concatenate([np.array(bar), img], axis=0)


def hstack(images: list[np.ndarray], gap: int = 4) -> np.ndarray:
    """Pictures side by side (padded to the tallest) with white gaps."""
    H = max(im.shape[0] for im in images)
    parts = []
    for i, im in enumerate(images):
        if im.shape[0] < H:
            im = np.concatenate([im, np.full((H - im.shape[0],) + im.shape[1:], 255, np.uint8)])
        parts.append(im)
        if i < len(images) - 1:
            parts.append(np.full((H, gap, 3), 255, np.uint8))
    return np.concatenate(parts, axis=1)


def fit_height(img: np.ndarray, height: int, width: int | None = None) -> np.ndarray:
    """(H, W, 3) -> ``height`` rows, the width scaled alike (or ``width``)."""
    w = width or max(1, round(img.shape[1] * height / img.shape[0]))
    if img.shape[:2] == (height, w):
        return img
    return np.array(Image.fromarray(img).resize((w, height), Image.BILINEAR))


def crop_box(masks: list[np.ndarray], aspect: float, margin: float = CROP_MARGIN) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) around the union of (H, W) bool masks, widened to ``aspect`` (w / h)."""
    H, W = masks[0].shape
    union = np.logical_or.reduce(masks)
    if not union.any():
        return 0, 0, W, H
    ys, xs = np.nonzero(union)
    cy, cx = 0.5 * (ys.min() + ys.max()), 0.5 * (xs.min() + xs.max())
    h = (ys.max() - ys.min() + 1) * (1 + 2 * margin)
    w = (xs.max() - xs.min() + 1) * (1 + 2 * margin)
    h = min(max(h, w / aspect, CROP_MIN_FRACTION * H), H)
    w = min(h * aspect, W)
    x0 = int(np.clip(round(cx - w / 2), 0, W - w))
    y0 = int(np.clip(round(cy - h / 2), 0, H - h))
    return x0, y0, x0 + int(round(w)), y0 + int(round(h))


def overlay_strip(result: ResultData, painter: ModelPainter, frame: int, cameras: list[int],
                  height: int | None = None, crop: bool = False) -> tuple[np.ndarray, dict]:
    """One frame's overlays for ``cameras`` side by side -> ((H, W, 3) uint8, {camera: XOR pixels}).

    height: scale each picture to this many rows; crop: zoom each camera to the actor, keeping
    the camera's own aspect ratio (each tile is shaped like its camera's image).
    """
    seq = _need_sequence(result)
    i = frame_index(result, frame)
    cams = tuple(seq.studio[c] for c in cameras)
    sil = seq.silhouettes(frame)
    masks = painter.silhouettes(result.motion.params[i], cams)
    drawn = "mesh" if painter.gl else "ellipsoids"  # known once it has drawn
    pics, xor = [], {}
    for c, cam, model_mask in zip(cameras, cams, masks):
        own = sil[c, :cam.height, :cam.width]  # cameras of different sizes: a padded stack
        xor[cam.name] = int(np.count_nonzero(own ^ model_mask))
        pic = overlay_image(own, model_mask)
        if crop:
            x0, y0, x1, y1 = crop_box([own, model_mask], cam.width / cam.height)
            pic = pic[y0:y1, x0:x1]
        if height:  # a crop is the camera's shape to a pixel: every frame's tile the same size
            pic = fit_height(pic, height, round(height * cam.width / cam.height) if crop else None)
        pics.append(_caption(pic, f"{cam.name}  frame {frame}  {drawn} XOR {xor[cam.name]} px"))
    return hstack(pics), xor


def model_views(result: ResultData, painter: ModelPainter, frame: int,
                angles=((-70.0, 12.0), (0.0, 12.0), (-90.0, 70.0)), size=VIEW_SIZE) -> np.ndarray:
    """The fitted model at ``frame`` from several (azimuth, elevation) viewpoints, side by side."""
    i = frame_index(result, frame)
    joints = result.motion.fit_joints[i]
    truth = result.truth[i] if result.truth is not None else None
    target = view_target(joints)
    pics = []
    for az, el in angles:
        cam = orbit_camera(target, az, el, size)
        pics.append(_caption(painter.view(result.motion.params[i], cam, truth),
                             f"frame {frame}  azimuth {az:g}  elevation {el:g}"))
    return hstack(pics)


def _need_sequence(result: ResultData) -> Sequence:
    if result.sequence is None:
        raise UserError(f"{result.path}: overlays need the sequence's silhouettes; pass --sequence SEQ")
    return result.sequence


def sequence_frames(result: ResultData, painter: ModelPainter, indices, camera: int | None = None,
                    progress=None) -> Iterator[np.ndarray]:
    """Pictures of the frames at ``indices`` (into motion.frames), one at a time (a long take's
    would not fit in memory together), each (H, W, 3) uint8 of one size: one camera's overlay
    (cropped to the actor, the camera's aspect kept) beside a 3D view from one fixed direction
    that follows the pelvis, under a caption."""
    joints = result.motion.fit_joints
    ground_z = 0.5 * (joints[..., 2].max() + max(joints[..., 2].min(), 0.0))
    size = (GIF_HEIGHT, GIF_HEIGHT)
    for n, i in enumerate(indices):
        target = np.array([joints[i, 0, 0], joints[i, 0, 1], ground_z])
        cam = orbit_camera(target, -70.0, 12.0, size, distance_m=GIF_VIEW_DISTANCE_M)
        panels = [painter.view(result.motion.params[i], cam)]
        caption = f"frame {int(result.motion.frames[i])}"
        if result.sequence is not None:
            c = 0 if camera is None else camera
            strip, _ = overlay_strip(result, painter, int(result.motion.frames[i]), [c], GIF_HEIGHT, crop=True)
            panels = [strip[16:], panels[0]]
            caption += f"  {result.sequence.studio[c].name}"
        yield _caption(hstack(panels), caption)
        if progress:
            progress(n + 1, len(indices))


def gif_step(frame_count: int) -> int:
    """Every how many frames the GIF shows one (at most MAX_GIF_FRAMES)."""
    return max(1, int(np.ceil(frame_count / MAX_GIF_FRAMES)))


def save_gif(frames: list[np.ndarray], path, step: int, fps: float) -> Path:
    """(H, W, 3) pictures, each ``step`` frames of a take at ``fps`` apart -> a looping GIF."""
    images = [Image.fromarray(f).quantize(colors=64, method=Image.Quantize.MEDIANCUT) for f in frames]
    duration_ms = max(20, int(round(1000.0 * step / fps)))
    path = Path(path)
    images[0].save(path, save_all=True, append_images=images[1:], duration=duration_ms, loop=0, optimize=False)
    return path


def save_video(frames: Iterable[np.ndarray], path, fps: float) -> Path:
    """(H, W, 3) pictures of one size -> an H.264 MP4 at ``fps`` (yuv420p and the index at the
    front, which browsers play from a data URI), padded white to even sizes."""
    import imageio_ffmpeg

    frames = iter(frames)
    first = next(frames)
    H, W = first.shape[:2]
    Hp, Wp = -(-H // VIDEO_BLOCK) * VIDEO_BLOCK, -(-W // VIDEO_BLOCK) * VIDEO_BLOCK
    path = Path(path)
    writer = imageio_ffmpeg.write_frames(str(path), (Wp, Hp), fps=float(fps), codec="libx264", quality=VIDEO_QUALITY,
                                         macro_block_size=VIDEO_BLOCK, output_params=["-movflags", "+faststart"])
    writer.send(None)  # start ffmpeg
    padded = np.full((Hp, Wp, 3), 255, np.uint8)
    for f in itertools.chain([first], frames):
        padded[:H, :W] = f
        writer.send(padded.tobytes())
    writer.close()
    return path


def write_sequence_animations(result: ResultData, painter: ModelPainter, gif, video, camera: int | None = None,
                              progress=None) -> list[Path]:
    """Animated GIF at ``gif`` and MP4 at ``video``: per frame one camera's overlay beside a 3D
    view that follows the actor (``sequence_frames``).

    The video has every fitted frame at their rate (``FittedMotion.rate``: real time); the GIF
    at most MAX_GIF_FRAMES of them (longer takes are subsampled, the frame delay grows to
    match). Returns the written paths.
    """
    F, fps = len(result.motion.frames), result.motion.rate
    step = gif_step(F)
    kept = []

    def keep_gif_frames(frames):  # the video takes every frame as it is drawn; the GIF keeps some
        for i, f in enumerate(frames):
            if i % step == 0:
                kept.append(f)
            yield f

    save_video(keep_gif_frames(sequence_frames(result, painter, range(F), camera, progress)), video, fps)
    return [save_gif(kept, gif, step, fps), Path(video)]


# -------------------------------------------------------------------------------------- plots

def _figure(width=7.0, height=3.0, cols=1):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, cols, figsize=(width, height), dpi=100, squeeze=False)
    return fig, axes[0]


def _png(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def plot_energy(result: ResultData) -> bytes:
    """XOR energy per frame, and per chain before and after its sub-optimization, PNG bytes."""
    fig, (ax, bx) = _figure(11.0, 3.2, cols=2)
    ax.plot(result.motion.frames, result.energies, color="#444", lw=1.5, marker=".")
    ax.set_xlabel("frame")
    ax.set_ylabel("XOR energy (pixels)")
    ax.set_title("Energy after fitting (all cameras)")
    ax.grid(alpha=0.3)
    chains = _chains(result)
    if chains:
        before = [np.mean([r["chains"][c].get("energy_before", np.nan) for r in result.records if c in r.get("chains", {})])
                  for c in chains]
        after = [np.mean([r["chains"][c].get("energy", np.nan) for r in result.records if c in r.get("chains", {})])
                 for c in chains]
        y = np.arange(len(chains))
        bx.barh(y - 0.2, before, height=0.4, color="#bbb", label="before")
        bx.barh(y + 0.2, after, height=0.4, color="#2e86ab", label="after")
        bx.set_yticks(y, chains, fontsize=8)
        bx.invert_yaxis()
        bx.legend(fontsize=7, loc="lower right")
    bx.set_xlabel("energy in the chain's windows, its solves summed (pixels, mean per frame)")
    bx.set_title("Per chain")
    bx.grid(alpha=0.3, axis="x")
    return _png(fig)


def _chains(result: ResultData) -> list[str]:
    return list(dict.fromkeys(c for r in result.records for c in r.get("chains", {})))


def plot_joint_error(result: ResultData) -> bytes | None:
    """Mean and max joint error per frame, mean per joint (mm), PNG bytes; None without truth."""
    err = result.joint_errors_mm()
    if err is None:
        return None
    fig, (ax, bx) = _figure(11.0, 3.2, cols=2)
    f = result.motion.frames
    ax.plot(f, err.mean(axis=1), color="#e4572e", lw=1.5, label="mean")
    ax.plot(f, err.max(axis=1), color="#e4572e", lw=1, ls="--", label="max")
    ax.set_xlabel("frame")
    ax.set_ylabel("joint error (mm)")
    ax.set_title("Joint position error per frame")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    per_joint = np.nanmean(err, axis=0)
    bx.barh(range(len(JOINT_NAMES)), per_joint, color="#2e86ab")
    bx.set_yticks(range(len(JOINT_NAMES)), JOINT_NAMES, fontsize=7)
    bx.invert_yaxis()
    bx.set_xlabel("mean error (mm)")
    bx.set_title("Per joint")
    bx.grid(alpha=0.3, axis="x")
    return _png(fig)


def plot_timing(result: ResultData) -> bytes:
    """Seconds per frame split by chain (stacked), and per chain totals, PNG bytes."""
    chains = _chains(result)
    fig, (ax, bx) = _figure(11.0, 3.2, cols=2)
    f = result.motion.frames
    bottom = np.zeros(len(f))
    colours = ["#2e86ab", "#e4572e", "#f3a712", "#6a994e", "#a23b72", "#7f7f7f", "#3b1f2b"]
    for k, c in enumerate(chains):
        wall = np.array([r.get("chains", {}).get(c, {}).get("wall_seconds", 0.0) for r in result.records])
        ax.bar(f, wall, bottom=bottom, width=1.0, color=colours[k % len(colours)], label=c)
        bottom += wall
    ax.plot(f, result.seconds, color="black", lw=1.2, label="frame total")
    ax.set_xlabel("frame")
    ax.set_ylabel("seconds")
    ax.set_title("Time per frame (chains: wall seconds)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="upper right")
    if chains:
        evals = [np.mean([r.get("chains", {}).get(c, {}).get("evaluations", 0) for r in result.records]) for c in chains]
        cpu = [np.mean([r.get("chains", {}).get(c, {}).get("cpu_seconds", 0.0) for r in result.records]) for c in chains]
        y = np.arange(len(chains))
        bx.barh(y, cpu, color=[colours[k % len(colours)] for k in range(len(chains))])
        bx.set_yticks(y, chains, fontsize=8)
        bx.invert_yaxis()
        bx.set_xlabel("CPU seconds per frame")
        for yy, (c_s, e) in enumerate(zip(cpu, evals)):
            bx.text(c_s, yy, f" {e:.0f} evals", va="center", fontsize=7)
    bx.set_title("Per chain (mean per frame)")
    bx.grid(alpha=0.3, axis="x")
    return _png(fig)


def make_plots(result: ResultData) -> dict[str, bytes]:
    """{file name: PNG bytes} of every plot this result supports."""
    plots = {}
    err = plot_joint_error(result)
    if err is not None:
        plots["joint_error.png"] = err
    plots["energy.png"] = plot_energy(result)
    plots["timing.png"] = plot_timing(result)
    return plots


def png_bytes(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


# --------------------------------------------------------------------------------- all of it

def make_result_pictures(result_dir, sequence_dir=None, frames=None, cameras=None, gif: bool = True,
                         quiet: bool = True, fps: float | None = None) -> list[Path]:
    """Writes RESULT/pictures/: plots, overlay strips and 3D views of chosen frames, and with
    ``gif`` sequence.gif and sequence.mp4 (the slowest pictures: every frame of the take).

    frames: frame numbers (default: spread over the sequence, with the worst one);
    cameras: camera names or indices for the overlays (default: up to 4 spread over the studio).
    Overlays and the GIF's overlay panel need the sequence; without it (then ``fps`` must say
    the frame rate) only plots and views. quiet: no progress bar. Returns the written paths.
    """
    result = load_result(result_dir, sequence_dir, fps)
    final = result.path / PICTURES_DIR
    # built beside and swapped in whole: an earlier set (other frames, another rate) leaves nothing
    with staged_folder(final) as out_dir:
        written = []
        for name, data in make_plots(result).items():
            (out_dir / name).write_bytes(data)
            written.append(out_dir / name)
        painter = ModelPainter(result.motion.model)
        frames = list(frames) if frames else default_frames(result)
        cam_idx = None
        if result.sequence is not None:
            cam_idx = camera_indices(result.sequence.studio, cameras or default_cameras(result.sequence.studio))
        for frame in frames:
            if cam_idx is not None:
                strip, _ = overlay_strip(result, painter, frame, cam_idx)
                path = out_dir / f"overlay_{int(frame):06d}.png"
                Image.fromarray(strip).save(path)
                written.append(path)
            path = out_dir / f"model_{int(frame):06d}.png"
            Image.fromarray(model_views(result, painter, frame)).save(path)
            written.append(path)
        if gif:
            bar = Progress("gif", len(result.motion.frames), enabled=False if quiet else None)
            written += write_sequence_animations(result, painter, out_dir / GIF_NAME, out_dir / VIDEO_NAME,
                                                 camera=cam_idx[0] if cam_idx else None, progress=bar)
    return [final / p.name for p in written]
