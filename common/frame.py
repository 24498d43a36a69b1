"""One frame's input as the fit sees it: silhouettes undistorted into pinhole images, at full
and half resolution, with the energies and windows built from them (``FrameData``)."""
from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import replace
from functools import cached_property

import numpy as np

from common.body import BodyModel, forward_kinematics, rest_params
from common.camera import Camera, Studio, distort_normalized
from common.conic_bits import pack_rows
from common.energy import EnergySetup, Window, camera_weights, counted_bounds, open_image_edges, window_corners
from common.objective import make_energy
from common.packing import clear_padding, downsample_masks, pad_stack
from common.voxels import silhouette_centre

HALF = 0.5  # torso works at half resolution (paper: 160x120 of 320x240)
VOLUME_GRID = 64  # voxels per side for the volume energy's SPOT reconstruction


_UNDISTORT_MAPS: dict = {}
_SPOT_GRIDS: OrderedDict = OrderedDict()  # lookup tables per studio and box, the most recent kept
_SPOT_GRIDS_LOCK = threading.Lock()
SPOT_GRIDS_KEPT = 4  # each about 20 MB (64^3, 8 cameras); an actor crossing the studio needs a few


def undistort_map(cam: Camera) -> np.ndarray:
    """(H, W) flat indices into the distorted image for each pixel of the ideal pinhole image."""
    key = (cam.K.tobytes(), cam.dist.tobytes(), cam.width, cam.height)
    if key not in _UNDISTORT_MAPS:
        v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
        fx, s_, cx, fy, cy = cam.K[0, 0], cam.K[0, 1], cam.K[0, 2], cam.K[1, 1], cam.K[1, 2]
        y = (v - cy) / fy
        x = (u - cx - s_ * y) / fx
        xd, yd = distort_normalized(x, y, cam.dist)
        ud = np.rint(fx * xd + s_ * yd + cx).astype(np.int64)
        vd = np.rint(fy * yd + cy).astype(np.int64)
        inside = (ud >= 0) & (ud < cam.width) & (vd >= 0) & (vd < cam.height)
        _UNDISTORT_MAPS[key] = np.where(inside, vd * cam.width + ud, -1)
    return _UNDISTORT_MAPS[key]


def undistort_masks(studio: Studio, masks: np.ndarray) -> tuple[Studio, np.ndarray]:
    """Silhouettes resampled into ideal pinhole images (same K, no distortion), and that studio.

    masks: (K, H, W) bool, the padded stack (``packing.pad_stack``) -> the same shape.
    Fitting works in undistorted images so that every energy backend projects with plain
    pinhole cameras and agrees; a mask is resampled once per frame (nearest pixel).
    """
    if not any(c.has_distortion for c in studio):
        return studio, masks
    cams, out = [], []
    for cam, mask in zip(studio, masks):
        mask = mask[:cam.height, :cam.width]
        if cam.has_distortion:
            idx = undistort_map(cam)
            mask = np.where(idx >= 0, mask.reshape(-1)[np.maximum(idx, 0)], False)
            cam = replace(cam, dist=np.zeros_like(cam.dist))
        cams.append(cam)
        out.append(mask)
    return Studio(tuple(cams), studio.source), pad_stack(out)


def recorded_pixels(studio: Studio, flags: np.ndarray) -> np.ndarray:
    """(K, H, W) bool flags over the ideal pinhole images (``undistort_masks``'s) -> the same
    over the images as recorded: a recorded pixel is flagged where an ideal pixel sampled from it
    is, so that masks cleared there and undistorted again are clear at every flagged pixel."""
    flags = np.asarray(flags, dtype=bool)
    out = flags.copy()
    for k, cam in enumerate(studio):
        if cam.has_distortion:
            idx = undistort_map(cam)
            plane = np.zeros(cam.height * cam.width, dtype=bool)
            plane[idx[flags[k, :cam.height, :cam.width] & (idx >= 0)]] = True
            out[k] = False
            out[k, :cam.height, :cam.width] = plane.reshape(cam.height, cam.width)
    return out


def spot_grid(studio: Studio, masks: np.ndarray, grid: int):
    """SPOT lookup tables for a box around the actor; built once per studio and box."""
    from common.voxels import SpotGrid, actor_bounds

    bounds = actor_bounds(studio, masks)
    key = (grid, bounds.tobytes(), tuple((c.name, c.K.tobytes(), c.R.tobytes(), c.t.tobytes()) for c in studio))
    with _SPOT_GRIDS_LOCK:  # a fit's threads share the tables
        if key not in _SPOT_GRIDS:
            _SPOT_GRIDS[key] = SpotGrid.build(studio, grid=grid, q=2, bounds=bounds)
            while len(_SPOT_GRIDS) > SPOT_GRIDS_KEPT:
                _SPOT_GRIDS.popitem(last=False)
        _SPOT_GRIDS.move_to_end(key)
        return _SPOT_GRIDS[key]


class FrameData:
    """One frame's input silhouettes (undistorted) at full and half resolution, and its studio.

    masks: (K, H, W) bool, camera k's silhouette at [:h_k, :w_k] with (w_k, h_k) its image
    size and H, W the largest (cameras of one size: the plain stack; of different sizes: the
    padded stack of ``packing.pad_stack``). Pixels beyond a camera's image are cleared here,
    once per frame, and no energy counts them.
    """

    def __init__(self, model: BodyModel, studio: Studio, masks: np.ndarray):
        self.model = model
        masks = np.asarray(masks, dtype=bool)
        if masks.ndim != 3 or masks.shape[0] != len(studio):
            raise ValueError(f"expected (K, H, W) silhouettes of {len(studio)} cameras, got shape {masks.shape}")
        H, W = studio.padded_shape
        if masks.shape[1:] != (H, W):
            raise ValueError(f"silhouettes are {masks.shape[2]}x{masks.shape[1]}, the calibration's largest "
                             f"camera width and height {W}x{H}")
        masks = clear_padding(masks, studio.sizes)
        self.original_studio = studio
        studio, masks = undistort_masks(studio, masks)
        self.studio = studio
        self.masks = masks
        self._whole_image_energies: dict = {}  # half -> energy (see whole_image_energy)

    @cached_property
    def half_studio(self) -> Studio:
        """The studio at half resolution (image sizes rounded down, as the masks are)."""
        return Studio(tuple(replace(c.scaled(HALF), width=c.width // 2, height=c.height // 2) for c in self.studio))

    @cached_property
    def half_masks(self) -> np.ndarray:
        """(K, H // 2, W // 2) bool, camera k's at [:h_k // 2, :w_k // 2] (cleared beyond)."""
        return clear_padding(downsample_masks(self.masks, 2), self.half_studio.sizes)

    @cached_property
    def packed_masks(self) -> np.ndarray:
        """``masks`` as row bits (``conic_bits.pack_rows``): what energies' windows are cut from."""
        return pack_rows(self.masks)

    @cached_property
    def half_packed_masks(self) -> np.ndarray:
        """``half_masks`` as row bits."""
        return pack_rows(self.half_masks)

    @cached_property
    def counted_bounds(self) -> np.ndarray:
        """(K, 4) int64: the pixels each camera's windows count (``energy.counted_bounds``), not
        those past the image edges its silhouette touches (``energy.open_image_edges``): a person
        partly out of a camera's view is fitted from what that camera does see, not pushed back
        into its image. Once per frame: a fit builds thousands of windows' energies."""
        return counted_bounds(self.studio, open_image_edges(self.masks, self.studio.sizes))

    @cached_property
    def camera_weights(self) -> np.ndarray | None:
        """(K,) float64 or None: what a pixel of each camera is worth in every energy of this
        frame, at either resolution (``energy.camera_weights`` about the silhouettes' centre,
        ``voxels.silhouette_centre``): one weight per frame, so that every fit of a frame,
        on the server or a client, is measured alike."""
        return camera_weights(self.studio, silhouette_centre(self.studio, self.masks))

    @cached_property
    def surface_points(self) -> np.ndarray:
        """(n, 3) centres of the frame's SPOT surface voxels (for the volume energy)."""
        return spot_grid(self.studio, self.masks, VOLUME_GRID).reconstruct(self.masks).surface_points()

    def full_setup(self, params: np.ndarray, half: bool = False) -> EnergySetup:
        studio = self.half_studio if half else self.studio
        masks = self.half_masks if half else self.masks
        windows = tuple(Window(0, 0, c.width, c.height) for c in studio)
        # cameras of one size: their images are windows of one size, cut from the row bits
        packed = (self.half_packed_masks if half else self.packed_masks) if len(set(studio.sizes)) == 1 else None
        return EnergySetup(studio, windows, masks, tuple(range(16)), np.asarray(params), prerender=False,
                           packed=packed, weights=self.camera_weights)

    def whole_image_energy(self, half: bool = False):
        """The ``cpu`` energy of the whole images with every segment moving. Nothing is
        pre-rendered, so it does not depend on a pose: built once per frame and resolution
        (its bit masks of 8 full images cost more than a few evaluations)."""
        if half not in self._whole_image_energies:
            setup = self.full_setup(rest_params(self.model), half=half)
            self._whole_image_energies[half] = make_energy("cpu", self.model, setup)
        return self._whole_image_energies[half]

    def energy(self, backend: str, setup: EnergySetup):
        """The ``backend`` energy of ``setup`` for this frame (the volume energy is over its voxels)."""
        if backend == "volume":  # one energy over the whole body's voxels: no windows
            setup = replace(setup, volume_points=self.surface_points)
        return make_energy(backend, self.model, setup)

    def window_setup(self, params: np.ndarray, segments, size: int, prerender: bool) -> EnergySetup:
        """Windows of ``size`` centred on the projected centre of ``segments`` at ``params``."""
        pose = forward_kinematics(self.model, params)
        R, o = pose.rotations[0, list(segments)], pose.origins[0, list(segments)]
        # the mean of the parts' ellipsoid centres: the middle of the bones, not the joints
        centre = (np.einsum("sij,sj->si", R, self.model.ellipsoid_centres[list(segments)]) + o).mean(axis=0)
        corners = window_corners(*self._pinholes, centre, size)
        windows = tuple(Window(int(x0), int(y0), size, size) for x0, y0 in corners)
        return EnergySetup(self.studio, windows, None, tuple(segments), np.asarray(params), prerender=prerender,
                           packed=self.packed_masks, bounds=self.counted_bounds, weights=self.camera_weights)

    @cached_property
    def _pinholes(self) -> tuple:
        """The undistorted cameras as arrays for ``window_corners``: R (K, 3, 3), t (K, 3),
        K (K, 3, 3)."""
        cams = self.studio.cameras
        return (np.stack([c.R for c in cams]).astype(np.float64), np.stack([c.t for c in cams]).astype(np.float64),
                np.stack([c.K for c in cams]).astype(np.float64))
